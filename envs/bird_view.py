"""The bird-view frame: camera, road, cones, cars and dials drawn with matplotlib into an RGB array.

The camera follows the ego car (docs/carenv-single-agent.md §10): the CoG sits at 80 % of the image height,
the heading points up the screen, and one metre is ``height / 57.5`` pixels. The original draws into
a y-down raster without flipping, which mirrors the picture (the car's left appears on the screen's
right). We draw the physically correct view by default; ``mirrored=True`` reproduces the original.

Rendering runs on the host with numpy inputs; it never enters jitted code. Everything is drawn in
*view coordinates* (metres, x to the screen's right, y up the screen), so an ``overlay`` callback
can add its own artists (e.g. explanation boxes) with the same ``to_view`` transform.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PatchCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon, Rectangle

from envs.track import CONE_RADIUS
from envs.vehicle_state import VEHICLE_HALF_LENGTH, VEHICLE_HALF_WIDTH

BACKGROUND = (0.8, 0.8, 0.8)
ROAD_GREY = (0.6, 0.6, 0.6)
CENTRE_LINE_GREY = (0.8, 0.8, 0.8)
BLUE_CONE = (56 / 255, 103 / 255, 214 / 255)
YELLOW_CONE = (254 / 255, 211 / 255, 48 / 255)
CAR_BODY = (200 / 255, 211 / 255, 23 / 255)
GLASS = (0.2, 0.4, 0.7)
WHEEL_GREY = (0.2, 0.2, 0.2)
BUMPER_GREY = (0.45, 0.45, 0.45)

ROAD_HALF_WIDTH = 4.3  # the drawn road: centre line buffered by 4.3 m (not the 4.0 m "on track" limit)
CAR_LENGTH, CAR_WIDTH = 2 * VEHICLE_HALF_LENGTH, 2 * VEHICLE_HALF_WIDTH
AXLE_OFFSET = 1.2
WHEEL_LENGTH, WHEEL_WIDTH = 0.5, 0.3
METRES_VISIBLE_VERTICALLY = 57.5
EGO_HEIGHT_FRACTION = 0.8

Overlay = Callable[["object", Callable[[np.ndarray], np.ndarray]], None]


@dataclass(frozen=True)
class Pose:
    """A vehicle pose and the inputs the picture shows (steering angle, pedals, speed)."""

    x: float
    y: float
    theta: float
    steer: float = 0.0
    speed: float = 0.0
    throttle: float = 0.0
    brake: float = 0.0


def _world_to_view(pose: Pose, mirrored: bool) -> Callable[[np.ndarray], np.ndarray]:
    """World points (..., 2) to view metres: body frame B(θ)(P − p), then screen axes."""
    cos_t, sin_t = np.cos(pose.theta), np.sin(pose.theta)
    origin = np.array([pose.x, pose.y])

    def to_view(points: np.ndarray) -> np.ndarray:
        delta = np.asarray(points, dtype=np.float64) - origin
        forward = cos_t * delta[..., 0] + sin_t * delta[..., 1]
        left = -sin_t * delta[..., 0] + cos_t * delta[..., 1]
        screen_x = left if mirrored else -left
        return np.stack([screen_x, forward], axis=-1)

    return to_view


def _segment_quads(polyline: np.ndarray, half_width: float) -> np.ndarray:
    """One rectangle per segment of a closed polyline; with discs at the vertices, the union is the buffer."""
    start, end = polyline, np.roll(polyline, -1, axis=0)
    direction = end - start
    length = np.linalg.norm(direction, axis=-1, keepdims=True)
    normal = np.where(
        length > 1e-9, np.stack([-direction[:, 1], direction[:, 0]], -1) / np.maximum(length, 1e-9), 0
    )
    offset = half_width * normal
    quads = np.stack([start + offset, end + offset, end - offset, start - offset], axis=1)
    return quads[length[:, 0] > 1e-9]


def rotated_rect(centre: np.ndarray, length: float, width: float, angle: float) -> np.ndarray:
    """Corners (4, 2) of a rectangle in a frame where ``angle`` turns the rectangle's long axis."""
    c, s = np.cos(angle), np.sin(angle)
    half = np.array([[length, width], [length, -width], [-length, -width], [-length, width]]) / 2
    return centre + half @ np.array([[c, s], [-s, c]])


