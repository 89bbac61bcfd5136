"""Rendering of the scenarios: frames straight from an env state, PNG files, GIF/MP4 episodes.

Each frame is a bird view (``envs.bird_view``: the camera follows a car, docs/carenv-single-agent.md
§10; ``Pose`` and ``render_frame`` are re-exported here). Rendering runs on the host with numpy
inputs; it never enters jitted code.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np
from matplotlib.animation import FFMpegWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Polygon
from PIL import Image

from envs import intersection_geometry as geo
from envs.bird_view import (
    BACKGROUND,
    CAR_LENGTH,
    CAR_WIDTH,
    ROAD_GREY,
    Pose,
    render_frame,
    rotated_rect,
)

__all__ = [  # Pose and render_frame are re-exported: callers import them from here
    "Pose",
    "render_frame",
    "render_intersection_episode",
    "render_intersection_state",
    "render_racing_episode",
    "render_racing_state",
    "save_png",
    "save_video",
]


def save_png(frame: np.ndarray, path: str | Path) -> Path:
    """Write one ``(H, W, 3)`` uint8 frame as PNG."""
    path = Path(path)
    Image.fromarray(np.asarray(frame, dtype=np.uint8)).save(path)
    return path


def save_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write frames as an animated GIF (Pillow) or MP4 (ffmpeg), chosen by the file suffix.

    The default 10 frames per second plays an episode in real time (dt = 0.1 s).
    """
    path = Path(path)
    if not frames:
        raise ValueError("save_video needs at least one frame")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    suffix = path.suffix.lower()
    if suffix == ".gif":
        images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
        return path
    if suffix == ".mp4":
        if shutil.which("ffmpeg") is None:
            raise RuntimeError(
                "writing MP4 needs the ffmpeg program on PATH; install it or save a .gif instead"
            )
        height, width = np.asarray(frames[0]).shape[:2]
        figure = Figure(figsize=(width / 100, height / 100), dpi=100)
        FigureCanvasAgg(figure)
        ax = figure.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        image = ax.imshow(frames[0])
        writer = FFMpegWriter(fps=fps)
        with writer.saving(figure, str(path), dpi=100):
            for frame in frames:
                image.set_data(frame)
                writer.grab_frame()
        return path
    raise ValueError(f"unsupported video format {suffix!r}: use .gif or .mp4")


# ------------------------------------------------------------------------------------------------
# Racing scenarios (Country Road, Tracking): frames straight from an env state
# ------------------------------------------------------------------------------------------------


def _racing_track(state, params):
    """The episode's track as numpy: carried in the state, or looked up in the params' bank."""
    if getattr(state, "track", None) is not None:
        return _to_numpy(state.track)
    index = int(np.asarray(state.track_index))
    return _to_numpy(params.tracks, index)


def _to_numpy(tree, index: int | None = None):
    """A pytree of arrays as numpy, optionally taking one entry of the leading axis."""
    return jax.tree.map(lambda x: np.asarray(x if index is None else x[index]), tree)


def render_racing_state(
    state,
    params,
    control: Sequence[float] | None = None,
    *,
    show_cones: bool = True,
    points: np.ndarray | None = None,
    **frame_options,
) -> np.ndarray:
    """One frame of a Country Road / Tracking episode from its (unbatched) ``RacingState``.

    ``control`` is the mapped ``(steer, throttle, brake)`` of the last step, for the pedal bars and
    brake lights (``envs.actions.continuous_to_control`` / ``discrete_to_control`` give it). Hit cones
    are gone; Tracking has no cones. Other keyword arguments go to :func:`render_frame`.
    """
    track = _racing_track(state, params)
    vehicle = _to_numpy(state.vehicle)
    speed = np.cos(vehicle.theta) * vehicle.vx + np.sin(vehicle.theta) * vehicle.vy
    throttle, brake = (0.0, 0.0) if control is None else (float(control[1]), float(control[2]))
    pose = Pose(
        float(vehicle.x),
        float(vehicle.y),
        float(vehicle.theta),
        float(vehicle.steer),
        float(speed),
        throttle,
        brake,
    )
    cone_xy = cone_type = None
    if show_cones:
        alive = np.asarray(state.cone_alive, dtype=bool)
        cone_xy, cone_type = track.cone_xy[alive], track.cone_type[alive]
    centerline = track.centerline[: int(track.num_points)]
    return render_frame(pose, centerline, cone_xy, cone_type, points, **frame_options)


def render_racing_episode(states, params, controls=None, **frame_options) -> list[np.ndarray]:
    """Frames for a stacked sequence of states (leading time axis, e.g. the output of ``lax.scan``)."""
    states = _to_numpy(states)
    length = int(np.asarray(states.step_count).shape[0])
    frames = []
    for t in range(length):
        state_t = _to_numpy(states, t)
        control = None if controls is None else np.asarray(controls)[t]
        frames.append(render_racing_state(state_t, params, control, **frame_options))
    return frames


# ------------------------------------------------------------------------------------------------
# Intersection (multi-agent): ego camera on one slot, or a fixed top view of the whole crossing
# ------------------------------------------------------------------------------------------------

ROUTE_COLOUR = (1.0, 1.0, 1.0)
OTHER_CAR = (0.3, 0.5, 0.9)
TOP_VIEW_HALF_SIZE = 55.0  # metres around the centre shown by the top view


