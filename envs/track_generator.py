"""Random race tracks as in docs/carenv-single-agent.md §5, in fixed shapes (jit and vmap friendly).

Generator in fixed shapes: up to 20 raw points, a gift-wrapping convex hull (clockwise, as
the original's geometry library returns it), the non-convex perturbation, Gauss-Seidel push-apart
as `lax` loops, a closed centripetal Catmull-Rom spline (20 samples per segment, junctions repeated
exactly), and a bounded rejection loop (at most `MAX_ATTEMPTS` draws; the last draw is kept if none
is valid, which is vanishingly rare). Approximations, all documented as acceptable in
docs/carenv-single-agent.md:

* Validity: only the simplicity check (§5.6 check 1, exact, over all pairs of non-adjacent
  segments) plus a length bound that guarantees the cones fit (`MAX_TRACK_LENGTH`, above the
  longest tracks of §5.7). The buffer checks 2-3 ("one hole", "single polygon"), which practically
  never fire in the original, are dropped.
* Rejection rate: lower than the original's. `is_simple` on a spline whose junction repeats are
  equal only up to rounding (as the original samples them, §5.5 correction) rejects many draws that
  the same spline with exact repeats accepts: the original's extra rejections are rounding artefacts
  at the junctions, not real self-intersections, and are not reproduced (the accepted tracks'
  control-point, sample, length and cone statistics match §5.5 and §5.7).
* Cones (§5.7): instead of a polygon buffer, the 3.5 m offset curves are built from candidate
  points (offset segment midpoints, round-join arcs on the convex side of every vertex, the miter
  corner on the concave side); candidates closer than 3.5 m - `CONE_TRIM_TOL` to the centre line
  are trimmed (they lie in the overlapping loops of tight corners or pinch points), the rest is
  resampled every 5 m by arc length and each cone is finally moved radially onto the 3.5 m offset.
  The exterior ring is stored first, as in the original; the ring start points are arbitrary (as in
  the original).
* Travel direction: a fair coin reverses the stored order; cones are coloured by side (type 1 =
  blue = driver's right, type 2 = yellow = left), the net rule of §5.8.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from envs.core import default_float
from envs.track import CONE_TYPE_BLUE, CONE_TYPE_YELLOW, MAX_CENTERLINE, MAX_CONES, Track

MAX_RAW_POINTS = 20
MIN_RAW_POINTS = 10
MAX_CONTROL_POINTS = 2 * MAX_RAW_POINTS
SAMPLES_PER_SEGMENT = 20
MAX_DEDUP_POINTS = (SAMPLES_PER_SEGMENT - 1) * MAX_CONTROL_POINTS  # centre line without junction repeats
EXTENT = 150.0
MIN_DISTANCE = 15.0
PUSH_SWEEPS = 3
OFFSET_RANGE = 20.0
CONE_WIDTH = 7.0
CONE_SPACING = 5.0
CONE_TRIM_TOL = 0.05
MAX_ATTEMPTS = 16
MAX_TRACK_LENGTH = 775.0  # keeps 2 * L / 5 + 2 cones below MAX_CONES
_SEG_BLOCK = 40  # MAX_DEDUP_POINTS = 19 blocks
_POINT_BLOCK = 240  # (_JOIN_SLOTS + 1) * MAX_DEDUP_POINTS = 19 blocks
_JOIN_SLOTS = 5  # candidate points per round join of the cone offset curves


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _ring_cumlen(points: jax.Array) -> jax.Array:
    """Arc length at each vertex of the padded ring; entry MAX is the closed length."""
    segment = jnp.linalg.norm(jnp.roll(points, -1, axis=0) - points, axis=-1)
    return jnp.concatenate([jnp.zeros((1,), points.dtype), jnp.cumsum(segment)])


def _push_apart(points: jax.Array, count: jax.Array) -> jax.Array:
    """Gauss-Seidel push-apart of the first `count` points (§5.2): PUSH_SWEEPS sweeps over the
    ordered pairs i < j, i outer, using the current positions; each point of a too-close pair moves
    by the full deficit."""

    def body(step, pts):
        i = (step // count) % count
        j = step % count
        delta = pts[j] - pts[i]
        dist = jnp.linalg.norm(delta)
        move = (j > i) & (dist < MIN_DISTANCE) & (dist > 0)
        shift = jnp.where(move, delta / jnp.where(dist > 0, dist, 1) * (MIN_DISTANCE - dist), 0)
        return pts.at[j].add(shift).at[i].add(-shift)

    return jax.lax.fori_loop(0, PUSH_SWEEPS * count * count, body, points)


def _convex_hull(points: jax.Array, count: jax.Array):
    """Gift-wrapping hull of the first `count` points, clockwise, starting at the leftmost point.

    Returns (vertex indices (MAX_RAW_POINTS,), number of hull vertices h, ok flag)."""
    size = points.shape[0]
    ids = jnp.arange(size)
    valid = ids < count
    first = jnp.argmin(jnp.where(valid, points[:, 0], jnp.inf))

    def next_vertex(current):
        rel = points - points[current]
        cross = _cross(rel[:, None, :], rel[None, :, :])  # [q, r] > 0: r left of current->q
        other = valid & (ids != current)
        violations = jnp.sum(jnp.where(other[None, :] & (cross > 0), 1, 0), axis=1)
        # Clockwise wrapping: the next vertex has every other point on its right; prefer the
        # farthest one among (numerically) collinear candidates.
        dist = jnp.linalg.norm(rel, axis=-1)
        score = jnp.where(other, violations * 1e6 - dist, jnp.inf)
        return jnp.argmin(score).astype(jnp.int32)

    def body(step, carry):
        hull, h, current, done = carry
        hull = jnp.where(done, hull, hull.at[h].set(current))
        h = jnp.where(done, h, h + 1)
        nxt = next_vertex(current)
        done = done | (nxt == first)
        return hull, h, jnp.where(done, current, nxt), done

    init = (jnp.zeros((size,), jnp.int32), jnp.asarray(0, jnp.int32), first.astype(jnp.int32), False)
    hull, h, _, done = jax.lax.fori_loop(0, size, body, init)
    return hull, h, done & (h >= 3)


def _perturb(hull_xy: jax.Array, h: jax.Array, lam_u: jax.Array, off_u: jax.Array) -> jax.Array:
    """Insert one displaced point after each hull vertex (§5.4) -> (2 * MAX_RAW_POINTS, 2)."""
    ids = jnp.arange(hull_xy.shape[0])
    following = hull_xy[jnp.where(ids + 1 < h, ids + 1, 0)]
    lam = 0.25 + 0.5 * lam_u
    middle = lam[:, None] * hull_xy + (1 - lam)[:, None] * following
    edge = hull_xy - following
    norm = jnp.linalg.norm(edge, axis=-1, keepdims=True)
    normal = jnp.stack([edge[:, 1], -edge[:, 0]], axis=-1) / jnp.where(norm > 0, norm, 1)
    offset = 2 * OFFSET_RANGE * off_u - OFFSET_RANGE
    displaced = middle + offset[:, None] * normal
    return jnp.stack([hull_xy, displaced], axis=1).reshape(-1, 2)


def _barry_goldman(p0, p1, p2, p3, frac):
    """Centripetal Catmull-Rom point between p1 (frac = 0) and p2 (frac = 1), §5.5.

    p0..p3 broadcast against each other with a trailing axis of 2; frac has the shape of the
    leading axes."""

    def knot(a, b):
        return jnp.maximum(jnp.sqrt(jnp.linalg.norm(b - a, axis=-1, keepdims=True)), 1e-6)

    t0 = 0.0
    t1 = t0 + knot(p0, p1)
    t2 = t1 + knot(p1, p2)
    t3 = t2 + knot(p2, p3)
    t = t1 + (t2 - t1) * frac[..., None]
    a1 = ((t1 - t) * p0 + (t - t0) * p1) / (t1 - t0)
    a2 = ((t2 - t) * p1 + (t - t1) * p2) / (t2 - t1)
    a3 = ((t3 - t) * p2 + (t - t2) * p3) / (t3 - t2)
    b1 = ((t2 - t) * a1 + (t - t0) * a2) / (t2 - t0)
    b2 = ((t3 - t) * a2 + (t - t1) * a3) / (t3 - t1)
    return ((t2 - t) * b1 + (t - t1) * b2) / (t2 - t1)


def _catmull_rom(control: jax.Array, count: jax.Array) -> jax.Array:
    """Closed centripetal Catmull-Rom samples (§5.5): (MAX_CONTROL_POINTS, 20, 2).

    Segment j runs from C[j-1] to C[j] with 20 samples including both ends; the end samples are set
    to those control points exactly (the pyramid gives them up to rounding), so junctions repeat
    exactly and the curve is explicitly closed."""
    j = jnp.arange(control.shape[0])
    p0, p1, p2, p3 = (control[(j + shift) % count][:, None, :] for shift in (-2, -1, 0, 1))
    frac = jnp.broadcast_to(
        jnp.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT, dtype=control.dtype), (j.size, SAMPLES_PER_SEGMENT)
    )
    samples = _barry_goldman(p0, p1, p2, p3, frac)
    return samples.at[:, 0].set(p1[:, 0]).at[:, -1].set(p2[:, 0])


def _dedup_ring(samples: jax.Array, num_segments: jax.Array):
    """Centre line without the repeated junction points: (MAX_DEDUP_POINTS, 2) padded with point 0,
    and its vertex count 19 * K."""
    dedup = samples[:, :-1].reshape(-1, 2)
    count = (SAMPLES_PER_SEGMENT - 1) * num_segments
    dedup = jnp.where((jnp.arange(dedup.shape[0]) < count)[:, None], dedup, dedup[0])
    return dedup, count


def _is_simple(ring: jax.Array, count: jax.Array) -> jax.Array:
    """True iff no two non-adjacent segments of the closed ring cross (§5.6 check 1).

    Segments i and j cross properly iff the endpoints of each lie strictly on opposite sides of the
    other's line. Evaluated in blocks of _SEG_BLOCK x _SEG_BLOCK pairs with a data-dependent number
    of blocks, so the cost scales with count**2 rather than the capacity squared."""
    size = ring.shape[0]
    ids = jnp.arange(size)
    nxt = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    ax, ay, bx, by = ring[:, 0], ring[:, 1], nxt[:, 0], nxt[:, 1]
    blocks = (count + _SEG_BLOCK - 1) // _SEG_BLOCK

    def side(ox, oy, ex, ey, px, py):  # [i, j]: side of point j relative to line i
        return ex[:, None] * (py[None, :] - oy[:, None]) - ey[:, None] * (px[None, :] - ox[:, None])

    def block(step, found):
        rows = ids[:_SEG_BLOCK] + (step // blocks) * _SEG_BLOCK
        cols = ids[:_SEG_BLOCK] + (step % blocks) * _SEG_BLOCK
        sl = functools.partial(jax.lax.dynamic_slice_in_dim, slice_size=_SEG_BLOCK)
        rax, ray, rbx, rby = (sl(v, rows[0]) for v in (ax, ay, bx, by))
        cax, cay, cbx, cby = (sl(v, cols[0]) for v in (ax, ay, bx, by))
        col_by_row = side(rax, ray, rbx - rax, rby - ray, cax, cay) * side(
            rax, ray, rbx - rax, rby - ray, cbx, cby
        )
        row_by_col = side(cax, cay, cbx - cax, cby - cay, rax, ray) * side(
            cax, cay, cbx - cax, cby - cay, rbx, rby
        )
        crossing = (col_by_row < 0) & (row_by_col.T < 0)
        gap = jnp.mod(rows[:, None] - cols[None, :], count)
        considered = (rows[:, None] < count) & (cols[None, :] < count) & (gap > 1) & (gap < count - 1)
        return found | jnp.any(crossing & considered)

    return ~jax.lax.fori_loop(0, blocks * blocks, block, jnp.asarray(False))


def _ring_length(ring: jax.Array, count: jax.Array) -> jax.Array:
    segment = jnp.linalg.norm(jnp.roll(ring, -1, axis=0) - ring, axis=-1)
    return jnp.sum(jnp.where(jnp.arange(ring.shape[0]) < count, segment, 0))


def _draw_attempt(key: jax.Array, dtype):
    """One attempt of §5.1 steps 1-7: spline samples, number of control points, validity."""
    k_n, k_pts, k_lam, k_off = jax.random.split(key, 4)
    n = jax.random.randint(k_n, (), MIN_RAW_POINTS, MAX_RAW_POINTS + 1, dtype=jnp.int32)
    raw = jax.random.uniform(k_pts, (MAX_RAW_POINTS, 2), dtype=dtype) * EXTENT
    raw = _push_apart(raw, n)
    hull_ids, h, hull_ok = _convex_hull(raw, n)
    hull_xy = raw[hull_ids]
    lam_u = jax.random.uniform(k_lam, (MAX_RAW_POINTS,), dtype=dtype)
    off_u = jax.random.uniform(k_off, (MAX_RAW_POINTS,), dtype=dtype)
    control = _perturb(hull_xy, h, lam_u, off_u)
    num_control = 2 * h
    control = _push_apart(control, num_control)
    samples = _catmull_rom(control, num_control)
    ring, ring_count = _dedup_ring(samples, num_control)
    valid = hull_ok & _is_simple(ring, ring_count) & (_ring_length(ring, ring_count) <= MAX_TRACK_LENGTH)
    return samples, num_control, valid


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
    turn = jnp.arctan2(_cross(prev_normal, normal), jnp.sum(prev_normal * normal, axis=-1))
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
    n_seg_blocks = (count + _SEG_BLOCK - 1) // _SEG_BLOCK
    n_pt_blocks = (num_points + _POINT_BLOCK - 1) // _POINT_BLOCK

    def seg_block(sb, best, px, py):
        lo = sb * _SEG_BLOCK
        sl = functools.partial(jax.lax.dynamic_slice_in_dim, start_index=lo, slice_size=_SEG_BLOCK)
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
    cumlen = _ring_cumlen(compact)
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
    return 0.5 * jnp.sum(jnp.where(ids < count, _cross(ring, following), 0))


def _place_cones(ring: jax.Array, count: jax.Array, blue_is_left: jax.Array):
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


def _generate(key: jax.Array):
    """Full generator; also returns the number of attempts and whether the kept draw is valid."""
    dtype = default_float()
    k_attempts, k_dir = jax.random.split(key)

    def cond(carry):
        attempt, _, _, valid = carry
        return (~valid) & (attempt < MAX_ATTEMPTS)

    def body(carry):
        attempt, _, _, _ = carry
        samples, num_control, valid = _draw_attempt(jax.random.fold_in(k_attempts, attempt), dtype)
        return attempt + 1, samples, num_control, valid

    init = (
        jnp.asarray(0, jnp.int32),
        jnp.zeros((MAX_CONTROL_POINTS, SAMPLES_PER_SEGMENT, 2), dtype),
        jnp.asarray(3, jnp.int32),
        jnp.asarray(False),
    )
    attempts, samples, num_control, valid = jax.lax.while_loop(cond, body, init)

    generated = samples.reshape(-1, 2)  # (MAX_CENTERLINE, 2), explicitly closed
    count = SAMPLES_PER_SEGMENT * num_control
    reverse = jax.random.bernoulli(k_dir)
    ids = jnp.arange(MAX_CENTERLINE)
    order = jnp.where(ids < count, jnp.where(reverse, count - 1 - ids, ids), 0)
    centerline = generated[order]  # padding rows repeat point 0 (== the last valid row)
    cumlen = _ring_cumlen(centerline)

    # Start: generated sample 0, heading from sample 1 to sample 0; +pi when reversed (§5.8).
    start_xy = generated[0]
    back = generated[0] - generated[1]
    theta = jnp.arctan2(back[1], back[0])
    theta = jnp.where(reverse, jnp.arctan2(-back[1], -back[0]), theta)

    ring, ring_count = _dedup_ring(samples, num_control)
    # Travel is opposite to the stored order, so the driver's right is the stored order's left;
    # un-reversed the stored order is the generated order.
    blue_is_left = ~reverse
    cone_xy, cone_type, present = _place_cones(ring, ring_count, blue_is_left)
    track = Track(
        centerline=centerline,
        num_points=count.astype(jnp.int32),
        length=cumlen[-1],
        cumlen=cumlen,
        start_xy=start_xy,
        start_theta=theta,
        cone_xy=cone_xy,
        cone_type=cone_type,
        cone_present=present,
    )
    return track, attempts, valid


def generate_track(key: jax.Array) -> Track:
    """Random track as in §5 (fixed shapes; jit and vmap friendly)."""
    return _generate(key)[0]


def generation_batch_size() -> int:
    """Tracks generated at once: 1 on CPU, where the generator's data-dependent loops run fastest a
    track at a time, and 64 on an accelerator. Memory per track in flight is a few MB (760 x 760
    simplicity tables)."""
    return 1 if jax.default_backend() == "cpu" else 64


def make_track_bank(key: jax.Array, size: int, batch_size: int | None = None) -> Track:
    """`size` independent tracks stacked on a leading axis (a bank, drawn from at every reset).

    Tracks are generated `batch_size` at a time (vmapped inside `lax.map`), by default
    :func:`generation_batch_size`."""
    if int(size) < 1:
        raise ValueError(f"size must be a positive integer, got {size}")
    if batch_size is None:
        batch_size = generation_batch_size()
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size}")
    return _make_bank(key, int(size), min(int(batch_size), int(size)))


@functools.partial(jax.jit, static_argnames=("size", "batch_size"))
def _make_bank(key: jax.Array, size: int, batch_size: int) -> Track:
    return jax.lax.map(generate_track, jax.random.split(key, size), batch_size=batch_size)
