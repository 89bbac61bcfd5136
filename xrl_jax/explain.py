"""Explanations of a policy at a state: what each observed object contributes to the action.

For XSAC and XDSAC the explanation is not computed after the fact: the policy *is* the mixture
π(a|s) = Σ_o w_o π_o(a|s), so the weight w_o and the per-object distribution π_o are read off the
network, and they add up exactly to the action distribution (faithfulness by construction).
:func:`explain` packages them; :func:`prune` drops the least important objects while keeping a
guaranteed bound on how much the policy changes (total variation ≤ the weight removed).

Baselines (SAC, DSAC) have no objects: their explanation has one pseudo-object of weight 1 (the whole
observation), so figures can still show their action distribution.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax.distributions import (
    ABSENT_LOG_WEIGHT,
    CategoricalMixture,
    SquashedGaussianMixture,
)

Policy = SquashedGaussianMixture | CategoricalMixture


@struct.dataclass
class Explanation:
    """The per-object view of a policy at one or more states (leading batch axes preserved).

    * ``weights``: (..., O) mixture weight of each object slot, exactly 0 for absent slots.
    * ``present``: (..., O) which slots hold an object.
    * ``policy``: the combined action distribution (a ``distributions`` mixture). Its components are
      the per-object distributions: ``policy.component_probs()`` (..., O, N) for discrete actions;
      ``policy.loc`` / ``policy.scale`` (..., O·C, A) of the squashed Gaussians for continuous ones.
    * ``is_mixture``: False for the baselines (one pseudo-object: the whole observation).
    """

    weights: jax.Array
    present: jax.Array
    policy: Any
    is_mixture: bool = struct.field(pytree_node=False)

    @property
    def num_objects(self) -> int:
        return self.weights.shape[-1]


def explain(agent, agent_state, obs: Mapping[str, jax.Array]) -> Explanation:
    """Weights, per-object distributions and the combined policy of ``agent`` at ``obs``.

    ``obs`` may carry any leading batch axes; jit with ``agent`` static, e.g.
    ``jax.jit(explain, static_argnums=0)(agent, state, obs)``.
    """
    policy = agent.policy(agent_state.actor_params, obs)
    is_mixture = agent.config.algo in ("xsac", "xdsac")
    weights = policy.weights
    present = policy.present
    components_per_object = weights.shape[-1] // agent.obs_shape.num_objects if is_mixture else 1
    if components_per_object > 1:  # objects own C components each, w_{o,c} = w_o / C
        grouped = (*weights.shape[:-1], -1, components_per_object)
        weights = weights.reshape(grouped).sum(-1)
        present = present.reshape(grouped).any(-1)
    return Explanation(weights=weights, present=present, policy=policy, is_mixture=is_mixture)


def keep_components(policy: Policy, keep: jax.Array) -> Policy:
    """The mixture restricted to the components in ``keep`` (..., K), weights renormalised.

    If nothing is kept the policy is returned unchanged (there is nothing to renormalise to).
    """
    keep = keep & policy.present
    any_kept = jnp.any(keep, axis=-1, keepdims=True)
    keep = jnp.where(any_kept, keep, policy.present)
    masked = jnp.where(keep, policy.log_weights, -jnp.inf)
    log_norm = jax.scipy.special.logsumexp(masked, axis=-1, keepdims=True)
    log_weights = jnp.where(keep, policy.log_weights - log_norm, ABSENT_LOG_WEIGHT)
    return policy.replace(log_weights=log_weights, present=keep)


def prune(policy: Policy, epsilon: float) -> tuple[Policy, jax.Array]:
    """Drop the lightest components whose weights add up to at most ``epsilon``.

    Returns the pruned policy and the removed weight. Since π = (1−r)·π' + r·ρ for the removed part ρ
    with total weight r, the total-variation distance between π and the pruned π' is at most r ≤ ε.
    """
    weights = policy.weights
    order = jnp.argsort(weights, axis=-1)
    sorted_weights = jnp.take_along_axis(weights, order, axis=-1)
    drop_sorted = jnp.cumsum(sorted_weights, axis=-1) <= epsilon
    inverse = jnp.argsort(order, axis=-1)
    drop = jnp.take_along_axis(drop_sorted, inverse, axis=-1)
    removed = jnp.sum(jnp.where(drop, weights, 0.0), axis=-1)
    return keep_components(policy, ~drop), removed
