"""Track generator (docs/carenv-single-agent.md §5) and track geometry (§6.1, §7.3), against
brute-force numpy, closed forms, the measured statistics of §5 and the golden episodes."""

from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import track_reference as R

from envs import track as T
from envs import track_cones as C
from envs import track_generator as G
from envs import track_shape as S

DATA = Path(__file__).parent / "data"
GOLDEN = ("episode_tracking_public.npz", "episode_country_road_public.npz")
NUM_GENERATED = 64


# ------------------------------------------------------------------------------------------------
# numpy references
# ------------------------------------------------------------------------------------------------


def ring_of(track, index=None):
    """Valid centre-line points of a (possibly banked) track as float64 numpy."""
    line = np.asarray(track.centerline if index is None else track.centerline[index], dtype=np.float64)
    count = int(track.num_points if index is None else track.num_points[index])
    return line[:count]


def np_project(line, point):
    """Brute force nearest point on the closed polyline: (s, dist), float64."""
    a = line
    b = np.roll(line, -1, axis=0)
    edge = b - a
    len2 = np.sum(edge**2, axis=1)
    t = np.where(len2 > 0, np.sum((point - a) * edge, axis=1) / np.where(len2 > 0, len2, 1), 0)
    t = np.clip(t, 0, 1)
    closest = a + t[:, None] * edge
    dist = np.linalg.norm(point - closest, axis=1)
    k = int(np.argmin(dist))
    cum = np.concatenate([[0], np.cumsum(np.sqrt(len2))])
    return cum[k] + t[k] * np.sqrt(len2[k]), dist[k]


def np_point_at(line, s):
    closed = np.concatenate([line, line[:1]])
    cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    s = np.mod(s, cum[-1])
    return np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], axis=-1)


def np_distance_to_ring(line, points):
    a = line[None]
    edge = (np.roll(line, -1, axis=0) - line)[None]
    rel = points[:, None, :] - a
    len2 = np.maximum(np.sum(edge**2, axis=-1), 1e-300)
    t = np.clip(np.sum(rel * edge, axis=-1) / len2, 0, 1)
    return np.min(np.linalg.norm(rel - t[..., None] * edge, axis=-1), axis=1)


def np_is_simple(line):
    """Independent O(n^2) proper-crossing test on the ring without repeated points."""
    keep = np.linalg.norm(np.roll(line, -1, axis=0) - line, axis=1) > 1e-9
    ring = line[keep]
    n = len(ring)
    a, b = ring, np.roll(ring, -1, axis=0)

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )

    A, B = a[:, None], b[:, None]
    C, D = a[None, :], b[None, :]
    crossing = (orient(A, B, C) * orient(A, B, D) < 0) & (orient(C, D, A) * orient(C, D, B) < 0)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    gap = (i - j) % n
    return not np.any(crossing & (gap > 1) & (gap < n - 1))


def body_frame(points, xy, theta):
    d = points - xy
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def load_golden(name):
    return dict(np.load(DATA / name))


def golden_track(d):
    return T.track_from_arrays(
        d["track_centerline"], d["start_pose"][:2], d["start_pose"][2], d["cone_pos"], d["cone_type"]
    )


# ------------------------------------------------------------------------------------------------
# fixtures: one compiled generator for all statistics
# ------------------------------------------------------------------------------------------------


BANK_KEY = jax.random.key(2025)


@pytest.fixture(scope="module")
def generated():
    """NUM_GENERATED tracks from the public bank builder: the only generator compile of the
    default suite (batch_size=1: a sequential lax.map, the cheapest to compile)."""
    return G.make_track_bank(BANK_KEY, NUM_GENERATED, batch_size=1)


@pytest.fixture(scope="module")
def generated_np(generated):
    """The same bank as numpy arrays (fast host-side loops over tracks)."""
    return jax.tree_util.tree_map(np.asarray, generated)


@pytest.fixture(scope="module")
def geometry():
    """Jitted, vmapped geometry functions shared by the tests (float32 and float64 retrace)."""
    return {
        "project": jax.jit(jax.vmap(R.project, in_axes=(None, 0))),
        "point_at": jax.jit(R.point_at_arclength),
        "tangent": jax.jit(jax.vmap(R.travel_tangent, in_axes=(None, 0))),
        "travel_points": jax.jit(jax.vmap(R.travel_points, in_axes=(None, 0, None))),
    }


