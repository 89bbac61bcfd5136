"""The racing problem of Country Road and Tracking (docs/carenv-single-agent.md §3, §6, §8).

Both scenarios drive the same car on the same kind of track; they differ only in whether cones
exist (and can be hit) and in the sensor that is observed. This module holds everything they share:
params, state, the exact step order of §3.2, progress reward, cone collisions, idling and time
limits with integer counters, metrics, the off-track termination that OVERWRITES the reward, and the
track source (bank drawn at reset, or generation inside reset). Subclasses only add the sensor.

Tracks: ``params.tracks`` is a ``Track`` with a leading bank axis (size >= 1). With
``track_source="bank"`` (default) reset draws a bank index uniformly; the state stores only that
index (cheap to auto-reset under ``vmap``). A user track (``track_from_arrays``) is simply a bank of
size one (:func:`with_track`). ``RacingEnv.prepare`` (called by ``envs.make``) precomputes each bank
track's reset observation, so reset is a gather. A step never copies the bank track out: it reads
the few table entries it needs at ``[track_index, i]`` (:class:`TrackView`), and the projection is an
exact branch and bound over chunks of segments (:func:`project_point`). With
``track_source="generate"`` reset calls ``generate_track`` and the state carries the whole track
(costly under auto-reset: under vmap the reset, i.e. a track generation, runs every step).

Info (fixed shapes, every step): ``avg_track_velocity`` (the original's Metric.AvgTrackVelocity),
``cones_hit`` (Metric.ConesHit, cumulative, always 0 for Tracking), ``done_reason``
(:data:`DONE_NONE`/``LEFT_TRACK``/``MAX_TIME``/``IDLING`` = 0/1/2/3, as in the golden data, and
:data:`NONFINITE_ACTION` = 4), ``time_limit_truncated`` (= truncated), ``track_progress`` (m along the
travel direction), ``proj_s`` and ``dist_center`` (nearest centre-line point arc length in stored
order, distance), ``nonfinite_action`` (bool).

Invalid actions: a diverged policy must not poison the state or hang the step, so an action with a
NaN or ±inf entry (after the cast to the env's float dtype; a discrete index outside [0, 12), or a
float index that is not finite, counts the same) ends the episode: the car is stepped with the
neutral control (steering 0, pedals released), ``terminated`` is True with ``done_reason`` 4 (it
overrides the other reasons), the reward is ``offtrack_reward`` and ``info["nonfinite_action"]`` is
True. Finite continuous actions outside [-1, 1] are clipped (§4.1), however large.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import actions as actions_mod
from envs import track as track_mod
from envs.core import Box, Dict, Discrete, Environment, default_float
from envs.track import Track
from envs.vehicle import VehicleParams, VehicleState, odometry_observation, vehicle_step

DONE_NONE, LEFT_TRACK, MAX_TIME, IDLING, NONFINITE_ACTION = 0, 1, 2, 3, 4
DONE_REASONS = {
    DONE_NONE: "",
    LEFT_TRACK: "LeftTrack",
    MAX_TIME: "MaxTime",
    IDLING: "Idling",
    NONFINITE_ACTION: "NonFiniteAction",
}

# Collision box of the car around the CoG (§1.1) and cone radius (§5.7).
_BOX_HALF_LENGTH = 1.905
_BOX_HALF_WIDTH = 0.74
_CONE_RADIUS = 0.3


@struct.dataclass
class RingTables:
    """Per-track lookup tables for the hot path, derived from a ``Track`` by :func:`ring_tables`.

    Structure-of-arrays layout on purpose: XLA on CPU vectorises poorly over a trailing axis of 2,
    and the (N, 2) formulation of the projection ran ~40x slower. Segment i goes from vertex i to
    vertex i+1 of the padded ring (``Track`` pads with the first point, so padding segments have
    zero length). ``tangent_*[i]`` is the travel tangent used when the progress lookup lands on
    index i: minus the direction of the first real (>= 1e-9 m) segment at index >= i (§6.1),
    or of the last real segment when there is none.
    """

    start_x: jax.Array
    start_y: jax.Array
    end_x: jax.Array
    end_y: jax.Array
    edge_x: jax.Array
    edge_y: jax.Array
    len2: jax.Array
    s_start: jax.Array  # cumlen[:-1]
    s_end: jax.Array  # cumlen[1:]
    valid: jax.Array  # i < num_points
    tangent_x: jax.Array
    tangent_y: jax.Array
    cone_x: jax.Array
    cone_y: jax.Array
    chunk_x: jax.Array  # (MAX_CENTERLINE // CHUNK,) bounding circle of each chunk of segments
    chunk_y: jax.Array
    chunk_r: jax.Array  # inflated so that |p - c| - r is a strict lower bound; -inf: empty chunk


CHUNK = 16  # segments per chunk of the branch-and-bound projection


def _chunk_circles(start, end, valid):
    """Bounding circles of consecutive chunks of CHUNK segments (centre of the endpoints' bbox)."""
    shape = (start.shape[0] // CHUNK, CHUNK, 2)
    xs = jnp.stack([start[:, 0], end[:, 0]], -1).reshape(shape)
    ys = jnp.stack([start[:, 1], end[:, 1]], -1).reshape(shape)
    ok = jnp.repeat(valid[:, None], 2, axis=-1).reshape(shape)
    big = jnp.asarray(jnp.inf, start.dtype)
    lo_x, hi_x = jnp.min(jnp.where(ok, xs, big), (1, 2)), jnp.max(jnp.where(ok, xs, -big), (1, 2))
    lo_y, hi_y = jnp.min(jnp.where(ok, ys, big), (1, 2)), jnp.max(jnp.where(ok, ys, -big), (1, 2))
    any_valid = jnp.any(ok, axis=(1, 2))
    cx = jnp.where(any_valid, (lo_x + hi_x) / 2, 0)
    cy = jnp.where(any_valid, (lo_y + hi_y) / 2, 0)
    spread = jnp.where(ok, (xs - cx[:, None, None]) ** 2 + (ys - cy[:, None, None]) ** 2, 0)
    radius = jnp.sqrt(jnp.max(spread, (1, 2))) * (1 + 1e-6) + 1e-6  # margin for rounding
    return cx, cy, jnp.where(any_valid, radius, -jnp.inf)


def ring_tables(track: Track) -> RingTables:
    """Derive the hot-path tables of one (un-batched) track; ``jax.vmap`` it over a bank."""
    start = track.centerline
    count = start.shape[0]
    end = jnp.roll(start, -1, axis=0)
    edge = end - start
    len2 = edge[:, 0] * edge[:, 0] + edge[:, 1] * edge[:, 1]
    index = jnp.arange(count)
    valid = index < track.num_points
    seg_len = jnp.sqrt(len2)
    real = valid & (seg_len > track_mod.TINY_SEGMENT)
    last_real = count - 1 - jnp.argmax(real[::-1])
    next_real = jax.lax.cummin(jnp.where(real, index, count), reverse=True)
    use = jnp.where(next_real < count, next_real, last_real)
    safe_len = jnp.where(seg_len[use] > 0, seg_len[use], 1.0)
    chunk_x, chunk_y, chunk_r = _chunk_circles(start, end, valid)
    return RingTables(
        start_x=start[:, 0],
        start_y=start[:, 1],
        end_x=end[:, 0],
        end_y=end[:, 1],
        edge_x=edge[:, 0],
        edge_y=edge[:, 1],
        len2=len2,
        s_start=track.cumlen[:-1],
        s_end=track.cumlen[1:],
        valid=valid,
        tangent_x=-edge[use, 0] / safe_len,
        tangent_y=-edge[use, 1] / safe_len,
        cone_x=track.cone_xy[:, 0],
        cone_y=track.cone_xy[:, 1],
        chunk_x=chunk_x,
        chunk_y=chunk_y,
        chunk_r=chunk_r,
    )


@struct.dataclass
class RacingParams:
    """Everything configurable about a racing episode. Numeric leaves may be traced (vmapped sweeps).

    ``tracks`` is a bank with a leading axis and ``tables`` its :class:`RingTables` (same axis; use
    :func:`with_bank` / :func:`with_track` to set both). ``track_source`` is static.
    """

    vehicle: VehicleParams
    tracks: Track | None
    tables: RingTables | None = None
    start_s: jax.Array | None = None  # (bank,) start arc lengths, from RacingEnv.prepare
    reset_obs: dict | None = None  # (bank, ...) reset observations, from RacingEnv.prepare
    k_forwards: float = 0.1
    k_base: float = 0.0
    k_center: float = 0.0
    cone_penalty: float = 0.2
    offtrack_reward: float = -1.0
    track_width: float = 8.0
    idle_speed: float = 0.1
    max_steps: int = 600  # MaxTime truncation at this step count (60 s / 0.1 s)
    max_idle_steps: int = 51  # Idling truncation at this many consecutive idle steps (> 5 s)
    # Cone sensor (Country Road): strict bbox in the body frame and the single normaliser.
    cone_bbox: tuple = (-15.0, 45.0, -30.0, 30.0)
    cone_normaliser: float = 45.0
    # Trajectory sensor (Tracking): spacing of the lookahead points along the centre line.
    lookahead_spacing: float = 2.0
    track_source: str = struct.field(pytree_node=False, default="bank")

    @property
    def bank_size(self) -> int:
        return 0 if self.tracks is None else int(self.tracks.num_points.shape[0])


@struct.dataclass
class RacingState:
    """Per-episode state. ``track``/``tables`` are only carried with ``track_source="generate"``."""

    vehicle: VehicleState
    track_index: jax.Array  # int32, index into params.tracks
    track: Track | None
    tables: RingTables | None
    cone_alive: jax.Array  # (MAX_CONES,) bool: present on the track and not hit yet
    step_count: jax.Array  # int32
    idle_count: jax.Array  # int32, consecutive idle steps
    prev_xy: jax.Array  # (2,) CoG at the previous step
    prev_s: jax.Array  # projection arc length at the previous step
    track_progress: jax.Array  # m along the travel direction
    velocity_sum: jax.Array  # sum of per-step along-track speeds (for the running mean)
    cones_hit: jax.Array  # int32, cumulative


def stack_tracks(tracks) -> Track:
    """Stack single tracks into a bank (leading axis)."""
    tracks = list(tracks)
    if not tracks or not all(isinstance(t, Track) for t in tracks):
        raise ValueError("stack_tracks needs a non-empty sequence of Track")
    return jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *tracks)


def with_bank(params: RacingParams, bank: Track) -> RacingParams:
    """Params drawing from ``bank`` (a ``Track`` with a leading axis) at every reset."""
    if not isinstance(bank, Track) or jnp.ndim(bank.num_points) != 1:
        raise ValueError("bank must be a Track with a leading bank axis (see stack_tracks / make_track_bank)")
    tables = jax.jit(jax.vmap(ring_tables))(bank)
    return params.replace(tracks=bank, tables=tables, start_s=None, reset_obs=None, track_source="bank")


def with_track(params: RacingParams, track: Track) -> RacingParams:
    """Params whose bank holds exactly ``track`` (a single, un-batched ``Track``), e.g. for replays."""
    if not isinstance(track, Track) or jnp.ndim(track.num_points) != 0:
        raise ValueError("with_track needs a single (un-batched) Track, e.g. from track_from_arrays")
    return with_bank(params, stack_tracks([track]))


# --------------------------------------------------------------------------------------------
# Geometry helpers (same arithmetic as envs.track, on the structure-of-arrays tables)
# --------------------------------------------------------------------------------------------


def _first_min_index(values):
    """Index of the first minimum; cheaper than argmin on XLA CPU, identical result."""
    smallest = jnp.min(values)
    return jnp.min(jnp.where(values == smallest, jnp.arange(values.shape[0]), values.shape[0]))


class TrackView(NamedTuple):
    """The episode's track as seen by a step, without copying it out of the bank.

    ``tables`` leaves are (M,) for a carried track (``row`` None) or (bank, M) for the whole bank,
    read at ``[row, index]``: a step then touches only the table entries it needs (a bank track's
    tables are ~40 KB, and gathering them all every step made the step memory bound).
    """

    tables: RingTables
    row: jax.Array | None
    length: jax.Array
    num_points: jax.Array
    cone_type: jax.Array

    def take(self, leaf, index):
        return leaf[index] if self.row is None else leaf[self.row, index]

    @property
    def size(self) -> int:
        return self.tables.start_x.shape[-1]


def _search(view: TrackView, leaf, values, right: bool):
    """``jnp.searchsorted`` on a table row (bisection reading only ~10 entries per query)."""
    size = view.size
    lo = jnp.zeros(jnp.shape(values), jnp.int32)
    hi = jnp.full(jnp.shape(values), size, jnp.int32)
    for _ in range(int(np.ceil(np.log2(size + 1)))):
        active = lo < hi
        mid = (lo + hi) // 2
        entry = view.take(leaf, jnp.minimum(mid, size - 1))
        go_right = (entry <= values) if right else (entry < values)
        lo = jnp.where(active & go_right, mid + 1, lo)
        hi = jnp.where(active & ~go_right, mid, hi)
    return lo


def _segment_d2(view: TrackView, px, py, index):
    """Squared distance and parameter of the nearest point on segments ``index`` (envs.track's formula)."""
    tables = view.tables
    sx, sy = view.take(tables.start_x, index), view.take(tables.start_y, index)
    ex, ey = view.take(tables.edge_x, index), view.take(tables.edge_y, index)
    len2 = view.take(tables.len2, index)
    positive = len2 > 0
    t = jnp.where(positive, ((px - sx) * ex + (py - sy) * ey) / jnp.where(positive, len2, 1), 0)
    t = jnp.clip(t, 0, 1)
    cx = (1 - t) * sx + t * view.take(tables.end_x, index)
    cy = (1 - t) * sy + t * view.take(tables.end_y, index)
    d2 = (px - cx) ** 2 + (py - cy) ** 2
    return jnp.where(view.take(tables.valid, index), d2, jnp.inf), t


def _finish_projection(view: TrackView, j, t_j, d2_j):
    tables = view.tables
    lo, hi = view.take(tables.s_start, j), view.take(tables.s_end, j)
    s = jnp.clip((1 - t_j) * lo + t_j * hi, lo, hi)
    s = jnp.where(s >= view.length, s - view.length, s)
    lookup = jnp.minimum(_search(view, tables.s_end, s, right=False), view.size - 1)
    tangent = jnp.stack([view.take(tables.tangent_x, lookup), view.take(tables.tangent_y, lookup)])
    return s, jnp.sqrt(d2_j), tangent


def project_point_global(view: TrackView, px, py):
    """Global nearest point of the ring by brute force over all segments (reference for tests)."""
    d2, t = _segment_d2(view, px, py, jnp.arange(view.size))
    j = _first_min_index(d2)
    return _finish_projection(view, j, t[j], d2[j])


def project_point(view: TrackView, px, py):
    """Global nearest point of the ring (§6.1): (s in [0, L), distance, travel tangent (2,)).

    Same formula and tie-break as ``envs.track.project`` (the first of the nearest segments; a vertex
    belongs to the segment ending there); the tangent is the progress lookup of §6.1.

    Exact branch and bound instead of brute force: segments come in chunks of ``CHUNK`` with
    bounding circles; ``|p - c| - r`` bounds every distance in a chunk from below, and chunks are
    evaluated in order of that bound until no unvisited chunk could hold a segment as near as (or
    nearer than) the best so far. Every segment that can win or tie is evaluated with the brute-force
    formula, so the answer is the global one (tests compare with :func:`project_point_global`), but a
    step reads ~3 chunks of 16 segments instead of all 800. Under ``vmap`` the loop runs as many
    rounds as the slowest env of the batch needs.

    The loop runs at most once per chunk, for every input. A position that is not finite, or so far
    away that a squared distance overflows, is infinitely far from the ring: distance ``inf``, s = 0
    and the tangent at s = 0 (the racing step then reports it as off the track).
    """
    tables = view.tables
    chunks = jnp.arange(tables.chunk_x.shape[-1])
    cx, cy, cr = (
        view.take(tables.chunk_x, chunks),
        view.take(tables.chunk_y, chunks),
        view.take(tables.chunk_r, chunks),
    )
    bound = jnp.maximum(jnp.sqrt((px - cx) ** 2 + (py - cy) ** 2) - cr, 0)
    bound2 = jnp.where(jnp.isfinite(cr), bound * bound, jnp.inf)
    inf = jnp.asarray(jnp.inf, bound2.dtype)
    offsets = jnp.arange(CHUNK, dtype=jnp.int32)

    num_chunks = chunks.shape[0]

    def pending(carry):
        # Trip bound: a visit closes its chunk (bound -> inf), and once best_d2 is finite a closed chunk
        # never qualifies again, so a finite position visits each chunk at most once and stops by
        # itself within num_chunks rounds (its first visit, the lowest bound, is a chunk with a valid
        # segment and makes best_d2 finite). A non-finite position (or an overflowing d2) never finds
        # a finite best_d2, and without the counter it would revisit the closed chunks forever.
        return jnp.any(carry[0] <= carry[1]) & (carry[4] < num_chunks)

    def visit(carry):
        open_bound2, best_d2, best_j, best_t, rounds = carry
        chunk = _first_min_index(open_bound2).astype(jnp.int32)
        index = chunk * CHUNK + offsets
        d2, t = _segment_d2(view, px, py, index)
        k = _first_min_index(d2).astype(jnp.int32)
        better = (d2[k] < best_d2) | ((d2[k] == best_d2) & (index[k] < best_j))
        return (
            jnp.where(chunks == chunk, inf, open_bound2),
            jnp.where(better, d2[k], best_d2),
            jnp.where(better, index[k], best_j),
            jnp.where(better, t[k], best_t),
            rounds + 1,
        )

    start = (bound2, inf, jnp.asarray(view.size, jnp.int32), jnp.zeros_like(bound2[0]), jnp.int32(0))
    _, best_d2, best_j, best_t, _ = jax.lax.while_loop(pending, visit, start)
    # No finite distance (non-finite position): segment 0 at t = 0, distance sqrt(inf) = inf. (The
    # tie-break may have recorded an inf-distance segment with a NaN t; that is discarded here.)
    found = jnp.isfinite(best_d2)
    best_j, best_t = jnp.where(found, best_j, 0), jnp.where(found, best_t, 0)
    return _finish_projection(view, best_j, best_t, best_d2)


def points_at_arclength(view: TrackView, arcs):
    """Ring points at stored-order arc lengths ``arcs`` (mod L), as ``envs.track.point_at_arclength``."""
    tables = view.tables
    arcs = jnp.mod(arcs, view.length)
    k = jnp.minimum(_search(view, tables.s_end, arcs, right=True), view.num_points - 1)
    lo, hi = view.take(tables.s_start, k), view.take(tables.s_end, k)
    span = hi - lo
    t = jnp.clip(jnp.where(span > 0, (arcs - lo) / jnp.where(span > 0, span, 1), 0), 0, 1)
    x = (1 - t) * view.take(tables.start_x, k) + t * view.take(tables.end_x, k)
    y = (1 - t) * view.take(tables.start_y, k) + t * view.take(tables.end_y, k)
    return x, y


def _to_body(x_world, y_world, x, y, theta):
    """World points into the body frame of pose (x, y, theta): B(theta)(P - p) (§0)."""
    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    dx, dy = x_world - x, y_world - y
    return cos_t * dx + sin_t * dy, -sin_t * dx + cos_t * dy


def cone_body_positions(view: TrackView, vehicle: VehicleState):
    """All cone centres in the body frame of the car (§6.3, §7.2)."""
    cones = jnp.arange(view.tables.cone_x.shape[-1])
    x_world, y_world = view.take(view.tables.cone_x, cones), view.take(view.tables.cone_y, cones)
    return _to_body(x_world, y_world, vehicle.x, vehicle.y, vehicle.theta)


def _cone_hits(bx, by):
    """Cone centres (body frame) inside the collision box dilated by the cone radius (§6.3)."""
    a, b, r = _BOX_HALF_LENGTH, _BOX_HALF_WIDTH, _CONE_RADIUS
    candidate = (bx > -a - r) & (bx < a + r) & (by > -b - r) & (by < b + r)
    along = (bx > -a) & (bx < a) & (by > -b - r) & (by < b + r)
    across = (bx > -a - r) & (bx < a + r) & (by > -b) & (by < b)
    corner_dx = jnp.abs(bx) - a
    corner_dy = jnp.abs(by) - b
    corner = corner_dx * corner_dx + corner_dy * corner_dy < r * r
    return candidate & (along | across | corner)


# --------------------------------------------------------------------------------------------
# The environment
# --------------------------------------------------------------------------------------------


class RacingEnv(Environment):
    """Shared racing logic; subclasses set ``has_cones`` and implement ``_sensor``/``_sensor_space``.

    ``discrete=True`` selects the paper's 12-way action table (§4.2); otherwise the action is
    the native Box(-1, 1, (3,)) (steer, throttle pedal, brake pedal) of §4.1.
    """

    has_cones: bool = True
    sensor_key: str = ""

    def __init__(self, discrete: bool = False):
        self.discrete = bool(discrete)

    def _config(self) -> tuple:
        """Static configuration; equal configs hash equal, so jit caches are shared between instances."""
        return (type(self), self.discrete)

    def __eq__(self, other) -> bool:
        return isinstance(other, RacingEnv) and self._config() == other._config()

    def __hash__(self) -> int:
        return hash(self._config())

    def __repr__(self) -> str:
        return f"{type(self).__name__}(discrete={self.discrete})"

    # ----- to implement in the scenarios -----
    def _sensor(self, params: RacingParams, view: TrackView, vehicle: VehicleState, cone_alive, s):
        raise NotImplementedError

    def _sensor_space(self, params: RacingParams | None):
        raise NotImplementedError

    # ----- API -----
    @property
    def name(self) -> str:
        return type(self).__name__ + ("Discrete" if self.discrete else "")

    @property
    def default_params(self) -> RacingParams:
        raise NotImplementedError("use envs.make(...) to get params with a track bank")

    def action_space(self, params: RacingParams | None = None):
        if self.discrete:
            return Discrete(actions_mod.NUM_DISCRETE_ACTIONS)
        return Box(-1.0, 1.0, (3,), jnp.float32)

    def observation_space(self, params: RacingParams | None = None):
        return Dict({"state": Box(-1.0, 1.0, (6,), jnp.float32), self.sensor_key: self._sensor_space(params)})

    def current_track(self, state: RacingState, params: RacingParams) -> Track:
        """The episode's full ``Track`` (from the bank by index, or carried in the state)."""
        if state.track is not None:
            return state.track
        return jax.tree.map(lambda leaf: leaf[state.track_index], params.tracks)

    def _view(self, state: RacingState, params: RacingParams) -> TrackView:
        if state.track is not None:
            track = state.track
            return TrackView(state.tables, None, track.length, track.num_points, track.cone_type)
        tracks, row = params.tracks, state.track_index
        if params.tables is None:  # params built by hand: derive the tables of this track (slow)
            track = self.current_track(state, params)
            return TrackView(ring_tables(track), None, track.length, track.num_points, track.cone_type)
        return TrackView(
            params.tables, row, tracks.length[row], tracks.num_points[row], tracks.cone_type[row]
        )

    def _control(self, action):
        if self.discrete:
            return actions_mod.discrete_to_control(jnp.asarray(action, jnp.int32))
        return actions_mod.continuous_to_control(jnp.asarray(action, default_float()))

    def _checked_control(self, action):
        """``(control, invalid)``: the control, or the neutral zeros when the action is invalid
        (non-finite, or a discrete index outside the table; see the module docstring)."""
        if self.discrete:
            invalid = actions_mod.invalid_discrete_index(action)
        else:
            invalid = ~jnp.all(jnp.isfinite(jnp.asarray(action, default_float())))
        control = self._control(action)
        return jnp.where(invalid, jnp.zeros_like(control), control), invalid

    def _observation(self, params, view, vehicle, cone_alive, s) -> dict[str, jax.Array]:
        return {
            "state": odometry_observation(params.vehicle, vehicle),
            self.sensor_key: self._sensor(params, view, vehicle, cone_alive, s),
        }

    def _start(self, params: RacingParams, track: Track, tables: RingTables):
        """Reset observation and start arc length of a track (depends on nothing else)."""
        dtype = default_float()
        start = jnp.asarray(track.start_xy, dtype)
        vehicle = VehicleState.at_pose(start[0], start[1], track.start_theta)
        view = TrackView(tables, None, track.length, track.num_points, track.cone_type)
        s, _, _ = project_point(view, start[0], start[1])
        return self._observation(params, view, vehicle, self._initial_cones(track), s), s

    def _initial_cones(self, track: Track):
        alive = jnp.asarray(track.cone_present, bool)
        return alive if self.has_cones else jnp.zeros_like(alive)

    def prepare(self, params: RacingParams) -> RacingParams:
        """Precompute each bank track's reset observation and start arc length (makes reset a gather).

        ``envs.make`` calls this; call it again after replacing ``params.tracks`` (``with_bank``).
        Without it, reset computes them on the fly (correct, but slower under auto-reset + vmap).
        """
        if params.track_source != "bank" or params.tracks is None:
            return params
        if params.tables is None:
            params = with_bank(params, params.tracks)
        obs, s = _start_bank(self, params)
        return params.replace(start_s=s, reset_obs=obs)

    def reset_env(self, key: jax.Array, params: RacingParams):
        dtype = default_float()
        if params.track_source == "generate":
            track = track_mod.generate_track(key)
            tables = ring_tables(track)
            index = jnp.zeros((), jnp.int32)
            carried = (track, tables)
            obs, s = self._start(params, track, tables)
        elif params.track_source == "bank":
            if params.tracks is None:
                raise ValueError("track_source='bank' needs params.tracks (a bank of at least one track)")
            index = jax.random.randint(key, (), 0, params.bank_size, dtype=jnp.int32)
            pick = lambda leaf: leaf[index]
            carried = (None, None)
            cached = params.reset_obs is not None and self.sensor_key in params.reset_obs
            if cached:
                track = params.tracks.replace(
                    start_xy=pick(params.tracks.start_xy),
                    start_theta=pick(params.tracks.start_theta),
                    cone_present=pick(params.tracks.cone_present),
                )
                obs = {
                    "state": pick(params.reset_obs["state"]),
                    self.sensor_key: pick(params.reset_obs[self.sensor_key]),
                }
                s = pick(params.start_s)
            else:
                track = jax.tree.map(pick, params.tracks)
                tables = ring_tables(track) if params.tables is None else jax.tree.map(pick, params.tables)
                obs, s = self._start(params, track, tables)
        else:
            raise ValueError(f"track_source must be 'bank' or 'generate', got {params.track_source!r}")
        start = jnp.asarray(track.start_xy, dtype)
        zero = jnp.zeros((), dtype)
        state = RacingState(
            vehicle=VehicleState.at_pose(start[0], start[1], track.start_theta),
            track_index=index,
            track=carried[0],
            tables=carried[1],
            cone_alive=self._initial_cones(track),
            step_count=jnp.zeros((), jnp.int32),
            idle_count=jnp.zeros((), jnp.int32),
            prev_xy=start,
            prev_s=jnp.asarray(s, dtype),
            track_progress=zero,
            velocity_sum=zero,
            cones_hit=jnp.zeros((), jnp.int32),
        )
        return obs, state

    def step_env(self, key: jax.Array, state: RacingState, action: Any, params: RacingParams):
        del key  # the racing dynamics are deterministic
        dtype = default_float()
        view = self._view(state, params)
        vp = params.vehicle
        dt = jnp.asarray(vp.dt, dtype)

        # 1-3: action mapping, counter, vehicle update.
        control, invalid = self._checked_control(action)
        step_count = state.step_count + 1
        vehicle = vehicle_step(vp, state.vehicle, control)
        position = jnp.stack([vehicle.x, vehicle.y])

        # 4: cone collisions against the new pose; hit cones are removed for good.
        if self.has_cones:
            bx, by = cone_body_positions(view, vehicle)
            hit = state.cone_alive & _cone_hits(bx, by)
            cone_alive = state.cone_alive & ~hit
            hits = jnp.sum(hit, dtype=jnp.int32)
        else:
            cone_alive = state.cone_alive
            hits = jnp.zeros((), jnp.int32)
        cones_hit = state.cones_hit + hits

        # 6 (geometry first; the sensor of step 5 reuses the projection).
        s, distance, tangent = project_point(view, vehicle.x, vehicle.y)
        reward = (
            -params.cone_penalty * hits
            + params.k_base
            + params.k_forwards * dt * (vehicle.vx * tangent[0] + vehicle.vy * tangent[1])
            - params.k_center * dt * distance
        )
        moved = jnp.sqrt(jnp.sum((position - state.prev_xy) ** 2))
        idle_count = jnp.where(moved / dt < params.idle_speed, state.idle_count + 1, 0)
        along = jnp.mod(state.prev_s - s, view.length)
        along = jnp.where(along > view.length / 2, along - view.length, along)
        velocity_sum = state.velocity_sum + along / dt
        avg_track_velocity = velocity_sum / step_count

        # Exactly one ending reason, in the priority order of §3.3.
        left_track = distance > params.track_width / 2
        max_time = step_count >= params.max_steps
        idling = idle_count >= params.max_idle_steps
        reason = jnp.where(
            left_track, LEFT_TRACK, jnp.where(max_time, MAX_TIME, jnp.where(idling, IDLING, DONE_NONE))
        )
        reason = jnp.where(invalid, NONFINITE_ACTION, reason).astype(jnp.int32)
        terminated = left_track | invalid
        truncated = ~terminated & (max_time | idling)
        reward = jnp.where(terminated, params.offtrack_reward, reward).astype(dtype)

        # 5: observation from the new state and the remaining cones.
        obs = self._observation(params, view, vehicle, cone_alive, s)

        new_state = state.replace(
            vehicle=vehicle,
            cone_alive=cone_alive,
            step_count=step_count,
            idle_count=idle_count.astype(jnp.int32),
            prev_xy=position,
            prev_s=s,
            track_progress=state.track_progress + along,
            velocity_sum=velocity_sum,
            cones_hit=cones_hit,
        )
        info = {
            "avg_track_velocity": avg_track_velocity,
            "cones_hit": cones_hit,
            "done_reason": reason,
            "time_limit_truncated": truncated,
            "track_progress": new_state.track_progress,
            "proj_s": s,
            "dist_center": distance,
            "nonfinite_action": invalid,
        }
        return obs, new_state, reward, terminated, truncated, info


@functools.partial(jax.jit, static_argnums=0)
def _start_bank(env: RacingEnv, params: RacingParams):
    return jax.vmap(env._start, in_axes=(None, 0, 0))(params, params.tracks, params.tables)


def check_action(env: RacingEnv, action) -> np.ndarray:
    """Host-side validation used by the Gymnasium adaptors: raises ValueError outside the space, on
    NaN/inf, and on a complex action (casting would silently drop its imaginary part)."""
    arr = np.asarray(action)
    if np.iscomplexobj(arr):
        raise ValueError(f"action must be real, got complex dtype {arr.dtype}: {action!r}")
    if env.discrete:
        n = actions_mod.NUM_DISCRETE_ACTIONS
        if arr.shape != () or not np.issubdtype(arr.dtype, np.integer) or not 0 <= int(arr) < n:
            raise ValueError(f"action must be an integer in [0, {n}), got {action!r}")
        return arr.astype(np.int32)
    if arr.shape != (3,) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"action must be a numeric array of shape (3,), got {action!r}")
    if np.any(~np.isfinite(arr)) or np.any(np.abs(arr) > 1.0):
        raise ValueError(f"action must lie in [-1, 1]^3 and be finite, got {action!r}")
    return arr.astype(np.float32)
