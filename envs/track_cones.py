"""Cones along a generated centre line (docs/carenv-single-agent.md §5.7), in fixed shapes.

Instead of a polygon buffer, the 3.5 m offset curves are built from candidate points (offset
segment midpoints, round-join arcs on the convex side of every vertex, the miter corner on the
concave side); candidates closer than 3.5 m - `CONE_TRIM_TOL` to the centre line are trimmed (they
lie in the overlapping loops of tight corners or pinch points), the rest is resampled every 5 m by
arc length and each cone is finally moved radially onto the 3.5 m offset. The exterior ring is
stored first, as in the original; the ring start points are arbitrary (as in the original). Cones
are coloured by the driver's side (type 1 = blue = right, type 2 = yellow = left), the net rule of
§5.8.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from envs.track import CONE_TYPE_BLUE, CONE_TYPE_YELLOW, MAX_CONES
from envs.track_shape import SEG_BLOCK, cross_2d, ring_cumlen

CONE_WIDTH = 7.0
CONE_SPACING = 5.0
CONE_TRIM_TOL = 0.05
_POINT_BLOCK = 240  # (_JOIN_SLOTS + 1) * MAX_DEDUP_POINTS = 19 blocks
_JOIN_SLOTS = 5  # candidate points per round join of the cone offset curves


def _rotate(vec: jax.Array, angle: jax.Array) -> jax.Array:
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * vec[..., 0] - s * vec[..., 1], s * vec[..., 0] + c * vec[..., 1]], axis=-1)


def _offset_candidates(ring: jax.Array, count: jax.Array, half_width: float):
    """Candidate points of the left (+) and right (-) offset curves in ring order.

    Per vertex k five join slots, then the midpoint of segment k shifted along its normal. On the
    convex side of the vertex the join slots trace the round-join arc from the previous segment's
    normal to the next one's; on the concave side the offset segments overlap, and the buffer's
    boundary has a corner where the two offset lines meet (the miter point, middle slot; the other
    slots are unused, as they would make the ring zig-zag back and forth). Returns
    (left, right, left_ok, right_ok) with shapes (6 * MAX_DEDUP_POINTS, 2) and (6 * MAX_DEDUP_POINTS,)."""
    size = ring.shape[0]
    ids = jnp.arange(size)
    following = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    edge = following - ring
    norm = jnp.linalg.norm(edge, axis=-1, keepdims=True)
    unit = edge / jnp.where(norm > 0, norm, 1)
    normal = jnp.stack([-unit[:, 1], unit[:, 0]], axis=-1)  # left normal
    prev_normal = normal[jnp.where(ids > 0, ids - 1, count - 1)]
    turn = jnp.arctan2(cross_2d(prev_normal, normal), jnp.sum(prev_normal * normal, axis=-1))
    fractions = jnp.linspace(0.0, 1.0, _JOIN_SLOTS, dtype=ring.dtype)
    arc_dirs = _rotate(prev_normal[:, None, :], turn[:, None] * fractions[None, :])  # (size, slots, 2)
    bisector = prev_normal + normal
    bis2 = jnp.sum(bisector * bisector, axis=-1, keepdims=True)
    miter_ok = bis2[:, 0] > 1.0  # turn below 120 degrees; sharper concave joins are trimmed anyway
    miter = 2 * bisector / jnp.where(miter_ok[:, None], bis2, 1)
    mid_base = (0.5 * (ring + following))[:, None]
    used = ids < count
    slot = jnp.arange(_JOIN_SLOTS + 1)
    middle = _JOIN_SLOTS // 2

    def side(sign):
        convex = sign * turn <= 0  # left side is convex for a right (clockwise) turn
        join = jnp.where(convex[:, None, None], arc_dirs, miter[:, None, :])
        dirs = jnp.concatenate([join, normal[:, None, :]], axis=1)  # (size, slots + 1, 2)
        base = jnp.concatenate([jnp.repeat(ring[:, None, :], _JOIN_SLOTS, axis=1), mid_base], axis=1)
        points = (base + sign * half_width * dirs).reshape(-1, 2)
        ok = (
            (slot[None, :] == _JOIN_SLOTS) | convex[:, None] | ((slot[None, :] == middle) & miter_ok[:, None])
        )
        return points, (used[:, None] & ok).reshape(-1)

    left, left_ok = side(1.0)
    right, right_ok = side(-1.0)
    return left, right, left_ok, right_ok


def _distance_to_ring(points: jax.Array, num_points: jax.Array, ring: jax.Array, count: jax.Array):
    """Distance of the first `num_points` points to the closed polyline of the first `count` ring
    vertices (rows beyond `num_points` get +inf).

    Blocked loops with data-dependent trip counts: a typical track uses about a third of the
    fixed capacity, so only the used blocks of the (points x segments) table are computed."""
    ids = jnp.arange(ring.shape[0])
    nxt = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    edge_x, edge_y = (nxt - ring).T
    len2 = edge_x * edge_x + edge_y * edge_y
    inv_len2 = jnp.where(len2 > 0, 1 / jnp.where(len2 > 0, len2, 1), 0)
    seg_ok = ids < count
    n_seg_blocks = (count + SEG_BLOCK - 1) // SEG_BLOCK
    n_pt_blocks = (num_points + _POINT_BLOCK - 1) // _POINT_BLOCK

    def seg_block(sb, best, px, py):
        lo = sb * SEG_BLOCK
        sl = functools.partial(jax.lax.dynamic_slice_in_dim, start_index=lo, slice_size=SEG_BLOCK)
        ax, ay, ex, ey, inv, ok = (sl(v) for v in (ring[:, 0], ring[:, 1], edge_x, edge_y, inv_len2, seg_ok))
        rx = px[:, None] - ax[None, :]
        ry = py[:, None] - ay[None, :]
        t = jnp.clip((rx * ex + ry * ey) * inv, 0, 1)
        dx = rx - t * ex
        dy = ry - t * ey
        d2 = jnp.where(ok[None, :], dx * dx + dy * dy, jnp.inf)
        return jnp.minimum(best, jnp.min(d2, axis=1))

    def point_block(pb, out):
        px = jax.lax.dynamic_slice_in_dim(points[:, 0], pb * _POINT_BLOCK, _POINT_BLOCK)
        py = jax.lax.dynamic_slice_in_dim(points[:, 1], pb * _POINT_BLOCK, _POINT_BLOCK)
        init = jnp.full((_POINT_BLOCK,), jnp.inf, points.dtype)
        best = jax.lax.fori_loop(0, n_seg_blocks, lambda sb, b: seg_block(sb, b, px, py), init)
        return jax.lax.dynamic_update_slice_in_dim(out, best, pb * _POINT_BLOCK, 0)

    out = jnp.full((points.shape[0],), jnp.inf, points.dtype)
    out = jax.lax.fori_loop(0, n_pt_blocks, point_block, out)
    return jnp.sqrt(out)


def _place_on_ring(points: jax.Array, keep: jax.Array, capacity: int):
    """Compact the kept points into a closed ring and place cones every CONE_SPACING metres by arc
    length from its first point (§5.7). Returns ((capacity, 2) positions, number of cones)."""
    size = points.shape[0]
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1
    count = jnp.sum(keep.astype(jnp.int32))
    compact = jnp.zeros_like(points).at[jnp.where(keep, rank, size)].set(points, mode="drop")
    compact = jnp.where((jnp.arange(size) < count)[:, None], compact, compact[0])
    cumlen = ring_cumlen(compact)
    total = cumlen[-1]
    targets = CONE_SPACING * jnp.arange(capacity, dtype=points.dtype)
    num = jnp.minimum(jnp.sum(targets < total), capacity)
    k = jnp.searchsorted(cumlen[1:], targets, side="right", method="scan")
    k = jnp.minimum(k, jnp.maximum(count - 1, 0))
    lo, hi = cumlen[k], cumlen[k + 1]
    span = hi - lo
    t = jnp.clip(jnp.where(span > 0, (targets - lo) / jnp.where(span > 0, span, 1), 0), 0, 1)
    pos = (1 - t)[:, None] * compact[k] + t[:, None] * compact[(k + 1) % size]
    return pos, jnp.where(count >= 2, num, 0)


def _snap_to_offset(points: jax.Array, ring: jax.Array, count: jax.Array, half_width: float) -> jax.Array:
    """Move each point along the direction from its nearest centre-line point to exactly
    `half_width` from it: removes the sag of the chords between candidate points (round joins,
    bridged concave corners) so cones sit on the buffer boundary as in the original."""
    ids = jnp.arange(ring.shape[0])
    ax, ay = ring[:, 0], ring[:, 1]
    nxt = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    ex, ey = nxt[:, 0] - ax, nxt[:, 1] - ay
    inv_len2 = 1 / jnp.maximum(ex * ex + ey * ey, 1e-12)

    def nearest_on(px, py, k):
        t = jnp.clip(((px - ax[k]) * ex[k] + (py - ay[k]) * ey[k]) * inv_len2[k], 0, 1)
        return ax[k] + t * ex[k], ay[k] + t * ey[k]

    px, py = points[:, 0:1], points[:, 1:2]
    qx, qy = nearest_on(px, py, ids[None, :])
    d2 = jnp.where((ids < count)[None, :], (px - qx) ** 2 + (py - qy) ** 2, jnp.inf)
    k = jnp.argmin(d2, axis=1)
    qx, qy = nearest_on(points[:, 0], points[:, 1], k)
    away = points - jnp.stack([qx, qy], axis=-1)
    dist = jnp.linalg.norm(away, axis=-1, keepdims=True)
    nearest = points - away
    return jnp.where(dist > 1e-6, nearest + half_width * away / jnp.where(dist > 1e-6, dist, 1), points)


def _signed_area(ring: jax.Array, count: jax.Array) -> jax.Array:
    ids = jnp.arange(ring.shape[0])
    following = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    return 0.5 * jnp.sum(jnp.where(ids < count, cross_2d(ring, following), 0))


def place_cones(ring: jax.Array, count: jax.Array, blue_is_left: jax.Array):
    """Cones on both 3.5 m offset curves; exterior ring first, types by the driver's side."""
    half = CONE_WIDTH / 2
    left, right, left_ok, right_ok = _offset_candidates(ring, count, half)
    num_candidates = (_JOIN_SLOTS + 1) * count  # used candidates form a prefix of each side's array
    keep_left = left_ok & (_distance_to_ring(left, num_candidates, ring, count) >= half - CONE_TRIM_TOL)
    keep_right = right_ok & (_distance_to_ring(right, num_candidates, ring, count) >= half - CONE_TRIM_TOL)
    # The left side of a clockwise ring is its exterior.
    left_is_exterior = _signed_area(ring, count) < 0
    ext_pts = jnp.where(left_is_exterior, left, right)
    ext_keep = jnp.where(left_is_exterior, keep_left, keep_right)
    int_pts = jnp.where(left_is_exterior, right, left)
    int_keep = jnp.where(left_is_exterior, keep_right, keep_left)
    ext_pos, n_ext = _place_on_ring(ext_pts, ext_keep, MAX_CONES)
    int_pos, n_int = _place_on_ring(int_pts, int_keep, MAX_CONES)
    slot = jnp.arange(MAX_CONES)
    from_int = jnp.clip(slot - n_ext, 0, MAX_CONES - 1)
    cone_xy = jnp.where((slot < n_ext)[:, None], ext_pos, int_pos[from_int])
    cone_xy = _snap_to_offset(cone_xy, ring, count, half)
    present = slot < jnp.minimum(n_ext + n_int, MAX_CONES)
    ext_blue = left_is_exterior == blue_is_left
    ext_type = jnp.where(ext_blue, CONE_TYPE_BLUE, CONE_TYPE_YELLOW)
    int_type = CONE_TYPE_BLUE + CONE_TYPE_YELLOW - ext_type
    cone_type = jnp.where(present, jnp.where(slot < n_ext, ext_type, int_type), 0).astype(jnp.int32)
    cone_xy = jnp.where(present[:, None], cone_xy, 0)
    return cone_xy, cone_type, present