def one(tracks, i):
    return jax.tree_util.tree_map(lambda leaf: leaf[i], tracks)


# ------------------------------------------------------------------------------------------------
# track_from_arrays and the golden files
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", GOLDEN)
def test_track_from_golden_arrays_reproduces_stored_track(name):
    d = load_golden(name)
    with jax.enable_x64(True):
        track = golden_track(d)
        line = d["track_centerline"]
        assert track.centerline.dtype == jnp.float64
        assert int(track.num_points) == line.shape[0] == 320
        np.testing.assert_array_equal(np.asarray(track.centerline[:320]), line)
        np.testing.assert_array_equal(np.asarray(track.centerline[320:]), np.broadcast_to(line[0], (480, 2)))
        assert abs(float(track.length) - float(d["track_length"])) < 1e-9
        np.testing.assert_allclose(np.asarray(track.cumlen[320:]), float(d["track_length"]), atol=1e-9)
        np.testing.assert_array_equal(np.asarray(track.start_xy), d["start_pose"][:2])
        assert float(track.start_theta) == d["start_pose"][2]
        num_cones = d["cone_pos"].shape[0]
        assert int(track.num_cones) == num_cones
        np.testing.assert_array_equal(np.asarray(track.cone_xy[:num_cones]), d["cone_pos"])
        np.testing.assert_array_equal(np.asarray(track.cone_type[:num_cones]), d["cone_type"])
        assert not np.any(np.asarray(track.cone_present[num_cones:]))
        assert np.all(np.asarray(track.cone_type[num_cones:]) == 0)
    # float32 build: same geometry to float32 precision
    track32 = golden_track(d)
    assert track32.centerline.dtype == jnp.float32
    assert abs(float(track32.length) - float(d["track_length"])) < 1e-3


@pytest.mark.parametrize("name", GOLDEN)
def test_projection_reproduces_golden_proj_s_and_distance(name, geometry):
    d = load_golden(name)
    with jax.enable_x64(True):
        track = golden_track(d)
        s, dist = geometry["project"](track, jnp.asarray(d["state"][:, :2]))
        s, dist = np.asarray(s), np.asarray(dist)
    length = float(d["track_length"])
    ds = np.mod(s - d["proj_s"] + length / 2, length) - length / 2
    assert np.max(np.abs(ds)) < 1e-6
    assert np.max(np.abs(dist - d["dist_center"])) < 1e-6
    assert np.all((s >= 0) & (s < length))


def test_travel_tangent_reproduces_golden_rewards(geometry):
    """racing_tracking reward = 0.01 * v . t(s) exactly (§6.2); includes the two vertex steps
    where only the 'segment ending at the vertex' rule gives the stored reward."""
    d = load_golden("episode_tracking_public.npz")
    with jax.enable_x64(True):
        track = golden_track(d)
        s, _ = geometry["project"](track, jnp.asarray(d["state"][1:, :2]))
        tangent = np.asarray(geometry["tangent"](track, s))
    reward = 0.01 * np.sum(d["state"][1:, 3:5] * tangent, axis=1)
    np.testing.assert_allclose(reward, d["reward"], atol=1e-9, rtol=0)


def test_travel_points_reproduce_golden_trajectory_set(geometry):
    """Lookahead points along the reversed ring (§7.3) from the stored-order projection."""
    d = load_golden("episode_tracking_public.npz")
    with jax.enable_x64(True):
        track = golden_track(d)
        xy, theta = d["state"][:, :2], d["state"][:, 2]
        s, _ = geometry["project"](track, jnp.asarray(xy))
        points = np.asarray(geometry["travel_points"](track, s, 2.0 * jnp.arange(25)))
    local = body_frame(points, xy[:, None, :], theta[:, None])
    expected = d["obs_trajectory_set"][..., 2:4]
    np.testing.assert_allclose(np.clip(local / (np.sqrt(2) * 2 * 25), -1, 1), expected, atol=1e-9, rtol=0)