def _draw_vehicle(ax, pose: Pose, mirrored: bool) -> None:
    """The ego car in its own frame: it always points up the screen, centred on the origin."""
    side = 1.0 if mirrored else -1.0  # view x of a point at body y = +1 (left)

    def body(points: np.ndarray) -> np.ndarray:  # body (forward, left) to view
        points = np.asarray(points, dtype=np.float64)
        return np.stack([side * points[..., 1], points[..., 0]], axis=-1)

    outline = rotated_rect(np.zeros(2), CAR_LENGTH, CAR_WIDTH, 0.0)
    for wheel_x in (AXLE_OFFSET, -AXLE_OFFSET):
        for wheel_y in (CAR_WIDTH / 2 - 0.1 - WHEEL_WIDTH / 2, -(CAR_WIDTH / 2 - 0.1 - WHEEL_WIDTH / 2)):
            angle = pose.steer if wheel_x > 0 else 0.0
            corners = rotated_rect(np.array([wheel_x, wheel_y]), WHEEL_LENGTH, WHEEL_WIDTH, angle)
            ax.add_patch(Polygon(body(corners), closed=True, facecolor=WHEEL_GREY, zorder=7))
    ax.add_patch(Polygon(body(outline), closed=True, facecolor=CAR_BODY, edgecolor="black", lw=0.8, zorder=5))
    for bumper_x in (CAR_LENGTH / 2 - 0.1, -CAR_LENGTH / 2 + 0.1):
        bumper = rotated_rect(np.array([bumper_x, 0.0]), 0.2, CAR_WIDTH, 0.0)
        ax.add_patch(Polygon(body(bumper), closed=True, facecolor=BUMPER_GREY, zorder=6))
    for glass_x, glass_len in ((0.55, 0.55), (-1.05, 0.35)):
        glass = rotated_rect(np.array([glass_x, 0.0]), glass_len, CAR_WIDTH - 0.3, 0.0)
        ax.add_patch(Polygon(body(glass), closed=True, facecolor=GLASS, zorder=6))
    brake_colour = (1.0, 0.0, 0.0) if pose.brake > 0.05 else (0.45, 0.0, 0.0)
    for light_y in (CAR_WIDTH / 2 - 0.2, -(CAR_WIDTH / 2 - 0.2)):
        light = rotated_rect(np.array([-CAR_LENGTH / 2 + 0.05, light_y]), 0.1, 0.3, 0.0)
        ax.add_patch(Polygon(body(light), closed=True, facecolor=brake_colour, zorder=7))


def _draw_hud(ax, pose: Pose) -> None:
    """Speedometer (0–100 km/h) at the bottom right, brake and throttle bars to its left.

    Drawn in view metres (the axes have equal aspect) so the dial stays round at any frame size.
    """
    x_max, (y_min, y_max) = ax.get_xlim()[1], ax.get_ylim()
    radius = 0.12 * (y_max - y_min)
    margin = 0.02 * (y_max - y_min)
    centre = np.array([x_max - margin - radius, y_min + margin + radius])
    ax.add_patch(Circle(tuple(centre), radius, facecolor=(0.15, 0.15, 0.15), alpha=0.85, zorder=20))
    kmh = float(np.clip(abs(pose.speed) * 3.6, 0.0, 100.0))
    angle = np.deg2rad(225.0 - 270.0 * kmh / 100.0)
    tip = centre + 0.85 * radius * np.array([np.cos(angle), np.sin(angle)])
    ax.plot([centre[0], tip[0]], [centre[1], tip[1]], color="red", lw=2, zorder=21)
    ax.text(
        centre[0],
        centre[1] - 0.5 * radius,
        f"{kmh:.0f} km/h",
        color="white",
        ha="center",
        va="center",
        fontsize=9,
        zorder=21,
    )
    bar_width, bar_height = 0.15 * radius, 2 * radius
    for i, (value, colour) in enumerate(((pose.brake, "red"), (pose.throttle, "green"))):
        left = centre[0] - radius - margin - (2 - i) * 1.5 * bar_width
        bottom = y_min + margin
        ax.add_patch(
            Rectangle(
                (left, bottom), bar_width, bar_height, facecolor=(0.15, 0.15, 0.15), alpha=0.85, zorder=20
            )
        )
        filled = bar_height * float(np.clip(value, 0.0, 1.0))
        ax.add_patch(Rectangle((left, bottom), bar_width, filled, facecolor=colour, zorder=21))


