"""Reference track geometry for the tests: plain, brute-force versions of what the racing step computes
on the ring tables (docs/carenv-single-agent.md §6.1, §6.4, §7.3).

The package's hot path (``envs.ring_geometry``) is checked against these: the global projection on
the ``Track`` arrays, points by arc length, the travel tangent, the progress between two arc lengths,
and a brute-force projection over all segments of a ``TrackView``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from envs.ring_geometry import TrackView, first_min_index, projection_at, segment_distances
from envs.track import MAX_CENTERLINE, TINY_SEGMENT, Track


def _nearest_segment(track: Track, point: jax.Array):
    """Index, parameter and squared distance of the globally nearest ring segment.

    The closest point is written as (1 - t) a + t b so that it equals a vertex exactly at t = 0 or 1;
    at a vertex the tie between the two segments meeting there then goes to the EARLIER one (argmin
    takes the first minimum), i.e. the segment that ends at the vertex, as the original's progress
    lookup requires (tests/data/README.md §4).
    """
    ax, ay = track.centerline[:, 0], track.centerline[:, 1]
    bx = jnp.concatenate([ax[1:], ax[:1]])
    by = jnp.concatenate([ay[1:], ay[:1]])
    ex, ey = bx - ax, by - ay
    len2 = ex * ex + ey * ey
    t = jnp.clip(((point[0] - ax) * ex + (point[1] - ay) * ey) / jnp.where(len2 > 0, len2, 1), 0, 1)
    dx = point[0] - ((1 - t) * ax + t * bx)
    dy = point[1] - ((1 - t) * ay + t * by)
    d2 = jnp.where(jnp.arange(ax.shape[0]) < track.num_points, dx * dx + dy * dy, jnp.inf)
    index = jnp.argmin(d2)
    return index, t[index], d2[index]


def project(track: Track, point: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Stored-order arc length s in [0, L) of the nearest point of the closed centre line to `point`
    (global over all segments, §6.1) and the Euclidean distance to it."""
    point = jnp.asarray(point, dtype=track.centerline.dtype)
    index, t, d2 = _nearest_segment(track, point)
    lo, hi = track.cumlen[index], track.cumlen[index + 1]
    s = jnp.clip((1 - t) * lo + t * hi, lo, hi)
    s = jnp.where(s >= track.length, s - track.length, s)
    return s, jnp.sqrt(d2)


def point_at_arclength(track: Track, s: jax.Array) -> jax.Array:
    """Point of the closed centre line at stored-order arc length s (taken mod L), linear
    interpolation along the polyline; works elementwise for any shape of `s` -> (*s.shape, 2).

    Binary search on the cumulative lengths (sorted by construction): O(log N) per query."""
    s = jnp.asarray(s, dtype=track.centerline.dtype)
    flat = jnp.mod(s.reshape(-1), track.length)
    # Segment k with cumlen[k] <= s < cumlen[k+1]; zero-length segments can never satisfy that.
    k = jnp.searchsorted(track.cumlen[1:], flat, side="right", method="scan")
    k = jnp.minimum(k, track.num_points - 1)
    lo, hi = track.cumlen[k], track.cumlen[k + 1]
    span = hi - lo
    t = jnp.clip(jnp.where(span > 0, (flat - lo) / jnp.where(span > 0, span, 1), 0), 0, 1)
    k_next = jnp.where(k + 1 < MAX_CENTERLINE, k + 1, 0)
    cx, cy = track.centerline[:, 0], track.centerline[:, 1]
    points = jnp.stack([(1 - t) * cx[k] + t * cx[k_next], (1 - t) * cy[k] + t * cy[k_next]], axis=-1)
    return points.reshape((*s.shape, 2))


def travel_points(track: Track, s: jax.Array, distances: jax.Array) -> jax.Array:
    """Points `distances` metres AHEAD along the travel direction from stored arc length s.

    The tracking sensor (§7.3) walks the REVERSED ring: arc length a on the reversed ring and
    s on the stored ring denote the same point when a = (c - s) mod L for a constant c that depends
    only on where the reversed ring starts, so (a + d) mod L on the reversed ring is the stored
    point at (s - d) mod L. With a = the reversed ring's nearest point this gives Q_k for
    d = k * spacing, whatever the start of the reversed ring.
    """
    return point_at_arclength(track, s - jnp.asarray(distances, dtype=track.centerline.dtype))


def stored_direction(track: Track, s: jax.Array) -> jax.Array:
    """Unit direction e_k (stored order) of the segment used by the progress reward (§6.1):
    the first segment, longer than TINY_SEGMENT, whose end arc length is >= s (at an exact vertex
    the segment ending there); clamped to the last real segment when s exceeds L by rounding.

    Segment lengths are read from `cumlen` differences, so the choice is consistent with the arc
    length that `project` returns (same numbers, same vertex ties)."""
    s = jnp.asarray(s, dtype=track.centerline.dtype)
    ends = track.cumlen[1:]
    k = jnp.searchsorted(ends, s, side="left", method="scan")
    last_real = jnp.searchsorted(ends, track.length - TINY_SEGMENT, side="left", method="scan")
    k = jnp.minimum(k, last_real)
    # A (near) zero-length segment has no direction: use the next real one.
    tiny = ends[k] - track.cumlen[k] <= TINY_SEGMENT
    k = jnp.where(tiny, jnp.searchsorted(ends, ends[k] + TINY_SEGMENT, side="right", method="scan"), k)
    k = jnp.minimum(k, last_real)
    k_next = jnp.where(k + 1 < MAX_CENTERLINE, k + 1, 0)
    edge = track.centerline[k_next] - track.centerline[k]
    return edge / jnp.linalg.norm(edge)


def travel_tangent(track: Track, s: jax.Array) -> jax.Array:
    """Travel tangent t(s) = -e_k (the car drives opposite to the stored order, §6.1)."""
    return -stored_direction(track, s)


def progress_delta(track: Track, s_prev: jax.Array, s_now: jax.Array) -> jax.Array:
    """Along-track distance moved, positive in the travel direction (§6.4)."""
    delta = jnp.mod(s_prev - s_now, track.length)
    return jnp.where(delta > track.length / 2, delta - track.length, delta)


def sample_from_bank(key: jax.Array, bank: Track) -> Track:
    """One track of the bank, chosen uniformly (cheap enough for every reset)."""
    size = bank.num_points.shape[0]
    index = jax.random.randint(key, (), 0, size)
    return jax.tree_util.tree_map(lambda leaf: leaf[index], bank)


def project_point_global(view: TrackView, px, py):
    """Global nearest point of the ring by brute force over all segments (reference for
    ``envs.ring_geometry.project_point``)."""
    d2, t = segment_distances(view, px, py, jnp.arange(view.size))
    j = first_min_index(d2)
    return projection_at(view, j, t[j], d2[j])
