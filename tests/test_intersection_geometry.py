"""Intersection geometry (docs/carenv-intersection.md §2, §5.3, §5.4, §10): routes, road, rectangle tests.

Reference numbers come from §10 there; the jittable tests are checked against small numpy brute forces
(distance to the route polylines, dense sampling, exact convex-polygon overlap)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs.intersection_geometry as geo

HL, HW = geo.VEHICLE_HALF_LENGTH, geo.VEHICLE_HALF_WIDTH
STRAIGHT, RIGHT, LEFT = 103.0, 98.05376199450839, 104.05376199450839


# ------------------------------------------------------------------------------------------------
# numpy brute forces
# ------------------------------------------------------------------------------------------------


def _segment_distances(points, a, b):
    """(N, S) distances from points (N, 2) to segments a -> b (S, 2)."""
    d = b - a
    w = points[:, None, :] - a[None]
    t = np.clip(np.sum(w * d, -1) / np.sum(d * d, -1), 0, 1)
    return np.linalg.norm(w - t[..., None] * d, axis=-1)


def _road_clearance(points):
    """Signed clearance of points from the road boundary (> 0 inside), from the definition in §2.2 of
    the road (points within 2.5 m of some route, flat ends at +-51.5). Lipschitz 1."""
    a = geo.ROUTE_XY[:, :-1].reshape(-1, 2)
    b = geo.ROUTE_XY[:, 1:].reshape(-1, 2)
    dist = _segment_distances(points, a, b).min(axis=1)
    return np.minimum(geo.ROAD_HALF_WIDTH - dist, geo.ROAD_END - np.abs(points).max(axis=1))


def _np_corners(pose, hl, hw):
    x, y, theta = pose
    c, s = math.cos(theta), math.sin(theta)
    body = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])
    return np.stack([x + c * body[:, 0] - s * body[:, 1], y + s * body[:, 0] + c * body[:, 1]], axis=1)


def _cross(o, a, b):
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _convex_overlap(p, q):
    """Closed overlap of two counter-clockwise convex quadrilaterals: a vertex inside the other, or two
    edges crossing (generic positions; degenerate cases are filtered out by the callers)."""

    def contains(poly, point):
        return all(_cross(poly[i], poly[(i + 1) % 4], point) >= 0 for i in range(4))

    if any(contains(q, v) for v in p) or any(contains(p, v) for v in q):
        return True
    for i in range(4):
        a, b = p[i], p[(i + 1) % 4]
        for j in range(4):
            c, d = q[j], q[(j + 1) % 4]
            if _cross(a, b, c) * _cross(a, b, d) <= 0 and _cross(c, d, a) * _cross(c, d, b) <= 0:
                return True
    return False


def _box_polygon(box):
    xmin, xmax, ymin, ymax = box
    return np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])


def _rotate(points, quarters):
    for _ in range(quarters):
        points = np.stack([-points[..., 1], points[..., 0]], axis=-1)
    return points


# ------------------------------------------------------------------------------------------------
# shared jitted functions
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fns():
    return {
        "project": jax.jit(jax.vmap(geo.route_project, in_axes=(None, None, 0))),
        "project_routes": jax.jit(jax.vmap(jax.vmap(geo.route_project, (None, None, 0)), (0, 0, None))),
        "point_at": jax.jit(geo.route_point_at),
        "on_road": jax.jit(jax.vmap(geo.point_on_road)),
        "contained": jax.jit(jax.vmap(geo.rectangle_on_road, in_axes=(0, 0, 0, None, None))),
        "intersect": jax.jit(jax.vmap(geo.rectangles_intersect, in_axes=(0, 0, None, None))),
        "box": jax.jit(jax.vmap(geo.rectangle_intersects_box, in_axes=(0, None, None, 0))),
        "contained_one": jax.jit(geo.rectangle_on_road),
        "project_one": jax.jit(geo.route_project),
    }


def _contained(fns, poses, hl=HL, hw=HW):
    poses = jnp.asarray(np.atleast_2d(poses))
    return np.asarray(fns["contained"](poses[:, 0], poses[:, 1], poses[:, 2], hl, hw))


# ------------------------------------------------------------------------------------------------
# routes
# ------------------------------------------------------------------------------------------------


def test_route_tables_shapes_names_and_lengths():
    assert geo.ROUTE_XY.shape == (12, geo.MAX_ROUTE_VERTICES, 2) and geo.ROUTE_XY.dtype == np.float64
    assert geo.ROUTE_CUMLEN.shape == (12, 10) and geo.ROUTE_LENGTH.shape == (12,)
    names = "N->S N->W N->E S->N S->E S->W W->E W->S W->N E->W E->N E->S"
    assert tuple(names.split()) == geo.ROUTE_NAMES
    np.testing.assert_array_equal(geo.ROUTE_APPROACH, np.repeat(np.arange(4), 3))
    np.testing.assert_allclose(geo.ROUTE_LENGTH, [STRAIGHT, RIGHT, LEFT] * 4, rtol=0, atol=1e-9)
    np.testing.assert_allclose(7 * 2 * 4.5 * math.sin(math.pi / 28), RIGHT - 91.0, atol=1e-12)
    seg = np.linalg.norm(np.diff(geo.ROUTE_XY, axis=1), axis=-1)
    np.testing.assert_allclose(geo.ROUTE_CUMLEN[:, 0], 0)
    np.testing.assert_allclose(np.diff(geo.ROUTE_CUMLEN, axis=1), seg, atol=1e-12)
    assert (seg > 1).all()  # padding never creates degenerate segments
    # every route starts and ends 51.5 m from the centre, on its lane
    assert np.allclose(np.abs(geo.ROUTE_XY[:, [0, -1]]).max(-1), 51.5)
    assert np.allclose(np.abs(geo.ROUTE_XY[:, [0, -1]]).min(-1), 1.5)
    assert geo.route_index("W", "left") == 8 and geo.ROUTE_NAMES[geo.route_index("E", "right")] == "E->N"
    with pytest.raises(ValueError, match="unknown route"):
        geo.route_index("X", "left")


def test_route_test_vectors():
    n_to_w = [
        (-1.5, -51.5), (-1.5, -6), (-1.612824, -4.998656), (-1.94564, -4.047523), (-2.481758, -3.194296),
        (-3.194296, -2.481758), (-4.047523, -1.94564), (-4.998656, -1.612824), (-6, -1.5), (-51.5, -1.5),
    ]  # fmt: skip
    n_to_e = [
        (-1.5, -51.5), (-1.5, -3), (-1.387176, -1.998656), (-1.05436, -1.047523), (-0.518242, -0.194296),
        (0.194296, 0.518242), (1.047523, 1.05436), (1.998656, 1.387176), (3, 1.5), (51.5, 1.5),
    ]  # fmt: skip
    np.testing.assert_allclose(geo.ROUTE_XY[1], n_to_w, atol=1e-6)
    np.testing.assert_allclose(geo.ROUTE_XY[2], n_to_e, atol=1e-6)
    # arcs centred at (-6, -6) (right turn) and (3, -3) (left turn), radius 4.5
    np.testing.assert_allclose(np.linalg.norm(geo.ROUTE_XY[1, 1:9] - [-6, -6], axis=1), 4.5, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(geo.ROUTE_XY[2, 1:9] - [3, -3], axis=1), 4.5, atol=1e-12)
    # N->S: padded with collinear, evenly spaced vertices from (-1.5, -51.5) to (-1.5, 51.5)
    straight = geo.ROUTE_XY[0]
    np.testing.assert_array_equal(straight[:, 0], -1.5)
    np.testing.assert_array_equal(straight[[0, -1], 1], [-51.5, 51.5])
    np.testing.assert_allclose(np.diff(straight[:, 1]), 103 / 9, atol=1e-12)


def test_route_symmetry():
    """E routes = N routes rotated by +90 degrees, S by 180, W by 270 (kinds preserved)."""
    north = geo.ROUTE_XY[0:3]
    for approach, quarters in (("E", 1), ("S", 2), ("W", 3)):
        a = geo.APPROACHES.index(approach)
        np.testing.assert_allclose(geo.ROUTE_XY[3 * a : 3 * a + 3], _rotate(north, quarters), atol=1e-12)
        np.testing.assert_allclose(geo.ROUTE_CUMLEN[3 * a : 3 * a + 3], geo.ROUTE_CUMLEN[0:3], atol=1e-12)


def test_goal_thresholds():
    expected = [98.0, 93.05376199450839, 99.05376199450839] * 4
    np.testing.assert_allclose(geo.ROUTE_LENGTH - 5.0, expected, rtol=0, atol=1e-9)


def test_spawn_areas_and_poses(fns):
    np.testing.assert_allclose(
        geo.SPAWN_AREAS,
        [[-2.5, -0.5, -50, -43], [0.5, 2.5, 43, 50], [-50, -43, 0.5, 2.5], [43, 50, -2.5, -0.5]],
        atol=1e-12,
    )
    np.testing.assert_allclose(
        geo.SPAWN_POSES,
        [[-1.5, -46.5, math.pi / 2], [1.5, 46.5, -math.pi / 2], [-46.5, 1.5, 0.0], [46.5, -1.5, math.pi]],
        atol=1e-12,
    )
    # spawn pose = route point at arc length 5 on every route of the approach
    for r in range(12):
        point = np.asarray(
            fns["point_at"](geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r], jnp.asarray(geo.SPAWN_OFFSET))
        )
        np.testing.assert_allclose(point, geo.SPAWN_POSES[geo.ROUTE_APPROACH[r], :2], atol=1e-5)
    # a jittered vehicle's box lies inside its spawn area (§2.3)
    for a in range(4):
        for jx in (-0.2, 0.2):
            for jy in (-0.2, 0.2):
                pose = geo.SPAWN_POSES[a] + [jx, jy, 0]
                corners = _np_corners(pose, HL, HW)
                xmin, xmax, ymin, ymax = geo.SPAWN_AREAS[a]
                assert (corners[:, 0] >= xmin).all() and (corners[:, 0] <= xmax).all()
                assert (corners[:, 1] >= ymin).all() and (corners[:, 1] <= ymax).all()


# ------------------------------------------------------------------------------------------------
# road polygon
# ------------------------------------------------------------------------------------------------


def test_road_polygon_area_bbox_orientation():
    poly = geo.ROAD_POLYGON
    assert poly.shape == (40, 2)
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)  # > 0: counter-clockwise
    assert area == pytest.approx(1587.744, abs=1e-3)
    np.testing.assert_allclose([x.min(), x.max(), y.min(), y.max()], [-51.5, 51.5, -51.5, 51.5])
    assert geo.ROAD_EDGES.shape == (40, 2, 2)
    np.testing.assert_array_equal(geo.ROAD_EDGES[:, 0], poly)
    np.testing.assert_array_equal(geo.ROAD_EDGES[:, 1], np.roll(poly, -1, axis=0))
    # 4-fold rotational symmetry
    rotated = _rotate(poly, 1)
    assert max(np.min(np.linalg.norm(rotated[:, None] - poly[None], axis=-1), axis=1)) < 1e-12


def test_fillet_vertices():
    spec = np.array(
        [
            (-6.140397, -4), (-5.558478, -4.065567), (-5.139096, -4.212315), (-4.762883, -4.448705),
            (-4.448705, -4.762883), (-4.212315, -5.139096), (-4.065567, -5.558478), (-4, -6.140397),
        ]
    )  # fmt: skip
    poly = geo.ROAD_POLYGON
    for sx in (-1, 1):
        for sy in (-1, 1):
            expected = spec * [-sx, -sy]
            gaps = np.min(np.linalg.norm(expected[:, None] - poly[None], axis=-1), axis=1)
            assert gaps.max() < 1e-6, (sx, sy, gaps)
    # the (-4, -4) fillet in counter-clockwise order, and its closed form
    start = int(np.argmin(np.linalg.norm(poly - spec[0], axis=1)))
    fillet = poly[start : start + 8]
    np.testing.assert_allclose(fillet, spec, atol=1e-6)
    rho = 4.5 - 2.5 / math.cos(math.pi / 28)
    assert rho == pytest.approx(1.984181, abs=1e-6)
    angles = np.arange(6, 0, -1) * math.pi / 14
    closed = np.stack([-6 + rho * np.cos(angles), -6 + rho * np.sin(angles)], axis=1)
    np.testing.assert_allclose(fillet[1:7], closed, atol=1e-12)


def test_polygon_vertices_lie_on_the_offset_boundary():
    """Every outline vertex is exactly 2.5 m from the nearest route (or on an end line)."""
    clearance = _road_clearance(geo.ROAD_POLYGON)
    np.testing.assert_allclose(clearance, 0, atol=1e-12)


def test_point_on_road_reference_points(fns):
    on = fns["on_road"]
    np.testing.assert_array_equal(np.asarray(on(jnp.array([[-4.5, -4.5], [-5.5, -5.5]]))), [True, False])
    # vertices, edge midpoints (boundary: on), and points 1 mm outside / inside every edge
    a, b = geo.ROAD_EDGES[:, 0], geo.ROAD_EDGES[:, 1]
    mid = (a + b) / 2
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    outward = np.stack([d[:, 1], -d[:, 0]], axis=1)  # right of a ccw edge
    assert np.asarray(on(jnp.asarray(geo.ROAD_POLYGON))).all()
    assert np.asarray(on(jnp.asarray(mid))).all()
    assert not np.asarray(on(jnp.asarray(mid + 1e-3 * outward))).any()
    assert np.asarray(on(jnp.asarray(mid - 1e-3 * outward))).all()
    assert not np.asarray(on(jnp.array([[0.0, 52.0], [60.0, 0.0], [10.0, 10.0], [-20.0, 30.0]]))).any()


def test_point_on_road_matches_route_distance(fns):
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-55, 55, (3000, 2)), rng.uniform(-9, 9, (3000, 2))])
    clearance = _road_clearance(points)
    keep = np.abs(clearance) > 1e-3
    got = np.asarray(fns["on_road"](jnp.asarray(points[keep])))
    np.testing.assert_array_equal(got, clearance[keep] > 0)
    assert got.sum() > 500 and (~got).sum() > 500


# ------------------------------------------------------------------------------------------------
# containment
# ------------------------------------------------------------------------------------------------


def test_corner_only_counterexample(fns):
    """§10: all four corners on the road, yet the rectangle spans the off-road corner."""
    corners = geo.rectangle_corners(-4.3, -4.3, -math.pi / 4, HL, HW)
    assert corners.shape == (4, 2)
    assert np.asarray(fns["on_road"](corners)).all()
    assert not _contained(fns, [-4.3, -4.3, -math.pi / 4])[0]
    assert not bool(fns["contained_one"](-4.3, -4.3, -math.pi / 4))


def test_rectangle_corners_order():
    corners = np.asarray(geo.rectangle_corners(1.0, 2.0, math.pi / 2, 2.0, 1.0))
    np.testing.assert_allclose(corners, [[2, 4], [0, 4], [0, 0], [2, 0]], atol=1e-6)


def test_spawn_vehicles_contained(fns):
    jitter = np.array([[jx, jy, 0] for jx in (-0.2, 0, 0.2) for jy in (-0.2, 0, 0.2)])
    poses = (geo.SPAWN_POSES[:, None] + jitter[None]).reshape(-1, 3)
    assert _contained(fns, poses).all()
    # also the lane centre of every route at several arc lengths, with the route heading
    for r in range(12):
        s = np.linspace(3.2, geo.ROUTE_LENGTH[r] - 3.2, 40)
        xy = np.asarray(fns["point_at"](geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r], jnp.asarray(s)))
        ahead = np.asarray(fns["point_at"](geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r], jnp.asarray(s + 0.01)))
        heading = np.arctan2(ahead[:, 1] - xy[:, 1], ahead[:, 0] - xy[:, 0])
        assert _contained(fns, np.column_stack([xy, heading])).all(), geo.ROUTE_NAMES[r]
    # reversing 3.1 m past the spawn point leaves the road end (rear edge past 51.5)
    assert _contained(fns, [[-1.5, -51.5 + HL, math.pi / 2]])[0]
    assert not _contained(fns, [[-1.5, -51.5 + HL - 1e-3, math.pi / 2]])[0]


def test_lateral_offset_limit(fns):
    """§5.3: on an arm the centre may be at most 4 - 0.74 = 3.26 m from the arm's centre line."""
    margin = 1e-3  # float32; float64 is checked to 1e-6 in test_float64_parity
    limit = geo.ARM_HALF_WIDTH - HW  # 3.26
    assert limit == pytest.approx(3.26)
    poses = []
    for along in (-30.0, 30.0):
        for side in (-1, 1):
            for delta in (-margin, 0.0, margin):
                lateral = side * (limit + delta)
                poses.append([lateral, along, math.pi / 2])  # vertical arm
                poses.append([along, lateral, 0.0])  # horizontal arm
    poses = np.array(poses)
    expected = np.abs(poses[:, :2]).min(axis=1) <= limit + 1e-12
    np.testing.assert_array_equal(_contained(fns, poses), expected)