def _intersection_poses(state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vehicle = _to_numpy(state.vehicle)
    poses = np.stack([vehicle.x, vehicle.y, vehicle.theta], axis=-1).astype(np.float64)
    return poses, np.asarray(state.alive, dtype=bool), np.asarray(state.route)


def _route_polylines(routes: np.ndarray) -> list[np.ndarray]:
    return [np.asarray(geo.ROUTE_XY[int(r)], dtype=np.float64) for r in routes]


def _draw_top_view(poses, alive, routes, show_routes: bool, width: int, height: int) -> np.ndarray:
    """All alive cars over the whole road, north (negative y) at the top as in the original picture."""
    figure = Figure(figsize=(width / 100, height / 100), dpi=100, facecolor=BACKGROUND)
    canvas = FigureCanvasAgg(figure)
    ax = figure.add_axes((0, 0, 1, 1))
    ax.set_facecolor(BACKGROUND)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlim(-TOP_VIEW_HALF_SIZE, TOP_VIEW_HALF_SIZE)
    ax.set_ylim(TOP_VIEW_HALF_SIZE, -TOP_VIEW_HALF_SIZE)  # y down, like the original renderer
    ax.set_axis_off()
    road = np.asarray(geo.ROAD_POLYGON, dtype=np.float64)
    ax.add_patch(Polygon(road, closed=True, facecolor=ROAD_GREY, edgecolor="black", lw=0.8, zorder=1))
    if show_routes:
        for line in _route_polylines(routes[alive]):
            ax.plot(line[:, 0], line[:, 1], color=ROUTE_COLOUR, lw=1.0, zorder=2)
    for x, y, theta in poses[alive]:
        corners = rotated_rect(np.array([x, y]), CAR_LENGTH, CAR_WIDTH, theta)
        ax.add_patch(Polygon(corners, closed=True, facecolor=OTHER_CAR, edgecolor="black", lw=0.8, zorder=5))
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def render_intersection_state(
    state,
    params,
    ego_slot: int | None = None,
    controls: np.ndarray | None = None,
    show_routes: bool = True,
    **frame_options,
) -> np.ndarray:
    """One frame of an (unbatched) ``IntersectionState``.

    With ``ego_slot`` the camera follows that slot's car (drawn as the detailed ego car, the other
    alive cars as blue boxes, its route in white when ``show_routes``); ``controls`` (8, 3) are the
    mapped controls of the last step (pedal bars and brake lights of the ego). Without ``ego_slot``,
    or when that slot is empty, a fixed top view of the whole crossing shows every alive car and
    (``show_routes``) their routes. Other keyword arguments go to :func:`render_frame`; the top view
    uses only ``width`` and ``height``.
    """
    del params  # the geometry is fixed; kept for a uniform signature
    poses, alive, routes = _intersection_poses(state)
    width = int(frame_options.get("width", 1280))
    height = int(frame_options.get("height", 720))
    if ego_slot is not None and not 0 <= int(ego_slot) < len(alive):
        raise ValueError(f"ego_slot must be in 0..{len(alive) - 1} or None, got {ego_slot}")
    if ego_slot is None or not alive[int(ego_slot)]:
        if width < 16 or height < 16:
            raise ValueError(f"frame size must be at least 16x16 pixels, got {width}x{height}")
        return _draw_top_view(poses, alive, routes, show_routes, width, height)

    ego = int(ego_slot)
    vehicle = _to_numpy(state.vehicle)
    x, y, theta = poses[ego]
    speed = np.cos(theta) * vehicle.vx[ego] + np.sin(theta) * vehicle.vy[ego]
    control = None if controls is None else np.asarray(controls)[ego]
    throttle, brake = (0.0, 0.0) if control is None else (float(control[1]), float(control[2]))
    pose = Pose(float(x), float(y), float(theta), float(vehicle.steer[ego]), float(speed), throttle, brake)
    others = [Pose(*map(float, poses[i])) for i in range(len(alive)) if alive[i] and i != ego]
    user_overlay = frame_options.pop("overlay", None)
    route_line = _route_polylines(routes[ego : ego + 1])[0] if show_routes else None

    def overlay(ax, to_view):
        if route_line is not None:
            line = to_view(route_line)
            ax.plot(line[:, 0], line[:, 1], color=ROUTE_COLOUR, lw=1.5, zorder=2)
        if user_overlay is not None:
            user_overlay(ax, to_view)

    road = np.asarray(geo.ROAD_POLYGON, dtype=np.float64)
    return render_frame(pose, extra_vehicles=others, road_polygons=[road], overlay=overlay, **frame_options)


def render_intersection_episode(
    states, params, ego_slot: int | None = None, controls=None, **frame_options
) -> list[np.ndarray]:
    """Frames for stacked states (leading time axis); ``controls`` (T, 8, 3) optional."""
    states = _to_numpy(states)
    length = int(np.asarray(states.step).shape[0])
    frames = []
    for t in range(length):
        control = None if controls is None else np.asarray(controls)[t]
        frames.append(
            render_intersection_state(_to_numpy(states, t), params, ego_slot, control, **frame_options)
        )
    return frames
