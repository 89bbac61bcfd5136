"""The rolling window of finished episodes behind the rollout metrics (docs/algorithms.md §6.2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax.config import Scenario

EPISODE_WINDOW = 100  # rollout metrics average over the last 100 finished episodes (§6.2)
EARLY_TERMINATION_REWARD = -0.5  # ETR: terminated with a last reward below this (§6.1)


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


def window_means(window: EpisodeWindow, scenario: Scenario) -> tuple[dict[str, jax.Array], jax.Array]:
    """Averages over the window, and whether it holds any episode yet (the averages are 0 until
    then); multi-agent windows hold per-agent episodes (termination or the 60 s restart) and the
    env's mean velocity instead of the track velocity; a user's env has only returns and lengths."""
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
    if not scenario.custom:  # CarEnv's: a crash ends an episode with reward below -0.5
        means["rollout/early_termination_rate"] = mean(window.early)
        velocity = "rollout/avg_mean_velocity" if scenario.multi_agent else "rollout/avg_track_velocity"
        means[velocity] = mean(window.track_velocity)
    return means, filled > 0