def test_rectangle_on_road_matches_dense_boundary_sampling(fns):
    """Containment in a simply connected region <=> the rectangle's boundary is inside it; the boundary
    is sampled every ~1.3 cm and the clearance (Lipschitz 1) decides unless within half a spacing of 0."""
    rng = np.random.default_rng(1)
    n = 300
    arm = np.column_stack([rng.uniform(-4, 4, 150), rng.choice([-1, 1], 150) * rng.uniform(5, 52, 150)])
    arm[75:] = arm[75:, ::-1]  # half on the vertical, half on the horizontal arms (ends included)
    centre = np.concatenate([rng.uniform(-8, 8, (n - 150, 2)), arm])
    poses = np.column_stack([centre, rng.uniform(-math.pi, math.pi, n)])
    got = _contained(fns, poses)

    per_side = 300
    f = (np.arange(per_side) / per_side)[:, None]
    spacing = 2 * HL / per_side
    decided = 0
    for pose, contained in zip(poses, got, strict=True):
        c = _np_corners(pose, HL, HW)
        boundary = np.concatenate([c[i] + f * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        worst = _road_clearance(boundary).min()
        if worst < 0:
            assert not contained, pose
        elif worst > spacing / 2:
            assert contained, pose
        else:
            continue
        decided += 1
    assert decided > 0.95 * n
    assert got.sum() > 40 and (~got).sum() > 40

    # the literal rule of §2.2 (four corners inside-or-on AND no edge enters) gives the same answers
    def literal(pose):
        corners_on = jnp.all(jax.vmap(geo.point_on_road)(geo.rectangle_corners(*pose, HL, HW)))
        tol = geo.boundary_tolerance(pose.dtype)
        c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
        return corners_on & ~jnp.any(geo._edges_entering(pose[0], pose[1], c, s, HL, HW, tol))

    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(literal))(jnp.asarray(poses))), got)