def test_golden_geometry_in_float32(geometry):
    d = load_golden("episode_country_road_public.npz")
    track = golden_track(d)
    s, dist = geometry["project"](track, jnp.asarray(d["state"][:, :2], jnp.float32))
    length = float(d["track_length"])
    ds = np.mod(np.asarray(s, np.float64) - d["proj_s"] + length / 2, length) - length / 2
    assert np.max(np.abs(ds)) < 2e-3
    assert np.max(np.abs(np.asarray(dist) - d["dist_center"])) < 1e-3


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"centerline": np.zeros((5, 3))}, r"shape \(P, 2\)"),
        ({"centerline": np.zeros((T.MAX_CENTERLINE + 1, 2))}, "3..800 points"),
        ({"centerline": np.zeros((2, 2))}, "3..800 points"),
        ({"centerline": np.full((5, 2), np.nan)}, "finite"),
        ({"centerline": np.zeros((5, 2))}, "zero length"),
        ({"start_xy": np.zeros(3)}, r"start_xy must have shape \(2,\)"),
        ({"start_theta": np.zeros(2)}, "scalar"),
        ({"cone_xy": np.zeros((4, 2))}, "together"),
        ({"cone_xy": np.zeros((4, 2)), "cone_type": np.ones(3)}, r"cone_type must have shape \(4,\)"),
        ({"cone_xy": np.zeros((4, 3)), "cone_type": np.ones(4)}, r"cone_xy must have shape"),
        ({"cone_xy": np.zeros((T.MAX_CONES + 1, 2)), "cone_type": np.ones(T.MAX_CONES + 1)}, "at most 320"),
        ({"cone_xy": np.zeros((4, 2)), "cone_type": np.array([1, 2, 3, 1])}, "must be 1"),
    ],
)
def test_track_from_arrays_rejects_bad_input(kwargs, message):
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    args = {"centerline": square, "start_xy": np.zeros(2), "start_theta": 0.0, **kwargs}
    with pytest.raises(ValueError, match=message):
        T.track_from_arrays(**args)


def test_open_and_closed_inputs_give_the_same_ring(geometry):
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    open_track = T.track_from_arrays(square, square[0], 0.0)
    closed_track = T.track_from_arrays(np.concatenate([square, square[:1]]), square[0], 0.0)
    assert float(open_track.length) == pytest.approx(40.0) == float(closed_track.length)
    s = jnp.asarray([0.0, 5.0, 15.0, 35.0, 39.9, 40.0, -5.0, 85.0])
    expected = np.array([[0, 0], [5, 0], [10, 5], [0, 5], [0, 0.1], [0, 0], [0, 5], [5, 0]])
    for track in (open_track, closed_track):
        np.testing.assert_allclose(np.asarray(geometry["point_at"](track, s)), expected, atol=1e-5)
    # the car travels opposite to the stored order: 5 m ahead of (5, 0) is the origin
    ahead = geometry["travel_points"](open_track, jnp.asarray([5.0]), jnp.asarray([0.0, 5.0]))
    np.testing.assert_allclose(np.asarray(ahead[0]), [[5, 0], [0, 0]], atol=1e-5)
    np.testing.assert_allclose(
        np.asarray(geometry["tangent"](open_track, jnp.asarray([5.0]))), [[-1, 0]], atol=1e-6
    )
    delta = jax.jit(R.progress_delta)(
        open_track, jnp.asarray([5.0, 1.0, 39.0]), jnp.asarray([3.0, 39.0, 1.0])
    )
    np.testing.assert_allclose(np.asarray(delta), [2.0, 2.0, -2.0], atol=1e-5)


def test_direction_lookup_skips_tiny_segments_and_takes_the_segment_ending_at_a_vertex(geometry):
    """§6.1 and its correction: the first segment whose end arc length is >= s, skipping
    segments shorter than ~1e-9 m (junction repeats that differ by rounding only)."""
    with jax.enable_x64(True):
        # square with a repeated corner at (10, 0) displaced by 1e-12 m sideways
        line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 1e-12], [10.0, 10.0], [0.0, 10.0]])
        track = T.track_from_arrays(line, line[0], 0.0)
        cum = np.asarray(track.cumlen)
        s = jnp.asarray([5.0, cum[1], cum[1] + 0.5e-12, cum[2], cum[2] + 1.0, float(track.length) + 1e-12])
        tangent = np.asarray(geometry["tangent"](track, s))
    expected = [[-1, 0], [-1, 0], [0, -1], [0, -1], [0, -1], [0, 1]]
    np.testing.assert_allclose(tangent, expected, atol=1e-9)
    # a point outside the corner (10, 0) projects onto the vertex as the end of the first segment
    with jax.enable_x64(True):
        s_vertex, dist = geometry["project"](track, jnp.asarray([[12.0, -2.0]]))
    assert float(s_vertex[0]) == cum[1] and float(dist[0]) == pytest.approx(np.sqrt(8))


