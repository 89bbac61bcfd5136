"""Random race tracks as in docs/carenv-single-agent.md §5, in fixed shapes (jit and vmap friendly).

A bounded rejection loop (at most `MAX_ATTEMPTS` draws; the last draw is kept if none is valid,
which is vanishingly rare) over the centre-line draws of ``envs.track_shape``, a fair coin for the
travel direction (it reverses the stored order), and the cones of ``envs.track_cones``. Those two
modules list the approximations of the original, all documented as acceptable in
docs/carenv-single-agent.md.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import default_float
from envs.track import MAX_CENTERLINE, Track
from envs.track_cones import place_cones
from envs.track_shape import MAX_CONTROL_POINTS, SAMPLES_PER_SEGMENT, dedup_ring, draw_attempt, ring_cumlen

MAX_ATTEMPTS = 16


def _generate(key: jax.Array):
    """Full generator; also returns the number of attempts and whether the kept draw is valid."""
    dtype = default_float()
    k_attempts, k_dir = jax.random.split(key)

    def cond(carry):
        attempt, _, _, valid = carry
        return (~valid) & (attempt < MAX_ATTEMPTS)

    def body(carry):
        attempt, _, _, _ = carry
        samples, num_control, valid = draw_attempt(jax.random.fold_in(k_attempts, attempt), dtype)
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
    cumlen = ring_cumlen(centerline)

    # Start: generated sample 0, heading from sample 1 to sample 0; +pi when reversed (§5.8).
    start_xy = generated[0]
    back = generated[0] - generated[1]
    theta = jnp.arctan2(back[1], back[0])
    theta = jnp.where(reverse, jnp.arctan2(-back[1], -back[0]), theta)

    ring, ring_count = dedup_ring(samples, num_control)
    # Travel is opposite to the stored order, so the driver's right is the stored order's left;
    # un-reversed the stored order is the generated order.
    blue_is_left = ~reverse
    cone_xy, cone_type, present = place_cones(ring, ring_count, blue_is_left)
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

    Track ``i`` is generated from ``jax.random.split(key, size)[i]``, `batch_size` tracks at a time
    (vmapped inside `lax.map`), by default :func:`generation_batch_size`. The keys go through one
    compiled program in blocks of :func:`generation_block_size` (the last block padded and its extra
    tracks dropped), so every bank size reuses one compile (~15 s on CPU) instead of compiling its
    own; a track does not depend on the block it is generated in."""
    if int(size) < 1:
        raise ValueError(f"size must be a positive integer, got {size}")
    if batch_size is None:
        batch_size = generation_batch_size()
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size}")
    size, batch_size = int(size), int(batch_size)
    block = generation_block_size(batch_size)
    keys = jax.random.split(key, size)
    padded = keys[np.arange(-(-size // block) * block) % size]  # the last block repeats keys
    blocks = [_generate_block(padded[start : start + block], batch_size) for start in range(0, size, block)]
    if len(blocks) == 1:
        return jax.tree.map(lambda x: x[:size], blocks[0])
    return jax.tree.map(lambda *parts: jnp.concatenate(parts)[:size], *blocks)


def generation_block_size(batch_size: int) -> int:
    """Keys per compiled call of the bank builder: 16 or more, a whole number of batches. Padding a
    3-track bank to 16 tracks costs ~0.1 s on CPU, a compile for its size ~15 s."""
    return batch_size * -(-16 // batch_size)


@functools.partial(jax.jit, static_argnames=("batch_size",))
def _generate_block(keys: jax.Array, batch_size: int) -> Track:
    return jax.lax.map(generate_track, keys, batch_size=batch_size)
