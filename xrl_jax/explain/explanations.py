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

import functools
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from envs.actions import continuous_to_control, discrete_to_control
from xrl_jax.distributions import (
    ABSENT_LOG_WEIGHT,
    CategoricalMixture,
    SquashedGaussianMixture,
)
from xrl_jax.evaluation import evaluation_episode_keys, evaluation_step_key

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
    is_mixture = agent.config.is_mixture
    weights = policy.weights
    present = policy.present
    components_per_object = agent.config.components_per_object if is_mixture else 1
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


# ------------------------------------------------------------------------------------------------
# One evaluation episode with its explanations (device side; the figures are drawn on the host)
# ------------------------------------------------------------------------------------------------


@struct.dataclass
class EpisodeRecord:
    """One episode, padded to ``max_steps`` (leading time axis T everywhere).

    Step t holds the state s_t and observation o_t the agent saw, the explanation of π(·|o_t), the
    action a_t taken and its vehicle control, and the reward and end flags that a_t produced.
    ``valid[t]`` is False for the padding after the episode ended (those entries repeat the last state).
    """

    states: Any
    obs: Any
    explanations: Explanation
    actions: jax.Array
    controls: jax.Array  # (T, 3) mapped (steer, throttle, brake)
    rewards: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    valid: jax.Array

    @property
    def length(self) -> jax.Array:
        """Steps taken in the episode."""
        return jnp.sum(self.valid.astype(jnp.int32), axis=-1)


def single_track_params(params, index: int):
    """Racing params whose bank holds only track ``index`` of ``params``' bank (evaluation episode ``index``).

    This is how :func:`xrl_jax.evaluation.make_evaluate` gives episode i its fixed track.
    """
    bank_size = int(params.tracks.num_points.shape[0])
    if not 0 <= int(index) < bank_size:
        raise ValueError(f"track index {index} out of range: the bank holds {bank_size} tracks")
    pick = lambda leaf: leaf[int(index) : int(index) + 1]
    changes = {"tracks": jax.tree.map(pick, params.tracks)}
    if getattr(params, "tables", None) is not None:
        changes["tables"] = jax.tree.map(pick, params.tables)
    return params.replace(**changes)


def _act_and_record(agent, agent_state, mode: str, env_step, params, obs, state, act_key, env_key):
    """Act at ``obs``, step the env with ``env_step`` and return ``(next_obs, next_state, info,
    record)``; ``record`` holds the fields every episode record stores per step: the state and
    observation the action was taken in, the policy's explanation there, the action and its mapped
    control, and the outcome."""
    action = agent.act(act_key, agent_state, obs, mode)
    next_obs, next_state, reward, terminated, truncated, info = env_step(env_key, state, action, params)
    to_control = discrete_to_control if agent.is_discrete else continuous_to_control
    record = {
        "states": state,
        "obs": obs,
        "explanations": explain(agent, agent_state, obs),
        "actions": action,
        "controls": to_control(action),
        "rewards": reward,
        "terminated": terminated,
        "truncated": truncated,
    }
    return next_obs, next_state, info, record


def make_episode_rollout(env, agent, max_steps: int, mode: str = "eval") -> Callable:
    """``rollout(key, params, agent_state) -> EpisodeRecord``, jitted: one episode as one ``lax.scan``.

    The env is stepped without auto-reset (``reset_env`` / ``step_env``, like the evaluation); once
    the episode has ended the carry is frozen and the remaining steps are marked invalid, so the
    record has the fixed length ``max_steps``. ``mode`` is the agent's act mode (default: its
    evaluation policy, docs/algorithms.md §3.8).
    """
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")

    def rollout(key, params, agent_state) -> EpisodeRecord:
        reset_key, key = jax.random.split(key)
        obs, state = env.reset_env(reset_key, params)

        def step(carry, step_key):
            obs, state, done = carry
            act_key, env_key = jax.random.split(step_key)
            next_obs, next_state, _, out = _act_and_record(
                agent, agent_state, mode, env.step_env, params, obs, state, act_key, env_key
            )

            def freeze(new, old):
                return jax.tree.map(lambda n, o: jnp.where(done, o, n), new, old)

            out["valid"] = ~done
            ended = done | out["terminated"] | out["truncated"]
            carry = (freeze(next_obs, obs), freeze(next_state, state), ended)
            return carry, out

        carry = (obs, state, jnp.zeros((), bool))
        _, outs = jax.lax.scan(step, carry, jax.random.split(key, int(max_steps)))
        return EpisodeRecord(**outs)

    return jax.jit(rollout)


# ------------------------------------------------------------------------------------------------
# Multi-agent (Intersection): one evaluation episode, every slot explained
# ------------------------------------------------------------------------------------------------


@struct.dataclass
class MultiAgentEpisodeRecord(EpisodeRecord):
    """One multi-agent episode: time axis T, then the slot axis (8) on every per-agent field.

    Step t holds the state s_t and the per-slot observations o_t, the explanation of every slot's
    policy at o_t (also of empty slots, whose all-zero observation makes it meaningless: use
    ``acted``), the actions and their controls, and per slot the reward, end flags and
    ``done_reason`` (0 none, 1 route completed, 2 left the road, 3 collided, 4 non-finite action)
    of the step.
    ``acted[t, s]``: slot s held a car in s_t (its entries are meaningful); ``alive[t, s]``: it
    holds one after the step. A slot whose car ended can later be refilled by a NEW car (a larger
    ``states.spawn_seq``). ``valid`` is all True (kept for the single-agent record's interface).
    Fields beyond :class:`EpisodeRecord`'s carry the slot axis too (controls are (T, 8, 3)).
    """

    done_reason: jax.Array
    acted: jax.Array
    alive: jax.Array


@functools.lru_cache(maxsize=4)  # one compilation per (env, agent, length) in a process
def make_multiagent_episode_rollout(env, agent, max_steps: int, mode: str = "eval") -> Callable:
    """``rollout(episode, key, params, agent_state) -> MultiAgentEpisodeRecord``, jitted, one ``lax.scan``.

    Replays evaluation episode ``episode`` of a multi-agent env (keys of
    :func:`evaluation_episode_keys`; use the trainer's ``eval_params``, 8 vehicles) for
    ``max_steps`` steps (at most ``params.episode_steps``: beyond it the env restarts itself). Every
    slot acts with the agent's ``mode`` (default its evaluation policy); ``key`` feeds the policy's
    own randomness (XSAC samples), split per step like the evaluation.
    """
    max_steps = int(max_steps)
    if max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")

    def rollout(episode, key, params, agent_state) -> MultiAgentEpisodeRecord:
        if max_steps > int(params.episode_steps):
            raise ValueError(f"max_steps {max_steps} exceeds the episode length {params.episode_steps}")
        reset_key, stream_key = evaluation_episode_keys(episode)
        obs, state = env.reset(reset_key, params)

        def step(carry, t):
            obs, state, key = carry
            key, act_key = jax.random.split(key)
            env_key = evaluation_step_key(stream_key, t)
            next_obs, next_state, info, out = _act_and_record(
                agent, agent_state, mode, env.step, params, obs, state, act_key, env_key
            )
            out.update({k: info[k] for k in ("done_reason", "acted", "alive")}, valid=jnp.ones((), bool))
            return (next_obs, next_state, key), out

        steps = jnp.arange(max_steps, dtype=jnp.int32)
        _, outs = jax.lax.scan(step, (obs, state, key), steps)
        return MultiAgentEpisodeRecord(**outs)

    return jax.jit(rollout)