# ------------------------------------------------------------------------------------------------
# geometry vs brute force on generated tracks
# ------------------------------------------------------------------------------------------------


def test_project_and_point_at_arclength_match_brute_force(generated, geometry):
    tracks = generated
    rng = np.random.default_rng(0)
    for i in range(3):
        track = one(tracks, i)
        line = ring_of(track).astype(np.float64)
        lo, hi = line.min(0) - 10, line.max(0) + 10
        points = rng.uniform(lo, hi, size=(200, 2))
        s, dist = geometry["project"](track, jnp.asarray(points, jnp.float32))
        ref = np.array([np_project(line, p) for p in points])
        length = float(track.length)
        ds = np.mod(np.asarray(s) - ref[:, 0] + length / 2, length) - length / 2
        np.testing.assert_allclose(np.asarray(dist), ref[:, 1], atol=2e-3)
        # arc lengths agree except where two far-apart parts are (almost) equally near
        assert np.mean(np.abs(ds) < 1e-2) > 0.98
        np.testing.assert_allclose(
            np.asarray(dist),
            np.linalg.norm(np.asarray(geometry["point_at"](track, s)) - points, axis=1),
            atol=2e-3,
        )
        queries = rng.uniform(-length, 2 * length, size=300)
        got = np.asarray(geometry["point_at"](track, jnp.asarray(queries, jnp.float32)))
        np.testing.assert_allclose(got, np_point_at(line, queries), atol=2e-3)
        # a point on the curve projects onto itself
        on_curve = np_point_at(line, queries)
        _s_back, dist_back = geometry["project"](track, jnp.asarray(on_curve, jnp.float32))
        assert np.max(np.asarray(dist_back)) < 2e-3


# ------------------------------------------------------------------------------------------------
# generated tracks: validity, bounds, statistics
# ------------------------------------------------------------------------------------------------


def test_generated_tracks_are_valid_and_within_bounds(generated_np):
    tracks = generated_np
    assert tracks.centerline.shape == (NUM_GENERATED, T.MAX_CENTERLINE, 2)
    assert tracks.cone_xy.shape == (NUM_GENERATED, T.MAX_CONES, 2)
    for i in range(NUM_GENERATED):
        n = int(tracks.num_points[i])
        assert n % 40 == 0 and 6 * 20 <= n <= T.MAX_CENTERLINE  # 20 samples x 2h control points
        full = np.asarray(tracks.centerline[i], np.float64)
        line = full[:n]
        np.testing.assert_array_equal(line[0], line[-1])  # explicitly closed
        np.testing.assert_array_equal(full[n:], np.broadcast_to(line[0], (T.MAX_CENTERLINE - n, 2)))
        junctions = line[19:-1:20]  # every spline junction appears twice
        np.testing.assert_array_equal(junctions, line[20::20])
        seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
        cum = np.concatenate([[0], np.cumsum(seg)])
        np.testing.assert_allclose(np.asarray(tracks.cumlen[i, :n]), cum, rtol=1e-5, atol=1e-3)
        assert float(tracks.length[i]) == pytest.approx(cum[-1], rel=1e-5)
        assert float(tracks.length[i]) <= S.MAX_TRACK_LENGTH
        assert np_is_simple(line)
        present = np.asarray(tracks.cone_present[i])
        count = present.sum()
        assert np.all(present[:count]) and not np.any(present[count:])  # contiguous
        types = np.asarray(tracks.cone_type[i])
        assert set(types[:count]) <= {1, 2} and np.all(types[count:] == 0)


def test_cones_lie_on_the_offset_curves(generated_np):
    tracks = generated_np
    for i in range(8):
        line = ring_of(tracks, i)
        count = int(tracks.num_cones[i])
        cones = np.asarray(tracks.cone_xy[i, :count], np.float64)
        dist = np_distance_to_ring(line, cones)
        # on the 3.5 m buffer boundary (trimmed below 3.45 m; chords of the round joins dip a little)
        assert np.all(dist > 3.5 - C.CONE_TRIM_TOL - 1e-3) and np.all(dist < 3.5 + 1e-2)
        # consecutive cones of a ring are ~5 m apart (chords of the 5 m arc-length spacing)
        types = np.asarray(tracks.cone_type[i, :count])
        same_ring = types[1:] == types[:-1]
        gaps = np.linalg.norm(np.diff(cones, axis=0), axis=1)[same_ring]
        assert np.median(gaps) == pytest.approx(5.0, abs=0.05)
        assert np.max(gaps) < 5.0 + 1e-3


