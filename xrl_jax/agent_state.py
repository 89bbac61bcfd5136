"""What an agent carries through training: the traced hyper-parameters, the state pytree and the Adam
steps that update it (docs/algorithms.md §1.3-§1.5). :mod:`xrl_jax.agents` re-exports the public names."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from xrl_jax.config import AgentConfig

Array = jax.Array


@struct.dataclass
class HyperParams:
    """Traced optimisation constants (scalars; vmappable for sweeps, e.g. κ in paper Fig. 8).

    ``init_log_alpha`` is where log α starts, also after a re-initialisation, so that a swept
    initial α survives one."""

    actor_lr: Array
    critic_lr: Array
    alpha_lr: Array
    gamma: Array
    tau: Array
    kappa: Array
    target_entropy: Array
    init_log_alpha: Array


@struct.dataclass
class AgentState:
    """Everything that changes during training; a pytree with an optional leading seed axis."""

    actor_params: Any
    critic_params: Any
    target_critic_params: Any
    log_alpha: Array
    actor_opt_state: Any
    critic_opt_state: Any
    alpha_opt_state: Any
    step: Array
    hparams: HyperParams

    @property
    def alpha(self) -> Array:
        return jnp.exp(self.log_alpha)


def _float(x) -> Array:
    return jnp.asarray(x, dtype=jnp.result_type(float))


def make_hparams(config: AgentConfig, action_size: int) -> HyperParams:
    """The traced part of a config as a pytree of scalars (default float dtype)."""
    return HyperParams(
        actor_lr=_float(config.actor_lr),
        critic_lr=_float(config.critic_lr),
        alpha_lr=_float(config.resolved_alpha_lr()),
        gamma=_float(config.gamma),
        tau=_float(config.tau),
        kappa=_float(config.kappa),
        target_entropy=_float(config.resolved_target_entropy(action_size)),
        init_log_alpha=_float(math.log(config.init_alpha)),
    )


def adam(clip_norm: float | None) -> optax.GradientTransformation:
    """Adam without the learning-rate scaling (applied from the traced hparams); optional clipping."""
    if clip_norm is None:
        return optax.scale_by_adam()
    return optax.chain(optax.clip_by_global_norm(clip_norm), optax.scale_by_adam())


def adam_step(tx: optax.GradientTransformation, grads, opt_state, params, lr: Array):
    """params ← params − lr·Adam(grads): optax.adam with a traced learning rate."""
    updates, opt_state = tx.update(grads, opt_state, params)
    params = jax.tree_util.tree_map(lambda p, u: p - lr * u, params, updates)
    return params, opt_state


__all__ = ["AgentState", "HyperParams", "adam", "adam_step", "make_hparams"]
