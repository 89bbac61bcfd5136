"""The two action spaces of the agents (docs/algorithms.md §1.2, §7.2.9): continuous (SAC, XSAC) and
discrete (DSAC, XDSAC). An :class:`~xrl_jax.agents.Agent` picks one when it is built; together with the
policy of its actor (:mod:`xrl_jax.policies`) that is all that tells the four algorithms apart."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from xrl_jax import losses

Array = jax.Array


@dataclasses.dataclass(frozen=True)
class ContinuousActions:
    """SAC's and XSAC's actions, (..., A) in [-1, 1]: the critics score one given action."""

    size: int  # A

    def shape(self, batch_shape: tuple[int, ...]) -> tuple[int, ...]:
        return (*batch_shape, self.size)

    def random(self, key: Array, batch_shape: tuple[int, ...]) -> Array:
        return jax.random.uniform(key, self.shape(batch_shape), jnp.result_type(float), -1.0, 1.0)

    def explore(self, action: Array, mode: str, explore_key: Array, coin_key: Array) -> Array:
        """No ε-exploration: the Gaussians explore on their own."""
        return action

    def critic_inputs(self, obs: Any, action: Array) -> tuple[Any, ...]:
        return obs, action

    def td_target(self, critic, target_params, next_obs, next_pi, reward, discount, alpha, key) -> Array:
        # one fresh next-action sample per transition from the full (pre-update) policy (§3.3)
        next_action, next_log_prob = next_pi.sample_and_log_prob(key)
        next_q = critic.apply(target_params, next_obs, next_action)
        return losses.continuous_td_target(reward, discount, next_q, next_log_prob, alpha)

    def taken_q(self, critic, critic_params, obs, action) -> Array:
        return critic.apply(critic_params, obs, action)


@dataclasses.dataclass(frozen=True)
class DiscreteActions:
    """DSAC's and XDSAC's actions, (...,) int32 in 0..N-1: the critics value all N at once."""

    size: int  # N
    epsilon: float  # ε of the random actions at training time (§7.2.9)

    def shape(self, batch_shape: tuple[int, ...]) -> tuple[int, ...]:
        return tuple(batch_shape)

    def random(self, key: Array, batch_shape: tuple[int, ...]) -> Array:
        return jax.random.randint(key, batch_shape, 0, self.size, jnp.int32)

    def explore(self, action: Array, mode: str, explore_key: Array, coin_key: Array) -> Array:
        """In "train" mode a uniform random action with probability ε."""
        action = action.astype(jnp.int32)
        if mode == "train" and self.epsilon > 0:
            explore = jax.random.uniform(coin_key, action.shape) < self.epsilon
            action = jnp.where(explore, self.random(explore_key, action.shape), action)
        return action

    def critic_inputs(self, obs: Any, action: Array) -> tuple[Any, ...]:
        return (obs,)

    def td_target(self, critic, target_params, next_obs, next_pi, reward, discount, alpha, key) -> Array:
        next_q = critic.apply(target_params, next_obs)
        return losses.discrete_td_target(reward, discount, next_q, next_pi.probs(), alpha)

    def taken_q(self, critic, critic_params, obs, action) -> Array:
        q_all = critic.apply(critic_params, obs)
        action = jnp.asarray(action).astype(jnp.int32)
        index = jnp.broadcast_to(action[None, :, None], (*q_all.shape[:-1], 1))
        return jnp.take_along_axis(q_all, index, axis=-1)[..., 0]


__all__ = ["ContinuousActions", "DiscreteActions"]
