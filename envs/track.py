"""Fixed-shape, jittable race tracks for the CarEnv port (docs/carenv-single-agent.md §5, §6.1, §7.3).

A `Track` holds a closed centre line in the original's STORED order. The car always travels
OPPOSITE to that order (§5.8), so progress is measured by decreasing stored arc length and the
tracking sensor walks the ring backwards.

Padding convention: `centerline[i]` for `i >= num_points` repeats `centerline[0]`. The ring's
segments are then simply `centerline[i] -> centerline[(i + 1) % MAX_CENTERLINE]`: segment
`num_points - 1` closes the ring back to the first point and every padding segment has zero length,
so the geometry never needs a special case for the seam (a closed input whose last row repeats the
first just gets a zero-length closing segment). `cumlen[i]` is the stored-order arc length at vertex
`i`, `cumlen[num_points:] == length`.

Tracks come from :func:`track_from_arrays` (host arrays, e.g. the golden files) or from the random
generator of ``envs.track_generator`` (``generate_track``, ``make_track_bank``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.core import default_float

MAX_CENTERLINE = 800  # 20 samples x 2h control points, h <= 20 hull vertices (§5.10)
MAX_CONES = 320  # above the maximum cone count of §5.7
TINY_SEGMENT = 1e-9  # segments shorter than this are treated as zero-length (§5.5, §6.1)
CONE_RADIUS = 0.3  # §5.7
CONE_TYPE_BLUE = 1  # driver's right
CONE_TYPE_YELLOW = 2  # driver's left


@struct.dataclass
class Track:
    """A closed centre line (stored order, padded with its first point) with start pose and cones."""

    centerline: jax.Array  # (MAX_CENTERLINE, 2)
    num_points: jax.Array  # int32 scalar
    length: jax.Array  # closed ring length L
    cumlen: jax.Array  # (MAX_CENTERLINE + 1,) stored-order arc length at each vertex
    start_xy: jax.Array  # (2,)
    start_theta: jax.Array  # scalar
    cone_xy: jax.Array  # (MAX_CONES, 2)
    cone_type: jax.Array  # (MAX_CONES,) int32: 1 blue/right, 2 yellow/left, 0 padding
    cone_present: jax.Array  # (MAX_CONES,) bool

    @property
    def num_cones(self) -> jax.Array:
        return jnp.sum(self.cone_present.astype(jnp.int32), axis=-1)


def track_from_arrays(centerline, start_xy, start_theta, cone_xy=None, cone_type=None) -> Track:
    """Build a `Track` from numpy arrays, e.g. the golden files' `track_centerline`, `start_pose`,
    `cone_pos`, `cone_type` (all cones present).

    The centre line is taken as a closed ring in the given (stored) order; a last row repeating the
    first is allowed (it adds a zero-length closing segment). Arc lengths are accumulated in float64
    on the host and then cast to the default float dtype.
    """
    line = np.asarray(centerline, dtype=np.float64)
    if line.ndim != 2 or line.shape[1] != 2:
        raise ValueError(f"centerline must have shape (P, 2), got {line.shape}")
    if not 3 <= line.shape[0] <= MAX_CENTERLINE:
        raise ValueError(f"centerline must have 3..{MAX_CENTERLINE} points, got {line.shape[0]}")
    start = np.asarray(start_xy, dtype=np.float64)
    if start.shape != (2,):
        raise ValueError(f"start_xy must have shape (2,), got {start.shape}")
    theta = np.asarray(start_theta, dtype=np.float64)
    if theta.shape != ():
        raise ValueError(f"start_theta must be a scalar, got shape {theta.shape}")
    if (cone_xy is None) != (cone_type is None):
        raise ValueError("cone_xy and cone_type must be given together")
    if cone_xy is None:
        cones = np.zeros((0, 2))
        types = np.zeros((0,), dtype=np.int64)
    else:
        cones = np.asarray(cone_xy, dtype=np.float64)
        types = np.asarray(cone_type)
        if cones.ndim != 2 or cones.shape[1] != 2:
            raise ValueError(f"cone_xy must have shape (C, 2), got {cones.shape}")
        if types.shape != (cones.shape[0],):
            raise ValueError(f"cone_type must have shape ({cones.shape[0]},), got {types.shape}")
        if cones.shape[0] > MAX_CONES:
            raise ValueError(f"at most {MAX_CONES} cones are supported, got {cones.shape[0]}")
        if not np.all((types == CONE_TYPE_BLUE) | (types == CONE_TYPE_YELLOW)):
            raise ValueError("cone_type values must be 1 (blue, right) or 2 (yellow, left)")
    for name, value in (
        ("centerline", line),
        ("start_xy", start),
        ("start_theta", theta),
        ("cone_xy", cones),
    ):
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name} must be finite")

    count = line.shape[0]
    padded = np.concatenate([line, np.repeat(line[:1], MAX_CENTERLINE - count, axis=0)])
    segment = np.linalg.norm(np.roll(padded, -1, axis=0) - padded, axis=-1)
    cumlen = np.concatenate([[0.0], np.cumsum(segment)])
    if cumlen[-1] <= 0.0:
        raise ValueError("centerline has zero length")

    num_cones = cones.shape[0]
    cone_pad = np.zeros((MAX_CONES, 2))
    cone_pad[:num_cones] = cones
    type_pad = np.zeros((MAX_CONES,), dtype=np.int32)
    type_pad[:num_cones] = types
    dtype = default_float()
    return Track(
        centerline=jnp.asarray(padded, dtype=dtype),
        num_points=jnp.asarray(count, dtype=jnp.int32),
        length=jnp.asarray(cumlen[-1], dtype=dtype),
        cumlen=jnp.asarray(cumlen, dtype=dtype),
        start_xy=jnp.asarray(start, dtype=dtype),
        start_theta=jnp.asarray(theta, dtype=dtype),
        cone_xy=jnp.asarray(cone_pad, dtype=dtype),
        cone_type=jnp.asarray(type_pad),
        cone_present=jnp.arange(MAX_CONES) < num_cones,
    )