# ------------------------------------------------------------------------------------------------
# projection
# ------------------------------------------------------------------------------------------------


def test_projection_against_dense_sampling(fns):
    rng = np.random.default_rng(2)
    points = np.concatenate([rng.uniform(-60, 60, (40, 2)), rng.uniform(-8, 8, (40, 2))])
    s, dist = fns["project_routes"](
        jnp.asarray(geo.ROUTE_XY), jnp.asarray(geo.ROUTE_CUMLEN), jnp.asarray(points)
    )
    s, dist = np.asarray(s), np.asarray(dist)
    h = 0.01
    for r in range(12):
        xy, cum = geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r]
        dense_s = np.arange(0, geo.ROUTE_LENGTH[r], h)
        dense = np.column_stack([np.interp(dense_s, cum, xy[:, 0]), np.interp(dense_s, cum, xy[:, 1])])
        brute = np.linalg.norm(points[:, None] - dense[None], axis=-1).min(axis=1)
        assert (brute - dist[r] >= -1e-4).all() and (brute - dist[r] <= h / 2 + 1e-4).all()
        assert (s[r] >= 0).all() and (s[r] <= geo.ROUTE_LENGTH[r] + 1e-4).all()
        # s is the arc length of a nearest point
        foot = np.asarray(fns["point_at"](xy, cum, jnp.asarray(s[r])))
        np.testing.assert_allclose(np.linalg.norm(foot - points, axis=1), dist[r], atol=2e-4)