def render_frame(
    pose: Pose,
    centerline: np.ndarray | None = None,
    cone_xy: np.ndarray | None = None,
    cone_type: np.ndarray | None = None,
    points: np.ndarray | None = None,
    *,
    width: int = 1280,
    height: int = 720,
    mirrored: bool = False,
    hud: bool = True,
    overlay: Overlay | None = None,
    extra_vehicles: Sequence[Pose] = (),
    road_polygons: Sequence[np.ndarray] = (),
) -> np.ndarray:
    """Draw one bird-view frame and return it as a ``(height, width, 3)`` uint8 array.

    Args:
      pose: the ego pose the camera follows (world frame).
      centerline: ``(N, 2)`` closed centre line (only the real points, no padding); drawn as the road.
      cone_xy, cone_type: ``(M, 2)`` positions and types (1 blue/right, 2 yellow/left) of the cones
        still on the track; hit cones must already be left out.
      points: ``(P, 2)`` world points drawn as small discs (e.g. the tracking look-ahead).
      mirrored: reproduce the original's mirrored picture (left appears on the right).
      overlay: ``overlay(ax, to_view)`` draws extra artists; ``to_view`` maps world points to view metres.
      extra_vehicles: other cars to draw (multi-agent scenes).
      road_polygons: world-frame polygons to fill as road (scenes whose roads are not a buffered loop).
    """
    if width < 16 or height < 16:
        raise ValueError(f"frame size must be at least 16x16 pixels, got {width}x{height}")
    to_view = _world_to_view(pose, mirrored)
    metres_per_px = METRES_VISIBLE_VERTICALLY / height
    half_w = width / 2 * metres_per_px

    figure = Figure(figsize=(width / 100, height / 100), dpi=100, facecolor=BACKGROUND)
    canvas = FigureCanvasAgg(figure)
    ax = figure.add_axes((0, 0, 1, 1))
    ax.set_facecolor(BACKGROUND)
    ax.set_xlim(-half_w, half_w)
    ax.set_ylim(
        -(1 - EGO_HEIGHT_FRACTION) * METRES_VISIBLE_VERTICALLY,
        EGO_HEIGHT_FRACTION * METRES_VISIBLE_VERTICALLY,
    )
    ax.set_axis_off()

    for polygon in road_polygons:
        ax.add_patch(Polygon(to_view(polygon), closed=True, facecolor=ROAD_GREY, edgecolor="black", lw=0.8))
    if centerline is not None:
        centerline = np.asarray(centerline, dtype=np.float64)
        quads = to_view(_segment_quads(centerline, ROAD_HALF_WIDTH))
        ax.add_collection(PolyCollection(quads, facecolors=ROAD_GREY, edgecolors="none", zorder=1))
        joints = [Circle(tuple(p), ROAD_HALF_WIDTH) for p in to_view(centerline)]
        ax.add_collection(PatchCollection(joints, facecolors=ROAD_GREY, edgecolors="none", zorder=1))
        closed = to_view(np.concatenate([centerline, centerline[:1]]))
        ax.plot(closed[:, 0], closed[:, 1], color=CENTRE_LINE_GREY, lw=2, zorder=2)

    if cone_xy is not None and len(cone_xy):
        cone_type = np.ones(len(cone_xy), dtype=int) if cone_type is None else np.asarray(cone_type)
        colours = [BLUE_CONE if t == 1 else YELLOW_CONE for t in cone_type]
        centres = to_view(np.asarray(cone_xy))
        side = 2.4 * CONE_RADIUS
        squares = [Rectangle((cx - side / 2, cy - side / 2), side, side) for cx, cy in centres]
        circles = [Circle((cx, cy), CONE_RADIUS) for cx, cy in centres]
        tips = [Circle((cx, cy), 0.15 * CONE_RADIUS) for cx, cy in centres]
        for patches in (squares, circles, tips):
            ax.add_collection(
                PatchCollection(patches, facecolors=colours, edgecolors="black", lw=0.5, zorder=3)
            )

    if points is not None and len(points):
        discs = [Circle(tuple(p), 0.2) for p in to_view(np.asarray(points))]
        ax.add_collection(PatchCollection(discs, facecolors=(0.9, 0.1, 0.1), edgecolors="none", zorder=3))

    for other in extra_vehicles:
        corners = to_view(rotated_rect(np.array([other.x, other.y]), CAR_LENGTH, CAR_WIDTH, other.theta))
        ax.add_patch(
            Polygon(corners, closed=True, facecolor=(0.3, 0.5, 0.9), edgecolor="black", lw=0.8, zorder=5)
        )

    _draw_vehicle(ax, pose, mirrored)
    if overlay is not None:
        overlay(ax, to_view)
    if hud:
        _draw_hud(ax, pose)

    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