def test_generator_statistics_match_the_spec(generated_np):
    """§5.5-§5.8 measured: control points 8-22 (median 14), samples 160-440 (median 280),
    length 336-636 m (median 492), cones 135-254 (median 197, half each type), ~12 % rejected
    attempts (mean 1.14; checked in the slow test), 22-45 cones visible at reset (mean 28), laps
    CW/CCW 50/50."""
    tracks = generated_np
    n = np.asarray(tracks.num_points)
    control = n // 20
    length = np.asarray(tracks.length)
    cones = np.asarray(tracks.num_cones)
    assert 12 <= np.median(control) <= 16 and control.min() >= 6 and control.max() <= 26
    assert 440 <= np.median(length) <= 540 and length.min() > 250 and length.max() < 700
    assert 175 <= np.median(cones) <= 220 and cones.max() <= T.MAX_CONES
    types = np.asarray(tracks.cone_type)
    assert abs(np.sum(types == 1) / np.sum(types > 0) - 0.5) < 0.03
    visible = []
    clockwise = []
    for i in range(NUM_GENERATED):
        count = int(tracks.num_cones[i])
        local = body_frame(
            np.asarray(tracks.cone_xy[i, :count], np.float64),
            np.asarray(tracks.start_xy[i], np.float64),
            float(tracks.start_theta[i]),
        )
        inside = (local[:, 0] > -15) & (local[:, 0] < 45) & (local[:, 1] > -30) & (local[:, 1] < 30)
        visible.append(inside.sum())
        line = ring_of(tracks, i)
        area = 0.5 * np.sum(line[:, 0] * np.roll(line[:, 1], -1) - np.roll(line[:, 0], -1) * line[:, 1])
        clockwise.append(area > 0)  # travel opposite to a counter-clockwise stored order
    visible = np.asarray(visible)
    assert 24 <= visible.mean() <= 34 and visible.min() >= 15 and visible.max() <= 70
    assert 0.3 <= np.mean(clockwise) <= 0.7  # 64 fair coins: 0.5 +- 3.2 sd


def test_blue_cones_are_on_the_drivers_right(generated, geometry):
    tracks = generated
    for i in range(8):
        track = one(tracks, i)
        s, _ = geometry["project"](track, track.cone_xy)  # all MAX_CONES slots: one compile
        nearest = np.asarray(geometry["point_at"](track, s))
        tangent = np.asarray(geometry["tangent"](track, s))
        offset = np.asarray(track.cone_xy) - nearest
        left = tangent[:, 0] * offset[:, 1] - tangent[:, 1] * offset[:, 0] > 0
        count = int(track.num_cones)
        types = np.asarray(track.cone_type[:count])
        agree = np.where(types == T.CONE_TYPE_YELLOW, left[:count], ~left[:count])
        assert agree.mean() > 0.98  # exceptions only where the nearest point is ambiguous


def test_start_pose_is_on_the_centre_line_between_the_cones(generated, geometry):
    tracks = generated
    gaps = []
    for i in range(16):
        track = one(tracks, i)
        np.testing.assert_array_equal(np.asarray(track.start_xy), np.asarray(track.centerline[0]))
        _s, dist = geometry["project"](track, track.start_xy[None])
        assert float(dist[0]) < 1e-4
        heading = np.array([np.cos(float(track.start_theta)), np.sin(float(track.start_theta))])
        # facing the travel direction = against the stored order (§5.8); after a reversal the
        # heading is the chord G0 -> G1 of the generated curve, the tangent the stored chord into G0
        assert heading @ np.asarray(geometry["tangent"](track, jnp.zeros((1,))))[0] > 0.5
        count = int(track.num_cones)
        local = body_frame(
            np.asarray(track.cone_xy[:count]), np.asarray(track.start_xy), float(track.start_theta)
        )
        dist_cones = np.linalg.norm(local, axis=1)
        types = np.asarray(track.cone_type[:count])
        right = local[types == T.CONE_TYPE_BLUE]
        left = local[types == T.CONE_TYPE_YELLOW]
        nearest_right = right[np.argmin(np.linalg.norm(right, axis=1))]
        nearest_left = left[np.argmin(np.linalg.norm(left, axis=1))]
        assert nearest_right[1] < -3.0 and nearest_left[1] > 3.0
        gaps.append([np.linalg.norm(nearest_right), np.linalg.norm(nearest_left)])
        assert dist_cones.min() > 3.4  # no cone touches the car at reset
    # cones 5 m apart on the 3.5 m offsets: nearest at 3.5 .. ~4.3 m on straights, more at bends
    gaps = np.asarray(gaps)
    assert np.all(gaps < 7.0) and np.median(gaps) < 4.3


