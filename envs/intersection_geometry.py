"""Static geometry of the multi-agent intersection (docs/carenv-intersection.md §2, §5.3, §5.4).

Everything here is pure and free of environment state:

* host tables (numpy float64, built once at import): the 12 route polylines made by the turtle of
  §2.1, their cumulative arc lengths, the spawn areas and poses (§2.3) and the road outline (§2.2);
* jittable, vmap-friendly functions on those tables: projection onto a route, points along a route,
  vehicle rectangles, road containment and rectangle overlap tests.

Frame: ordinary maths axes; "N" is at negative y (§0). Route index r = 3 * approach + kind with
approaches (N, S, W, E) and kinds (straight, right, left).

Exactness: turtle headings are multiples of pi/2, so straight moves use exact unit vectors and only the
arc points carry rounding (order 1e-15). Every jittable function computes in the floating dtype of its
inputs (float32 by default, float64 under `jax.enable_x64`); boundary contact is decided with a small
tolerance (`boundary_tolerance`) that always resolves towards "touching", as the original's exact
predicates on the same coordinates would.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from envs.vehicle_state import VEHICLE_HALF_LENGTH, VEHICLE_HALF_WIDTH

# ------------------------------------------------------------------------------------------------
# Constants (§1)
# ------------------------------------------------------------------------------------------------

LANE_SPACING = 3.0
LANE_LENGTH = 50.0
TURN_RADIUS = 4.5
ROAD_HALF_WIDTH = 2.5
SPAWN_OFFSET = 5.0
SOFT_PAD_LONG = 0.5
SOFT_PAD_LAT = 0.25
SOFT_HALF_LENGTH = VEHICLE_HALF_LENGTH + SOFT_PAD_LONG  # 2.405: soft-collision rectangle (§5.4)
SOFT_HALF_WIDTH = VEHICLE_HALF_WIDTH + SOFT_PAD_LAT  # 0.99
MAX_ROUTE_VERTICES = 10
NUM_ROUTES = 12
NUM_APPROACHES = 4
APPROACHES = ("N", "S", "W", "E")
ROUTE_KINDS = ("straight", "right", "left")
ARC_CHORDS = 7  # chords per quarter circle (8 points incl. the start)
SPAWN_AREA_ARCLENGTH = (1.5, 8.5)  # spawn area along the lane (§2.3)
SPAWN_AREA_HALF_LATERAL = 1.0
ROAD_END = LANE_LENGTH + LANE_SPACING / 2  # 51.5: every route starts/ends this far from the centre
ARM_HALF_WIDTH = LANE_SPACING / 2 + ROAD_HALF_WIDTH  # 4.0: half width of each arm of the road cross

# ------------------------------------------------------------------------------------------------
# Routes (§2.1)
# ------------------------------------------------------------------------------------------------

# Heading k * pi/2 as an exact unit vector, so straight moves introduce no rounding.
_QUARTER_DIRECTIONS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])

# Start point and start heading (in quarter turns) of each approach, in APPROACHES order.
_APPROACH_STARTS = (
    ((-LANE_SPACING / 2, -ROAD_END), 1),  # N: heading +pi/2
    ((LANE_SPACING / 2, ROAD_END), 3),  # S: heading -pi/2
    ((-ROAD_END, LANE_SPACING / 2), 0),  # W: heading 0
    ((ROAD_END, -LANE_SPACING / 2), 2),  # E: heading pi
)

_ROUTE_MOVES = {
    "straight": (("forward", LANE_SPACING + 2 * LANE_LENGTH),),
    "right": (
        ("forward", LANE_LENGTH - TURN_RADIUS),
        ("turn", TURN_RADIUS),
        ("forward", LANE_LENGTH - TURN_RADIUS),
    ),
    "left": (
        ("forward", LANE_LENGTH + LANE_SPACING - TURN_RADIUS),
        ("turn", -TURN_RADIUS),
        ("forward", LANE_LENGTH + LANE_SPACING - TURN_RADIUS),
    ),
}


def _turtle(start, quarter: int, moves) -> np.ndarray:
    """Polyline of the turtle of §2.1: forward(d) appends one point; turn(r) sweeps a quarter circle
    about the centre |r| to the left (r > 0, maths-positive sweep) or right (r < 0) and appends 7 points."""
    points = [np.asarray(start, dtype=np.float64)]
    for move, amount in moves:
        cursor = points[-1]
        if move == "forward":
            points.append(cursor + amount * _QUARTER_DIRECTIONS[quarter % 4])
            continue
        side = 1 if amount > 0 else -1
        centre = cursor + amount * _QUARTER_DIRECTIONS[(quarter + 1) % 4]  # signed: left for r > 0
        rx, ry = cursor - centre
        for j in range(1, ARC_CHORDS):
            angle = side * j * (math.pi / 2) / ARC_CHORDS
            c, s = math.cos(angle), math.sin(angle)
            points.append(centre + np.array([c * rx - s * ry, s * rx + c * ry]))
        points.append(centre + side * np.array([-ry, rx]))  # the quarter rotation itself, exactly
        quarter += side
    return np.stack(points)


def _pad_collinear(points: np.ndarray, count: int) -> np.ndarray:
    """Subdivide a 2-vertex polyline evenly into `count` vertices (same line, same projections)."""
    if len(points) == count:
        return points
    if len(points) != 2:
        raise ValueError(f"only straight (2-vertex) routes can be padded, got {len(points)} vertices")
    fraction = np.linspace(0.0, 1.0, count)[:, None]
    padded = points[0] + fraction * (points[1] - points[0])
    padded[-1] = points[1]
    return padded


def _arm_name(point) -> str:
    """Compass name of the road arm on which a route end point lies (N at negative y, §0)."""
    x, y = point
    if abs(y) > abs(x):
        return "N" if y < 0 else "S"
    return "W" if x < 0 else "E"


def _build_routes():
    xy, approach, names = [], [], []
    for a, (start, quarter) in enumerate(_APPROACH_STARTS):
        for kind in ROUTE_KINDS:
            points = _turtle(start, quarter, _ROUTE_MOVES[kind])
            xy.append(_pad_collinear(points, MAX_ROUTE_VERTICES))
            approach.append(a)
            names.append(f"{APPROACHES[a]}->{_arm_name(points[-1])}")
    xy = np.stack(xy)
    segment_lengths = np.linalg.norm(np.diff(xy, axis=1), axis=-1)
    cumlen = np.concatenate([np.zeros((len(xy), 1)), np.cumsum(segment_lengths, axis=1)], axis=1)
    return xy, cumlen, np.asarray(approach, dtype=np.int32), tuple(names)


ROUTE_XY, ROUTE_CUMLEN, ROUTE_APPROACH, ROUTE_NAMES = _build_routes()
ROUTE_LENGTH = ROUTE_CUMLEN[:, -1].copy()


def route_index(approach: str, kind: str) -> int:
    """Route index r = 3 * approach + kind from names such as ("N", "left")."""
    if approach not in APPROACHES or kind not in ROUTE_KINDS:
        raise ValueError(f"unknown route ({approach!r}, {kind!r}); use {APPROACHES} x {ROUTE_KINDS}")
    return 3 * APPROACHES.index(approach) + ROUTE_KINDS.index(kind)


# ------------------------------------------------------------------------------------------------
# Spawn areas and poses (§2.3): computed on each approach's straight route
# ------------------------------------------------------------------------------------------------


def _build_spawns():
    areas, poses = [], []
    for start, quarter in _APPROACH_STARTS:
        forward = _QUARTER_DIRECTIONS[quarter % 4]
        left = _QUARTER_DIRECTIONS[(quarter + 1) % 4]
        corners = np.array(
            [
                np.asarray(start) + s * forward + lateral * left
                for s in SPAWN_AREA_ARCLENGTH
                for lateral in (-SPAWN_AREA_HALF_LATERAL, SPAWN_AREA_HALF_LATERAL)
            ]
        )
        areas.append([corners[:, 0].min(), corners[:, 0].max(), corners[:, 1].min(), corners[:, 1].max()])
        x, y = np.asarray(start) + SPAWN_OFFSET * forward
        poses.append([x, y, math.atan2(forward[1], forward[0])])
    return np.asarray(areas, dtype=np.float64), np.asarray(poses, dtype=np.float64)


SPAWN_AREAS, SPAWN_POSES = _build_spawns()  # (4, 4) = (xmin, xmax, ymin, ymax); (4, 3) = (x, y, theta)

# ------------------------------------------------------------------------------------------------
# Road outline (§2.2)
# ------------------------------------------------------------------------------------------------


def _line_intersection(p, d, q, e) -> np.ndarray:
    """Intersection of the lines p + t d and q + u e (not parallel)."""
    w = q - p
    t = (w[0] * e[1] - w[1] * e[0]) / (d[0] * e[1] - d[1] * e[0])
    return p + t * d


def _inner_fillet(route: np.ndarray) -> np.ndarray:
    """Mitred inner (left) 2.5 m offset of a right-turn route between its two straight parts.

    Joining consecutive offset lines gives the fillet of §2.2: the first and last joins lie on the
    offset straights (the arm sides |x| = 4, |y| = 4), the six others at rho from the turn centre."""
    direction = np.diff(route, axis=0)
    left = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    anchors = route[:-1] + ROAD_HALF_WIDTH * left
    return np.stack(
        [
            _line_intersection(anchors[i], direction[i], anchors[i + 1], direction[i + 1])
            for i in range(len(direction) - 1)
        ]
    )


def _rotate_quarter(points: np.ndarray, times: int) -> np.ndarray:
    """Rotate points by times * 90 degrees (maths sense) about the origin, exactly."""
    for _ in range(times % 4):
        points = np.stack([-points[:, 1], points[:, 0]], axis=1)
    return points


def _build_road_polygon() -> np.ndarray:
    """Counter-clockwise outline: plus-shaped cross with four fillets, 4-fold rotationally symmetric.

    One quarter is the fillet of the N->W turn (corner (-4, -4)) followed by the two corners of the N arm
    end; rotating it by 90, 180 and 270 degrees (N->W maps to E->N, S->E, W->S) gives the rest."""
    fillet = _inner_fillet(ROUTE_XY[route_index("N", "right")])[::-1]  # ccw: from y = -4 to x = -4
    arm_end = np.array([[-ARM_HALF_WIDTH, -ROAD_END], [ARM_HALF_WIDTH, -ROAD_END]])
    quarter = np.concatenate([fillet, arm_end])
    return np.concatenate([_rotate_quarter(quarter, k) for k in range(4)])


ROAD_POLYGON = _build_road_polygon()  # (40, 2)
# All 40 outline edges matter for containment: 4 x 7 fillet chords, 8 arm sides and 4 arm ends.
ROAD_EDGES = np.stack([ROAD_POLYGON, np.roll(ROAD_POLYGON, -1, axis=0)], axis=1)  # (40, 2, 2)

# ------------------------------------------------------------------------------------------------
# Jittable functions
# ------------------------------------------------------------------------------------------------


def _float_dtype(*values):
    """Common floating dtype of the inputs (float32 by default, float64 when x64 inputs are given)."""
    return jnp.result_type(*values, float)


def boundary_tolerance(dtype) -> float:
    """Distance below which two boundaries count as touching: 1e-9 m in float64, 1e-4 m in lower
    precision (a few ulps of coordinates up to ~52 m in float32)."""
    return 1e-9 if jnp.finfo(dtype).bits >= 64 else 1e-4


def _require_shape(name: str, value, shape: tuple) -> None:
    if jnp.shape(value) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {jnp.shape(value)}")


def _check_route(route_xy, cumlen) -> None:
    xy_shape, len_shape = jnp.shape(route_xy), jnp.shape(cumlen)
    if len(xy_shape) != 2 or xy_shape[1] != 2 or xy_shape[0] < 2 or len_shape != xy_shape[:1]:
        raise ValueError(
            f"route_xy must be (V, 2) with V >= 2 and cumlen (V,), got {xy_shape} and {len_shape}"
        )


def route_project(route_xy, cumlen, point):
    """Arc length s in [0, L] of the point of the route nearest to `point`, and the distance to it.

    Global nearest point over all segments (§6.1, Q12), each segment's closest point clamped to its
    ends; exact ties go to the earliest segment (argmin returns the first minimum). Zero-length segments
    are harmless."""
    _check_route(route_xy, cumlen)
    _require_shape("point", point, (2,))
    dtype = _float_dtype(route_xy, cumlen, point)
    route_xy = jnp.asarray(route_xy, dtype)
    cumlen = jnp.asarray(cumlen, dtype)
    point = jnp.asarray(point, dtype)
    ax, ay = route_xy[:-1, 0], route_xy[:-1, 1]
    ex, ey = route_xy[1:, 0] - ax, route_xy[1:, 1] - ay
    wx, wy = point[0] - ax, point[1] - ay
    len2 = ex * ex + ey * ey
    t = jnp.clip((wx * ex + wy * ey) / jnp.where(len2 > 0, len2, 1), 0, 1)
    gx, gy = wx - t * ex, wy - t * ey
    dist2 = gx * gx + gy * gy
    k = jnp.argmin(dist2)
    s = cumlen[k] + t[k] * (cumlen[k + 1] - cumlen[k])
    return jnp.clip(s, 0, cumlen[-1]), jnp.sqrt(dist2[k])


def route_point_at(route_xy, cumlen, s):
    """Point of the route at arc length s, clamped to [0, L]; elementwise over any shape of s -> (..., 2)."""
    _check_route(route_xy, cumlen)
    dtype = _float_dtype(route_xy, cumlen, s)
    route_xy = jnp.asarray(route_xy, dtype)
    cumlen = jnp.asarray(cumlen, dtype)
    s = jnp.clip(jnp.asarray(s, dtype), 0, cumlen[-1])
    # Segment k with cumlen[k] <= s < cumlen[k + 1] (the last segment for s = L): a fixed-size count.
    k = jnp.sum(s[..., None] >= cumlen[1:-1], axis=-1)
    lo, span = cumlen[k], cumlen[k + 1] - cumlen[k]
    t = jnp.clip(jnp.where(span > 0, (s - lo) / jnp.where(span > 0, span, 1), 0), 0, 1)[..., None]
    return (1 - t) * route_xy[k] + t * route_xy[k + 1]


def rectangle_corners(x, y, theta, half_length, half_width):
    """(4, 2) corners of the oriented rectangle, counter-clockwise from front-right (body (+l, -w))."""
    for name, value in (("x", x), ("y", y), ("theta", theta), ("half_length", half_length)):
        _require_shape(name, value, ())
    _require_shape("half_width", half_width, ())
    dtype = _float_dtype(x, y, theta, half_length, half_width)
    x, y, theta, hl, hw = (jnp.asarray(value, dtype) for value in (x, y, theta, half_length, half_width))
    c, s = jnp.cos(theta), jnp.sin(theta)
    body_x = jnp.stack([hl, hl, -hl, -hl])
    body_y = jnp.stack([-hw, hw, hw, -hw])
    return jnp.stack([x + c * body_x - s * body_y, y + s * body_x + c * body_y], axis=-1)


def _points_on_road(points):
    """Inside-or-on test of (..., 2) points against the road polygon -> (...,) bool.

    Crossing-number parity (half-open rule on y, so vertices are counted once) for the inside, plus a
    distance test to every edge so that points on the boundary count as on the road."""
    dtype = points.dtype
    edges = jnp.asarray(ROAD_EDGES, dtype)
    ax, ay, bx, by = edges[:, 0, 0], edges[:, 0, 1], edges[:, 1, 0], edges[:, 1, 1]
    px, py = points[..., 0:1], points[..., 1:2]
    straddles = (ay > py) != (by > py)
    dy = jnp.where(straddles, by - ay, 1)
    x_cross = ax + (py - ay) * (bx - ax) / dy
    inside = jnp.sum(straddles & (px < x_cross), axis=-1) % 2 == 1
    ex, ey = bx - ax, by - ay
    wx, wy = px - ax, py - ay
    t = jnp.clip((wx * ex + wy * ey) / (ex * ex + ey * ey), 0, 1)
    gx, gy = wx - t * ex, wy - t * ey
    tol = boundary_tolerance(dtype)
    on_edge = jnp.any(gx * gx + gy * gy <= tol * tol, axis=-1)
    return inside | on_edge


def point_on_road(p):
    """True iff the point lies inside or on the boundary of the road polygon (§2.2)."""
    _require_shape("p", p, (2,))
    return _points_on_road(jnp.asarray(p, _float_dtype(p)))


def _edges_entering(x, y, c, s, hl, hw, tol):
    """(M,) bool: which road edges enter the open interior of the rectangle (centre x, y; heading cos c,
    sin s; half extents hl, hw) by more than `tol`.

    Separating-axis test of each edge segment against the rectangle on the rectangle's two axes and the
    edge normal, with strict inequalities, vectorised over all edges as flat x/y vectors."""
    dtype = jnp.result_type(x)
    ax, ay = (jnp.asarray(ROAD_EDGES[:, 0, k], dtype) for k in (0, 1))
    ex, ey = (jnp.asarray(ROAD_EDGES[:, 1, k] - ROAD_EDGES[:, 0, k], dtype) for k in (0, 1))
    edge_length = jnp.asarray(np.linalg.norm(ROAD_EDGES[:, 1] - ROAD_EDGES[:, 0], axis=1), dtype)
    rx, ry = ax - x, ay - y
    u0, v0 = c * rx + s * ry, -s * rx + c * ry  # edge start in the rectangle frame
    du, dv = c * ex + s * ey, -s * ex + c * ey  # edge vector in the rectangle frame
    u1, v1 = u0 + du, v0 + dv
    overlap_u = (jnp.maximum(u0, u1) > -hl + tol) & (jnp.minimum(u0, u1) < hl - tol)
    overlap_v = (jnp.maximum(v0, v1) > -hw + tol) & (jnp.minimum(v0, v1) < hw - tol)
    # Edge normal (-ey, ex), unnormalised: |offset of the edge line| vs the rectangle's projected extent.
    line_offset = jnp.abs(ex * ry - ey * rx)
    extent = hl * jnp.abs(dv) + hw * jnp.abs(du)
    overlap_normal = line_offset < extent - tol * edge_length
    return overlap_u & overlap_v & overlap_normal


def rectangle_on_road(x, y, theta, half_length=VEHICLE_HALF_LENGTH, half_width=VEHICLE_HALF_WIDTH):
    """Exact containment of the oriented rectangle in the (non-convex) road polygon (§2.2, §5.3, Q11).

    Rule of §2.2: all four corners inside-or-on AND no road edge enters the rectangle's open interior;
    touching counts as contained. Evaluated in an equivalent, cheaper form: when no edge meets the open
    interior, that (connected) interior lies wholly inside or wholly outside the road, so the centre
    decides for every point, corners included. The edge test is a strict separating-axis test per edge
    (`_edges_entering`), the centre test the crossing-number test of `point_on_road`."""
    for name, value in (("x", x), ("y", y), ("theta", theta), ("half_length", half_length)):
        _require_shape(name, value, ())
    _require_shape("half_width", half_width, ())
    dtype = _float_dtype(x, y, theta, half_length, half_width)
    x, y, theta, hl, hw = (jnp.asarray(value, dtype) for value in (x, y, theta, half_length, half_width))
    enters = _edges_entering(x, y, jnp.cos(theta), jnp.sin(theta), hl, hw, boundary_tolerance(dtype))
    return _points_on_road(jnp.stack([x, y])) & ~jnp.any(enters)


def rectangles_intersect(pose_a, pose_b, half_length, half_width):
    """True iff two closed oriented rectangles of equal size share a point (touching counts, §5.4).

    Separating-axis test on the four rectangle axes with non-strict inequalities."""
    _require_shape("pose_a", pose_a, (3,))
    _require_shape("pose_b", pose_b, (3,))
    dtype = _float_dtype(pose_a, pose_b, half_length, half_width)
    pose_a, pose_b = jnp.asarray(pose_a, dtype), jnp.asarray(pose_b, dtype)
    hl, hw = jnp.asarray(half_length, dtype), jnp.asarray(half_width, dtype)
    ca, sa, cb, sb = jnp.cos(pose_a[2]), jnp.sin(pose_a[2]), jnp.cos(pose_b[2]), jnp.sin(pose_b[2])
    axes_x = jnp.stack([ca, -sa, cb, -sb])  # heading and lateral axis of a, then of b
    axes_y = jnp.stack([sa, ca, sb, cb])
    dx, dy = pose_b[0] - pose_a[0], pose_b[1] - pose_a[1]
    radius_a = hl * jnp.abs(axes_x * ca + axes_y * sa) + hw * jnp.abs(-axes_x * sa + axes_y * ca)
    radius_b = hl * jnp.abs(axes_x * cb + axes_y * sb) + hw * jnp.abs(-axes_x * sb + axes_y * cb)
    gap = jnp.abs(axes_x * dx + axes_y * dy)
    return jnp.all(gap <= radius_a + radius_b + boundary_tolerance(dtype))


def rectangle_intersects_box(pose, half_length, half_width, box):
    """True iff the closed oriented rectangle at `pose` and the closed axis-aligned box (xmin, xmax, ymin,
    ymax) share a point (touching counts); e.g. "is this spawn area occupied" (§2.3)."""
    _require_shape("pose", pose, (3,))
    _require_shape("box", box, (4,))
    dtype = _float_dtype(pose, half_length, half_width, box)
    pose, box = jnp.asarray(pose, dtype), jnp.asarray(box, dtype)
    hl, hw = jnp.asarray(half_length, dtype), jnp.asarray(half_width, dtype)
    c, s = jnp.abs(jnp.cos(pose[2])), jnp.abs(jnp.sin(pose[2]))
    bx, by = (box[1] - box[0]) / 2, (box[3] - box[2]) / 2
    dx, dy = (box[0] + box[1]) / 2 - pose[0], (box[2] + box[3]) / 2 - pose[1]
    cos_t, sin_t = jnp.cos(pose[2]), jnp.sin(pose[2])
    gaps = jnp.stack(
        [jnp.abs(dx), jnp.abs(dy), jnp.abs(cos_t * dx + sin_t * dy), jnp.abs(-sin_t * dx + cos_t * dy)]
    )
    radii = jnp.stack(
        [
            bx + hl * c + hw * s,  # box x axis
            by + hl * s + hw * c,  # box y axis
            hl + bx * c + by * s,  # rectangle heading axis
            hw + bx * s + by * c,  # rectangle lateral axis
        ]
    )
    return jnp.all(gaps <= radii + boundary_tolerance(dtype))
