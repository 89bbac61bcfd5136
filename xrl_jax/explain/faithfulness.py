"""Faithfulness, measured: deletion curves of how the action distribution and the return change when
the most important observed objects are removed.

An explanation ranks the objects of an observation; deleting the top-k (their rows zeroed, present
flag 0) and measuring the total variation between the policy before and after, or the return of an
agent that always acts on the deleted observation, tells whether the ranking found what the policy
uses. The rankings (:data:`RANKERS`): the mixture weight (X agents: their explanation), a random
order (the control), and for the Deep Set baselines, which have no weights, the post-hoc occlusion
(one object at a time) and gradient × input attributions.

X agents' per-object actors are myopic (a component sees its object and the ego state only), so
deleting an object from the observation is the same as dropping its component and renormalising the
weights (:func:`~xrl_jax.explain.explanations.keep_components`); deleting objects of total weight r
then changes the policy by at most r in total variation (π = (1−r)·π' + r·ρ).

Everything is jittable with the agent (and ranker, ks, set key) static; observations may carry any
leading batch axes (the Intersection's per-slot ones too).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp

from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture
from xrl_jax.explain.explanations import Policy, explain

Array = jax.Array
Observation = Mapping[str, Array]
Ranker = Callable[[Any, Any, Observation, Array], Array]
RANK_STREAM = 0x52414E4B  # folded into an act key for the ranker, so the act key itself stays the agent's


def present_objects(obs: Observation, set_key: str) -> Array:
    """(..., O) bool: the rows of the set that hold an object (column 0 is the present flag)."""
    return obs[set_key][..., 0] > 0


def delete_objects(obs: Observation, set_key: str, delete: Array) -> dict[str, Array]:
    """``obs`` with the row of every object where ``delete`` (..., O) is True zeroed (so absent);
    the other keys are passed through untouched."""
    rows = obs[set_key]
    return {**obs, set_key: jnp.where(delete[..., None], jnp.zeros((), rows.dtype), rows)}


def action_distance(p: Policy, q: Policy, key: Array, samples: int = 256) -> Array:
    """Total variation TV(p, q) (...,) between two policies of one agent (``agent.policy`` outputs).

    Categorical mixtures exactly: ½·Σ_a |p(a) − q(a)|. Squashed-Gaussian mixtures have no closed
    form, so by Monte Carlo in the pre-squash space u (TV is invariant under the bijection tanh, whose
    Jacobian cancels in q/p): TV = Σ max(0, p − q) = E_{u~p}[max(0, 1 − q(u)/p(u))]. The mean of
    ``samples`` i.i.d. draws is therefore unbiased, and as each term lies in [0, 1] its variance is at
    most TV·(1 − TV) ≤ ¼: standard error ≤ 0.5/√samples (0.031 at 256), and the estimate lies in [0, 1].
    """
    if isinstance(p, CategoricalMixture) and isinstance(q, CategoricalMixture):
        return 0.5 * jnp.sum(jnp.abs(p.probs() - q.probs()), axis=-1)
    if isinstance(p, SquashedGaussianMixture) and isinstance(q, SquashedGaussianMixture):
        draw = lambda k: p.sample_pre_squash_and_log_prob(k)[0]
        u = jax.vmap(draw)(jax.random.split(key, samples))  # (S, ..., A)
        log_ratio = q.log_prob_pre_squash(u) - p.log_prob_pre_squash(u)
        return jnp.mean(-jnp.expm1(jnp.minimum(log_ratio, 0.0)), axis=0)  # 1 − min(1, q/p), no overflow
    raise TypeError(f"no total variation between {type(p).__name__} and {type(q).__name__}")


# ------------------------------------------------------------------------------------------------
# Rankers: (agent, agent_state, obs, key) -> scores (..., O), higher = more important, absent -inf
# ------------------------------------------------------------------------------------------------


def _absent_last(scores: Array, obs: Observation, set_key: str) -> Array:
    return jnp.where(present_objects(obs, set_key), scores, -jnp.inf)


def rank_by_weight(agent, agent_state, obs: Observation, key: Array) -> Array:
    """The mixture weight of each object (the X agents' own explanation; the neutral component's
    weight is not an object's and is dropped)."""
    del key
    if not agent.config.is_mixture:
        raise ValueError(f"{agent.config.algo} has no mixture weights to rank by; use another ranker")
    weights = explain(agent, agent_state, obs).weights  # per object: components summed
    if agent.config.neutral_object:
        weights = weights[..., 1:]
    return _absent_last(weights, obs, agent.obs_shape.set_key)


def rank_random(agent, agent_state, obs: Observation, key: Array) -> Array:
    """I.i.d. uniform scores: the control a faithful ranking must beat."""
    del agent_state
    set_key = agent.obs_shape.set_key
    scores = jax.random.uniform(key, obs[set_key].shape[:-1], obs[set_key].dtype)
    return _absent_last(scores, obs, set_key)


def rank_by_occlusion(agent, agent_state, obs: Observation, key: Array) -> Array:
    """TV between the policy and the policy without object o, for each o. Every object's Monte Carlo
    estimate uses the same draws (``key``), so their comparison is not blurred by independent noise.
    One forward pass per object slot, vmapped: memory grows as slots × states, so chunk large batches."""
    set_key = agent.obs_shape.set_key
    params = agent_state.actor_params
    full = agent.policy(params, obs)
    num_objects = obs[set_key].shape[-2]

    def without(one_hot: Array) -> Array:
        return action_distance(full, agent.policy(params, delete_objects(obs, set_key, one_hot)), key)

    scores = jax.vmap(without)(jnp.eye(num_objects, dtype=bool))  # (O, ...)
    return _absent_last(jnp.moveaxis(scores, 0, -1), obs, set_key)


def _greedy_output(agent, params, obs: Observation) -> Array:
    """(..., D) what gradient × input explains: discrete agents the log-probability of their greedy
    action (D = 1); continuous ones the pre-squash location of the component whose tanh is the greedy
    action (D = A): SAC's mean μ, XSAC's approximate mode (docs/algorithms.md §3.9). A myopic XSAC
    component sees one object, so there only the mode's object scores above 0: gradient × input is
    meant for baselines."""
    out = agent.actor_output(params, obs)
    policy = agent.policy_from_output(out)
    greedy = jax.lax.stop_gradient(agent.networks.policy.greedy(out))
    if agent.is_discrete:
        return policy.log_prob(greedy.astype(jnp.int32))[..., None]
    miss = jnp.sum(jnp.abs(jnp.tanh(policy.loc) - greedy[..., None, :]), axis=-1)
    chosen = jnp.argmin(jnp.where(policy.weighted, jax.lax.stop_gradient(miss), jnp.inf), axis=-1)
    return jnp.take_along_axis(policy.loc, chosen[..., None, None], axis=-2)[..., 0, :]


def rank_by_gradient_x_input(agent, agent_state, obs: Observation, key: Array) -> Array:
    """Σ_d |Σ_f x_{o,f}·∂y_d/∂x_{o,f}|, y as in :func:`_greedy_output`: the first-order change of the
    greedy output when object o's row is scaled to zero, i.e. a linearised occlusion in one backward
    pass per output dimension. States are independent, so one gradient of the batch's sum serves all."""
    del key
    set_key = agent.obs_shape.set_key
    rows = obs[set_key]
    output = lambda r: _greedy_output(agent, agent_state.actor_params, {**obs, set_key: r})
    y, pullback = jax.vjp(output, rows)
    out_dim = y.shape[-1]  # one pullback per output dimension d: cotangent e_d at every state
    unit = jnp.eye(out_dim, dtype=y.dtype).reshape(out_dim, *([1] * (y.ndim - 1)), out_dim)
    cotangents = jnp.broadcast_to(unit, (out_dim, *y.shape))
    (grads,) = jax.vmap(pullback)(cotangents)  # (D, ..., O, F)
    scores = jnp.sum(jnp.abs(jnp.sum(grads * rows, axis=-1)), axis=0)
    return _absent_last(scores, obs, set_key)


RANKERS: dict[str, Ranker] = {
    "weight": rank_by_weight,
    "random": rank_random,
    "occlusion": rank_by_occlusion,
    "gradient_x_input": rank_by_gradient_x_input,
}


# ------------------------------------------------------------------------------------------------
# Deletion
# ------------------------------------------------------------------------------------------------


def deletion_mask(scores: Array, present: Array, k: int | Array, keep_one: bool = True) -> Array:
    """(..., O) bool: the ``k`` highest-scored present objects of each state, ties to the lower index.

    With ``keep_one`` at most (present − 1) are deleted: a mixture without a neutral component has
    nothing left to renormalise to once every object is gone. Scores must not be NaN.
    """
    mine, other = scores[..., :, None], scores[..., None, :]
    index = jnp.arange(scores.shape[-1])
    earlier = index[None, :] < index[:, None]  # [i, j]: j before i on a tie
    ahead = present[..., None, :] & ((other > mine) | ((other == mine) & earlier))
    rank = jnp.sum(ahead, axis=-1)  # among the present objects
    count = jnp.sum(present, axis=-1, keepdims=True)
    limit = jnp.clip(jnp.minimum(k, count - 1 if keep_one else count), 0)
    return present & (rank < limit)


def policy_change_curve(
    agent,
    agent_state,
    obs: Observation,
    set_key: str,
    ranker: Ranker,
    ks: tuple[int, ...],
    key: Array,
    samples: int = 256,
) -> Array:
    """(len(ks), ...) per state: TV between π(obs) and π(obs without its top-k objects) for each k in
    ``ks``. One ranking per state serves every k, and every k's Monte Carlo estimate uses the same
    draws, so the curve is not jagged by independent noise; averaging over states is the caller's.
    The ks are one vmapped axis (one forward pass in the program, len(ks) times the batch at run time)."""
    rank_key, distance_key = jax.random.split(key)
    scores = ranker(agent, agent_state, obs, rank_key)
    present = present_objects(obs, set_key)
    params = agent_state.actor_params
    full = agent.policy(params, obs)

    def change(k: Array) -> Array:
        deleted = delete_objects(obs, set_key, deletion_mask(scores, present, k))
        return action_distance(full, agent.policy(params, deleted), distance_key, samples)

    return jax.vmap(change)(jnp.asarray(ks, jnp.int32))


@dataclasses.dataclass(frozen=True, eq=False)  # hashes by identity, like Agent: a static jit argument
class DeletingAgent:
    """``agent`` acting on observations without their top-``k`` objects by ``ranker``, so that the
    project's evaluations (``make_evaluate(env, params, DeletingAgent(...), n)``) score the return of
    the deleted policy unchanged.

    Only :meth:`act` deletes; every other attribute is the wrapped agent's (its ``policy`` included).
    The wrapped agent gets the act key unchanged (the ranker a key folded from it), so a run differs
    from the agent's own only by the deletion; ``k = 0`` is the agent's own program, bit for bit.
    With ``k=None`` the count travels with the state instead, ``act(key, (agent_state, k), ...)``, so
    one compiled evaluation serves every k (vmapped over them).
    """

    agent: Any
    ranker: Ranker
    k: int | None
    keep_one: bool = True

    def __post_init__(self) -> None:
        if self.k is not None and (not isinstance(self.k, int) or self.k < 0):
            raise ValueError(f"k (objects deleted per observation) must be an int >= 0, got {self.k!r}")

    def act(self, key: Array, agent_state, obs: Observation, mode: str = "train") -> Array:
        if self.k == 0:
            return self.agent.act(key, agent_state, obs, mode)
        agent_state, k = (agent_state, self.k) if self.k is not None else agent_state
        set_key = self.agent.obs_shape.set_key
        scores = self.ranker(self.agent, agent_state, obs, jax.random.fold_in(key, RANK_STREAM))
        delete = deletion_mask(scores, present_objects(obs, set_key), k, self.keep_one)
        return self.agent.act(key, agent_state, delete_objects(obs, set_key, delete), mode)

    def __getattr__(self, name: str) -> Any:
        if name == "agent" or name.startswith("__"):  # not set yet (copying, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.agent, name)


__all__ = [
    "RANKERS",
    "DeletingAgent",
    "Ranker",
    "action_distance",
    "delete_objects",
    "deletion_mask",
    "policy_change_curve",
    "present_objects",
    "rank_by_gradient_x_input",
    "rank_by_occlusion",
    "rank_by_weight",
    "rank_random",
]