# ------------------------------------------------------------------------------------------------
# determinism, jit / vmap, banks
# ------------------------------------------------------------------------------------------------


def test_bank_is_deterministic(generated):
    tracks = generated
    again = G.make_track_bank(BANK_KEY, NUM_GENERATED, batch_size=1)  # cached compile
    chex.assert_trees_all_equal(tracks, again)
    assert len({float(x) for x in np.asarray(tracks.length)}) == NUM_GENERATED  # keys differ
    with pytest.raises(ValueError, match="positive"):
        G.make_track_bank(BANK_KEY, 0)
    with pytest.raises(ValueError, match="positive"):
        G.make_track_bank(BANK_KEY, 4, batch_size=0)


def test_every_bank_size_reuses_the_one_compiled_generator(generated):
    """Banks of any size go through one compiled program (blocks of keys), and track i of a bank does
    not depend on the bank's size: a 3-track bank is the first 3 tracks of the 64-track one, bit for
    bit (the keys are a prefix: jax.random.split is partitionable)."""
    compiled = G._generate_block._cache_size()
    small = G.make_track_bank(BANK_KEY, 3, batch_size=1)
    assert G._generate_block._cache_size() == compiled
    chex.assert_trees_all_equal(small, jax.tree.map(lambda x: x[:3], generated))


@pytest.mark.slow
def test_vmapped_bank_equals_single_draws_and_attempt_statistics():
    """vmap inside the bank (batch_size > 1) gives the same tracks as jit(generate_track) on the
    same keys; rejection rate and attempts over 256 draws (§5.6: ~12 % rejected, mean 1.14)."""
    key = jax.random.key(7)
    bank = G.make_track_bank(key, 4, batch_size=2)
    single = jax.jit(G.generate_track)
    for i, k in enumerate(jax.random.split(key, 4)):
        track = single(k)
        assert int(track.num_points) == int(bank.num_points[i])
        np.testing.assert_allclose(np.asarray(track.centerline), np.asarray(bank.centerline[i]), atol=1e-3)
        np.testing.assert_array_equal(np.asarray(track.cone_present), np.asarray(bank.cone_present[i]))
    _, attempts, valid = jax.jit(lambda ks: jax.lax.map(G._generate, ks))(jax.random.split(key, 256))
    attempts, valid = np.asarray(attempts), np.asarray(valid)
    assert valid.all() and attempts.max() <= 4 and attempts.mean() < 1.3


@pytest.mark.slow
def test_generator_under_x64():
    with jax.enable_x64(True):
        track = jax.jit(G.generate_track)(jax.random.key(11))
        assert track.centerline.dtype == jnp.float64 and track.cone_type.dtype == jnp.int32
        line = ring_of(track)
        assert np_is_simple(line) and 120 <= line.shape[0] <= T.MAX_CENTERLINE
        assert 100 <= int(track.num_cones) <= T.MAX_CONES


# ------------------------------------------------------------------------------------------------
# generator pieces: closed forms
# ------------------------------------------------------------------------------------------------


def test_push_apart_moves_each_point_by_the_full_deficit():
    points = jnp.asarray([[0.0, 0.0], [5.0, 0.0], [100.0, 100.0]])
    pushed = np.asarray(jax.jit(S._push_apart)(points, jnp.int32(3)))
    np.testing.assert_allclose(pushed, [[-10.0, 0.0], [15.0, 0.0], [100.0, 100.0]], atol=1e-5)
    # points beyond `count` are left alone
    pushed = np.asarray(jax.jit(S._push_apart)(points.at[2].set([1.0, 0.0]), jnp.int32(2)))
    np.testing.assert_allclose(pushed[2], [1.0, 0.0])