def test_projection_ties_and_clamping(fns):
    # U-shaped polyline: (5, 1) is exactly 1 m from the first and from a later segment
    u_shape = np.array(
        [[0, 0], [10, 0], [10, 2], [8, 2], [6, 2], [4, 2], [2, 2], [0, 2], [0, 4], [0, 6]], float
    )
    cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(u_shape, axis=0), axis=1))])
    s, d = fns["project"](u_shape, cum, jnp.array([[5.0, 1.0], [5.0, 1.5]]))
    np.testing.assert_allclose(np.asarray(s), [5.0, 17.0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(d), [1.0, 0.5], atol=1e-6)
    # before the start and beyond the end: clamped to the end points
    xy, cum = geo.ROUTE_XY[1], geo.ROUTE_CUMLEN[1]
    s, d = fns["project"](xy, cum, jnp.array([[-1.5, -60.0], [-70.0, -1.5], [-1.5, -20.0], [-6.0, -1.5]]))
    np.testing.assert_allclose(np.asarray(s), [0.0, RIGHT, 31.5, RIGHT - 45.5], atol=1e-4)
    np.testing.assert_allclose(np.asarray(d), [8.5, 18.5, 0.0, 0.0], atol=1e-4)


def test_route_point_at_vertices_and_clamping(fns):
    for r in (0, 1, 2, 10):
        xy, cum = geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r]
        np.testing.assert_allclose(np.asarray(fns["point_at"](xy, cum, jnp.asarray(cum))), xy, atol=1e-4)
        ends = np.asarray(fns["point_at"](xy, cum, jnp.array([-5.0, 0.0, cum[-1], cum[-1] + 3.0, 1e4])))
        np.testing.assert_allclose(ends, xy[[0, 0, -1, -1, -1]], atol=1e-4)
    grid = fns["point_at"](geo.ROUTE_XY[0], geo.ROUTE_CUMLEN[0], jnp.arange(12.0).reshape(3, 4) * 10)
    assert grid.shape == (3, 4, 2)
    np.testing.assert_allclose(
        np.asarray(grid[..., 1]), np.minimum(-51.5 + np.arange(12.0).reshape(3, 4) * 10, 51.5), atol=1e-4
    )
    np.testing.assert_allclose(np.asarray(grid[..., 0]), -1.5)


