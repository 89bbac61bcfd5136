"""Hot-path geometry of the racing step on a track's ring tables (docs/carenv-single-agent.md §6).

:class:`RingTables` are per-track lookup tables derived once from a ``Track`` (:func:`ring_tables`);
:class:`TrackView` reads them at ``[track_index, i]`` without copying a bank track out. On them:
the exact global projection (:func:`project_point`, a branch and bound over chunks of segments),
ring points by arc length (:func:`points_at_arclength`), cone positions in the body frame and the
cone collision test (§6.3).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.track import CONE_RADIUS, TINY_SEGMENT, Track
from envs.vehicle_state import VEHICLE_HALF_LENGTH, VEHICLE_HALF_WIDTH, VehicleState, world_to_body


@struct.dataclass
class RingTables:
    """Per-track lookup tables for the hot path, derived from a ``Track`` by :func:`ring_tables`.

    Structure-of-arrays layout on purpose: XLA on CPU vectorises poorly over a trailing axis of 2,
    and an (N, 2) formulation of the projection is much slower. Segment i goes from vertex i to
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
    real = valid & (seg_len > TINY_SEGMENT)
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


def first_min_index(values):
    """Index of the first minimum; cheaper than argmin on XLA CPU, identical result."""
    smallest = jnp.min(values)
    return jnp.min(jnp.where(values == smallest, jnp.arange(values.shape[0]), values.shape[0]))


class TrackView(NamedTuple):
    """The episode's track as seen by a step, without copying it out of the bank.

    ``tables`` leaves are (M,) for a carried track (``row`` None) or (bank, M) for the whole bank,
    read at ``[row, index]``: a step then touches only the table entries it needs (gathering a bank
    track's whole tables every step makes the step memory bound).
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
    """``jnp.searchsorted`` on a table row (bisection reading O(log M) entries per query)."""
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


def segment_distances(view: TrackView, px, py, index):
    """Squared distance and parameter of the nearest point on segments ``index`` (the formula of §6.1)."""
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


def projection_at(view: TrackView, j, t_j, d2_j):
    """(s in [0, L), distance, travel tangent) of the point at parameter ``t_j`` of segment ``j``."""
    tables = view.tables
    lo, hi = view.take(tables.s_start, j), view.take(tables.s_end, j)
    s = jnp.clip((1 - t_j) * lo + t_j * hi, lo, hi)
    s = jnp.where(s >= view.length, s - view.length, s)
    lookup = jnp.minimum(_search(view, tables.s_end, s, right=False), view.size - 1)
    tangent = jnp.stack([view.take(tables.tangent_x, lookup), view.take(tables.tangent_y, lookup)])
    return s, jnp.sqrt(d2_j), tangent


def project_point(view: TrackView, px, py):
    """Global nearest point of the ring (§6.1): (s in [0, L), distance, travel tangent (2,)).

    Same formula and tie-break as the reference projection of §6.1 (the first of the nearest
    segments; a vertex belongs to the segment ending there); the tangent is the progress lookup.

    Exact branch and bound instead of brute force: segments come in chunks of ``CHUNK`` with
    bounding circles; ``|p - c| - r`` bounds every distance in a chunk from below, and chunks are
    evaluated in order of that bound until no unvisited chunk could hold a segment as near as (or
    nearer than) the best so far. Every segment that can win or tie is evaluated with the brute-force
    formula, so the answer is the global one (the tests compare it with a brute-force reference), but
    a step typically reads a few chunks instead of all segments. Under ``vmap`` the loop runs as many
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
        chunk = first_min_index(open_bound2).astype(jnp.int32)
        index = chunk * CHUNK + offsets
        d2, t = segment_distances(view, px, py, index)
        k = first_min_index(d2).astype(jnp.int32)
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
    return projection_at(view, best_j, best_t, best_d2)


def points_at_arclength(view: TrackView, arcs):
    """Ring points at stored-order arc lengths ``arcs`` (mod L), (linear interpolation, §7.3)."""
    tables = view.tables
    arcs = jnp.mod(arcs, view.length)
    k = jnp.minimum(_search(view, tables.s_end, arcs, right=True), view.num_points - 1)
    lo, hi = view.take(tables.s_start, k), view.take(tables.s_end, k)
    span = hi - lo
    t = jnp.clip(jnp.where(span > 0, (arcs - lo) / jnp.where(span > 0, span, 1), 0), 0, 1)
    x = (1 - t) * view.take(tables.start_x, k) + t * view.take(tables.end_x, k)
    y = (1 - t) * view.take(tables.start_y, k) + t * view.take(tables.end_y, k)
    return x, y


def cone_body_positions(view: TrackView, vehicle: VehicleState):
    """All cone centres in the body frame of the car (§6.3, §7.2)."""
    cones = jnp.arange(view.tables.cone_x.shape[-1])
    x_world, y_world = view.take(view.tables.cone_x, cones), view.take(view.tables.cone_y, cones)
    return world_to_body(x_world, y_world, vehicle.x, vehicle.y, vehicle.theta)


def cone_hits(bx, by):
    """Cone centres (body frame) inside the collision box dilated by the cone radius (§6.3)."""
    a, b, r = VEHICLE_HALF_LENGTH, VEHICLE_HALF_WIDTH, CONE_RADIUS
    candidate = (bx > -a - r) & (bx < a + r) & (by > -b - r) & (by < b + r)
    along = (bx > -a) & (bx < a) & (by > -b - r) & (by < b + r)
    across = (bx > -a - r) & (bx < a + r) & (by > -b) & (by < b)
    corner_dx = jnp.abs(bx) - a
    corner_dy = jnp.abs(by) - b
    corner = corner_dx * corner_dx + corner_dy * corner_dy < r * r
    return candidate & (along | across | corner)
