"""The rolling window of finished episodes behind the rollout metrics (docs/algorithms.md §6.2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

EPISODE_WINDOW = 100  # rollout metrics average over the last 100 finished episodes (§6.2)


@struct.dataclass
class EpisodeWindow:
    """The last ``EPISODE_WINDOW`` finished episodes (ring), for the rollout metrics of §6.2."""

    returns: jax.Array
    lengths: jax.Array
    early: jax.Array
    track_velocity: jax.Array
    count: jax.Array  # episodes finished so far


def window_init(dtype) -> EpisodeWindow:
    zeros = jnp.zeros((EPISODE_WINDOW,), dtype)
    return EpisodeWindow(zeros, zeros, jnp.zeros((EPISODE_WINDOW,), bool), zeros, jnp.zeros((), jnp.int32))


def window_add(window: EpisodeWindow, done, returns, lengths, early, velocity) -> EpisodeWindow:
    """Append the finished episodes among E envs (masked scatter; unfinished ones are dropped)."""
    order = jnp.cumsum(done.astype(jnp.int32)) - 1
    slot = jnp.where(done, (window.count + order) % EPISODE_WINDOW, EPISODE_WINDOW)

    def put(store, value):
        return store.at[slot].set(value.astype(store.dtype), mode="drop")

    return EpisodeWindow(
        returns=put(window.returns, returns),
        lengths=put(window.lengths, lengths),
        early=put(window.early, early),
        track_velocity=put(window.track_velocity, velocity),
        count=window.count + jnp.sum(done, dtype=jnp.int32),
    )


def window_means(window: EpisodeWindow, velocity: str | None) -> tuple[dict[str, jax.Array], jax.Array]:
    """Averages over the window, and whether it holds any episode yet (the averages are 0 until
    then). With ``velocity`` (the metric name its kind gives the window's velocity: the track velocity
    of racing, the env's mean velocity of the multi-agent env, whose windows hold per-agent episodes)
    also the early-termination rate; without (a user's env), only returns and lengths."""
    filled = jnp.minimum(window.count, EPISODE_WINDOW)
    mask = jnp.arange(EPISODE_WINDOW) < filled
    denom = jnp.maximum(filled, 1)

    def mean(x):
        return jnp.sum(jnp.where(mask, x.astype(jnp.float32), 0.0)) / denom

    means = {
        "rollout/avg_episode_return": mean(window.returns),
        "rollout/avg_episode_length": mean(window.lengths),
        "rollout/episodes": window.count,
    }
    if velocity is not None:  # CarEnv's: a crash ends an episode with reward below -0.5
        means["rollout/early_termination_rate"] = mean(window.early)
        means[velocity] = mean(window.track_velocity)
    return means, filled > 0