# ------------------------------------------------------------------------------------------------
# rectangle overlap
# ------------------------------------------------------------------------------------------------


def _pose_touching_front_face(theta):
    """Pose of a rectangle whose rear-right corner touches (HL, 0.2) on the front face of a rectangle at
    the origin, lying entirely in x >= HL (theta in (-pi/2, 0))."""
    c, s = math.cos(theta), math.sin(theta)
    return [HL + c * HL - s * HW, 0.2 + s * HL + c * HW, theta]


def test_rectangles_intersect_touching_and_separated(fns):
    origin = [0.0, 0.0, 0.0]
    cases = [
        ([2 * HL, 0.0, 0.0], True),  # face to face
        ([2 * HL + 1e-3, 0.0, 0.0], False),
        ([2 * HL, 2 * HW, 0.0], True),  # corner to corner
        ([2 * HL, 2 * HW + 1e-3, 0.0], False),
        ([0.0, 2 * HW, math.pi], True),  # side by side, opposite headings
        ([0.0, -2 * HW - 1e-3, math.pi], False),
        (_pose_touching_front_face(-0.5), True),
        (list(np.add(_pose_touching_front_face(-0.5), [1e-3, 0, 0])), False),
        ([1.0, 0.5, 1.0], True),  # overlapping
        ([0.0, 0.0, math.pi / 2], True),  # crossed, no vertex inside the other
    ]
    a = jnp.asarray([origin] * len(cases))
    b = jnp.asarray([pose for pose, _ in cases])
    np.testing.assert_array_equal(np.asarray(fns["intersect"](a, b, HL, HW)), [e for _, e in cases])
    np.testing.assert_array_equal(np.asarray(fns["intersect"](b, a, HL, HW)), [e for _, e in cases])


