"""The centre line of a random race track (docs/carenv-single-agent.md §5.1-§5.6), in fixed shapes.

Up to 20 raw points, a gift-wrapping convex hull (clockwise, as the original's geometry library
returns it), the non-convex perturbation, Gauss-Seidel push-apart as ``lax`` loops, a closed
centripetal Catmull-Rom spline (20 samples per segment, junctions repeated exactly), and the
validity check of one draw. Approximations, documented as acceptable in
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
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

MAX_RAW_POINTS = 20
MIN_RAW_POINTS = 10
MAX_CONTROL_POINTS = 2 * MAX_RAW_POINTS
SAMPLES_PER_SEGMENT = 20
MAX_DEDUP_POINTS = (SAMPLES_PER_SEGMENT - 1) * MAX_CONTROL_POINTS  # centre line without junction repeats
EXTENT = 150.0
MIN_DISTANCE = 15.0
PUSH_SWEEPS = 3
OFFSET_RANGE = 20.0
MAX_TRACK_LENGTH = 775.0  # keeps 2 * L / 5 + 2 cones below MAX_CONES
SEG_BLOCK = 40  # MAX_DEDUP_POINTS = 19 blocks


def cross_2d(a, b):
    """z component of the cross product of 2-D vectors (last axis): > 0 when b is left of a."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ring_cumlen(points: jax.Array) -> jax.Array:
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
        cross = cross_2d(rel[:, None, :], rel[None, :, :])  # [q, r] > 0: r left of current->q
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


def dedup_ring(samples: jax.Array, num_segments: jax.Array):
    """Centre line without the repeated junction points: (MAX_DEDUP_POINTS, 2) padded with point 0,
    and its vertex count 19 * K."""
    dedup = samples[:, :-1].reshape(-1, 2)
    count = (SAMPLES_PER_SEGMENT - 1) * num_segments
    dedup = jnp.where((jnp.arange(dedup.shape[0]) < count)[:, None], dedup, dedup[0])
    return dedup, count


def _is_simple(ring: jax.Array, count: jax.Array) -> jax.Array:
    """True iff no two non-adjacent segments of the closed ring cross (§5.6 check 1).

    Segments i and j cross properly iff the endpoints of each lie strictly on opposite sides of the
    other's line. Evaluated in blocks of SEG_BLOCK x SEG_BLOCK pairs with a data-dependent number
    of blocks, so the cost scales with count**2 rather than the capacity squared."""
    size = ring.shape[0]
    ids = jnp.arange(size)
    nxt = ring[jnp.where(ids + 1 < count, ids + 1, 0)]
    ax, ay, bx, by = ring[:, 0], ring[:, 1], nxt[:, 0], nxt[:, 1]
    blocks = (count + SEG_BLOCK - 1) // SEG_BLOCK

    def side(ox, oy, ex, ey, px, py):  # [i, j]: side of point j relative to line i
        return ex[:, None] * (py[None, :] - oy[:, None]) - ey[:, None] * (px[None, :] - ox[:, None])

    def block(step, found):
        rows = ids[:SEG_BLOCK] + (step // blocks) * SEG_BLOCK
        cols = ids[:SEG_BLOCK] + (step % blocks) * SEG_BLOCK
        sl = functools.partial(jax.lax.dynamic_slice_in_dim, slice_size=SEG_BLOCK)
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


def draw_attempt(key: jax.Array, dtype):
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
    ring, ring_count = dedup_ring(samples, num_control)
    valid = hull_ok & _is_simple(ring, ring_count) & (_ring_length(ring, ring_count) <= MAX_TRACK_LENGTH)
    return samples, num_control, valid