def test_convex_hull_is_clockwise_and_contains_all_points():
    rng = np.random.default_rng(1)
    hull_fn = jax.jit(S._convex_hull)
    for count in (3, 10, 20):
        points = rng.uniform(0, 150, size=(20, 2))
        ids, h, ok = hull_fn(jnp.asarray(points, jnp.float32), jnp.int32(count))
        assert bool(ok)
        hull = points[np.asarray(ids)[: int(h)]]
        nxt = np.roll(hull, -1, axis=0)
        used = points[:count]
        cross = (nxt[:, None, 0] - hull[:, None, 0]) * (used[None, :, 1] - hull[:, None, 1]) - (
            nxt[:, None, 1] - hull[:, None, 1]
        ) * (used[None, :, 0] - hull[:, None, 0])
        assert np.all(cross <= 1e-3)  # every point on the right of (or on) every edge: clockwise hull
        assert int(np.argmin(used[:, 0])) == int(ids[0])
        # every point that is not a vertex lies strictly inside
        inner = np.setdiff1d(np.arange(count), np.asarray(ids)[: int(h)])
        assert np.all(cross[:, inner] < 0)


def test_spline_passes_through_control_points_and_reproduces_lines():
    rng = np.random.default_rng(2)
    control = rng.uniform(0, 150, size=(S.MAX_CONTROL_POINTS, 2))
    spline = jax.jit(S._catmull_rom)
    samples = np.asarray(spline(jnp.asarray(control, jnp.float32), jnp.int32(12)))
    for j in range(12):
        np.testing.assert_allclose(samples[j, 0], control[(j - 1) % 12], atol=1e-4)
        np.testing.assert_allclose(samples[j, -1], control[j], atol=1e-4)
    pyramid = jax.jit(S._barry_goldman)  # one compile: every call below has 12 rows
    c = [jnp.asarray(np.roll(control[:12], -k, axis=0), jnp.float32) for k in range(-2, 3)]
    # the Barry-Goldman pyramid itself interpolates its middle points (before the exact snap)
    np.testing.assert_allclose(
        np.asarray(pyramid(*c[:4], jnp.zeros(12))), control[np.arange(-1, 11) % 12], atol=1e-3
    )
    np.testing.assert_allclose(np.asarray(pyramid(*c[:4], jnp.ones(12))), control[:12], atol=1e-3)
    # equally spaced collinear points: a straight line with uniform samples (closed form)
    line = [jnp.broadcast_to(jnp.asarray([10.0 * k, 5.0 * k]), (12, 2)) for k in range(4)]
    frac = np.linspace(0, 1, 12)
    expected = np.asarray(line[1]) + frac[:, None] * (np.asarray(line[2]) - np.asarray(line[1]))
    np.testing.assert_allclose(
        np.asarray(pyramid(*line, jnp.asarray(frac, jnp.float32))), expected, atol=1e-3
    )
    # C1 at the junctions: the tangent just before C_j (end of segment j) and just after it
    # (start of segment j + 1) agree
    eps = 1e-3
    before = np.asarray(pyramid(c[0], c[1], c[2], c[3], jnp.full(12, 1 - eps)))
    after = np.asarray(pyramid(c[1], c[2], c[3], c[4], jnp.full(12, eps)))
    d_in, d_out = control[:12] - before, after - control[:12]
    cos = np.sum(d_in * d_out, axis=1) / np.linalg.norm(d_in, axis=1) / np.linalg.norm(d_out, axis=1)
    assert np.all(cos > 0.99)


def test_simplicity_check_detects_a_figure_eight():
    angle = np.linspace(0, 2 * np.pi, 200, endpoint=False) + 0.0123  # crossing not at a vertex
    circle = np.stack([50 * np.cos(angle), 50 * np.sin(angle)], axis=1)
    eight = np.stack([50 * np.sin(angle), 25 * np.sin(2 * angle)], axis=1)
    check = jax.jit(S._is_simple)
    for curve, simple in ((circle, True), (eight, False)):
        padded = np.concatenate([curve, np.repeat(curve[:1], S.MAX_DEDUP_POINTS - 200, axis=0)])
        assert bool(check(jnp.asarray(padded, jnp.float32), jnp.int32(200))) is simple
        assert np_is_simple(curve) is simple