def test_rectangles_intersect_against_polygon_overlap(fns):
    rng = np.random.default_rng(3)
    n = 500
    a = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    b = np.column_stack([rng.uniform(-3, 3, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    for hl, hw in ((HL, HW), (geo.SOFT_HALF_LENGTH, geo.SOFT_HALF_WIDTH)):
        got = np.asarray(fns["intersect"](jnp.asarray(a), jnp.asarray(b), hl, hw))
        checked = 0
        for i in range(n):
            grown = _convex_overlap(
                _np_corners(a[i], hl + 1e-6, hw + 1e-6), _np_corners(b[i], hl + 1e-6, hw + 1e-6)
            )
            shrunk = _convex_overlap(
                _np_corners(a[i], hl - 1e-6, hw - 1e-6), _np_corners(b[i], hl - 1e-6, hw - 1e-6)
            )
            if grown == shrunk:
                assert got[i] == grown, (a[i], b[i])
                checked += 1
        assert checked > 0.99 * n and 50 < got.sum() < n - 50


def test_rectangle_intersects_box(fns):
    rng = np.random.default_rng(4)
    n = 400
    poses = np.column_stack([rng.uniform(-4, 4, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    lo = rng.uniform(-3, 1, (n, 2))
    boxes = np.column_stack(
        [lo[:, 0], lo[:, 0] + rng.uniform(0.2, 3, n), lo[:, 1], lo[:, 1] + rng.uniform(0.2, 3, n)]
    )
    got = np.asarray(fns["box"](jnp.asarray(poses), HL, HW, jnp.asarray(boxes)))
    for i in range(n):
        grown = _convex_overlap(
            _np_corners(poses[i], HL + 1e-6, HW + 1e-6), _box_polygon(boxes[i] + [-1e-6, 1e-6] * 2)
        )
        shrunk = _convex_overlap(
            _np_corners(poses[i], HL - 1e-6, HW - 1e-6), _box_polygon(boxes[i] + [1e-6, -1e-6] * 2)
        )
        if grown == shrunk:
            assert got[i] == grown, (poses[i], boxes[i])
    assert 50 < got.sum() < n - 50
    # spawn areas: occupied by a vehicle at the spawn pose, touching counts, free otherwise
    areas = jnp.asarray(geo.SPAWN_AREAS)
    assert np.asarray(fns["box"](jnp.asarray(geo.SPAWN_POSES), HL, HW, areas)).all()
    touching = np.array([[-1.5, -50 - HL, math.pi / 2], [1.5, 50 + HL, -math.pi / 2]])
    assert np.asarray(fns["box"](jnp.asarray(touching), HL, HW, areas[:2])).all()
    apart = touching + np.array([[0, -1e-3, 0], [0, 1e-3, 0]])
    assert not np.asarray(fns["box"](jnp.asarray(apart), HL, HW, areas[:2])).any()


# ------------------------------------------------------------------------------------------------
# batching, dtypes, input checks
# ------------------------------------------------------------------------------------------------


def test_vmap_batches_match_single_calls(fns):
    rng = np.random.default_rng(5)
    poses = np.column_stack([rng.uniform(-6, 6, (8, 2)), rng.uniform(-math.pi, math.pi, 8)])
    batched = _contained(fns, poses)
    single = [bool(fns["contained_one"](*pose)) for pose in poses]
    np.testing.assert_array_equal(batched, single)
    # all pairs of 8 vehicles at once, and per-slot routes gathered from the table
    pairs = jax.jit(
        jax.vmap(jax.vmap(geo.rectangles_intersect, (None, 0, None, None)), (0, None, None, None))
    )
    matrix = np.asarray(pairs(jnp.asarray(poses), jnp.asarray(poses), HL, HW))
    assert matrix.shape == (8, 8) and matrix.diagonal().all() and (matrix == matrix.T).all()
    routes = jnp.array([0, 1, 2, 5, 7, 11, 4, 9])
    project = jax.jit(jax.vmap(geo.route_project, (0, 0, 0)))
    s, d = project(
        jnp.asarray(geo.ROUTE_XY)[routes], jnp.asarray(geo.ROUTE_CUMLEN)[routes], jnp.asarray(poses[:, :2])
    )
    assert s.shape == (8,) and d.shape == (8,)
    for i, r in enumerate(np.asarray(routes)):
        s1, d1 = fns["project_one"](geo.ROUTE_XY[r], geo.ROUTE_CUMLEN[r], poses[i, :2])
        assert float(s[i]) == pytest.approx(float(s1), abs=1e-5) and float(d[i]) == pytest.approx(
            float(d1), abs=1e-5
        )


def test_float64_parity(fns):
    """Under x64 the same functions compute in float64: exact-looking boundary decisions hold to 1e-6 m
    and results agree with float32 away from the boundary."""
    limit = geo.ARM_HALF_WIDTH - HW
    generic = np.array([[-3.0, -30.0, math.pi / 2], [-4.3, -4.3, -math.pi / 4], [-4.5, -4.6, 0.3], [3, 5, 1]])
    expected32 = _contained(fns, generic)
    point = np.array([[0.3, -2.0], [-30.0, 4.0]])
    s32, d32 = fns["project"](geo.ROUTE_XY[2], geo.ROUTE_CUMLEN[2], jnp.asarray(point, jnp.float32))
    assert s32.dtype == jnp.float32
    with jax.enable_x64(True):
        poses = [[-(limit + delta), -30.0, math.pi / 2] for delta in (-1e-6, 0.0, 1e-6)]
        poses += [[20.0, limit + delta, math.pi] for delta in (-1e-6, 0.0, 1e-6)]
        got = _contained(fns, np.concatenate([poses, generic]))
        np.testing.assert_array_equal(got, [True, True, False] * 2 + list(expected32))
        xy, cum = jnp.asarray(geo.ROUTE_XY[2]), jnp.asarray(geo.ROUTE_CUMLEN[2])
        assert xy.dtype == jnp.float64
        s64, d64 = fns["project"](xy, cum, jnp.asarray(point))
        assert s64.dtype == jnp.float64 and d64.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(s64), np.asarray(s32), atol=1e-4)
        np.testing.assert_allclose(np.asarray(d64), np.asarray(d32), atol=1e-5)
        foot = fns["point_at"](xy, cum, s64)
        assert foot.dtype == jnp.float64
        np.testing.assert_allclose(
            np.linalg.norm(np.asarray(foot) - point, axis=1), np.asarray(d64), atol=1e-12
        )
        np.testing.assert_allclose(np.asarray(fns["point_at"](xy, cum, cum)), geo.ROUTE_XY[2], atol=1e-13)
        touch = np.array([[2 * HL, 0.0, 0.0], [2 * HL + 1e-7, 0.0, 0.0]])
        hit = fns["intersect"](jnp.zeros((2, 3)), jnp.asarray(touch), HL, HW)
        np.testing.assert_array_equal(np.asarray(hit), [True, False])


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="point"):
        geo.route_project(geo.ROUTE_XY[0], geo.ROUTE_CUMLEN[0], np.zeros(3))
    with pytest.raises(ValueError, match="route_xy"):
        geo.route_point_at(geo.ROUTE_XY[0], geo.ROUTE_CUMLEN[0, :5], 1.0)
    with pytest.raises(ValueError, match="p must"):
        geo.point_on_road(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="pose_b"):
        geo.rectangles_intersect(np.zeros(3), np.zeros(2), HL, HW)
    with pytest.raises(ValueError, match="box"):
        geo.rectangle_intersects_box(np.zeros(3), HL, HW, np.zeros(3))
    with pytest.raises(ValueError, match="theta"):
        geo.rectangle_on_road(0.0, 0.0, np.zeros(2))
