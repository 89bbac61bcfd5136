"""The algorithm families, one object each (:class:`AlgorithmFamily`): the off-policy SAC family
(a replay buffer, one gradient step per transition) and the on-policy PPO family (rollouts, epochs of
minibatch updates on them). The trainer and its memory estimate ask the run's family how its agent is
built, what a member's state starts with, what one scan iteration of a chunk does and what the chunk
reports, instead of branching on the algorithm; :func:`algorithm_family` is the one place that picks.

The families share the chunk's scan (:func:`xrl_jax.train.chunk.scan_chunk`): a family's chunk step
covers ``stride`` vector steps (one for the SAC family, a rollout for the PPO family) and returns its
outputs per vector step, so the report, the health checks and the partial last chunk are the same
code for both.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp

from xrl_jax.agents import make_agent, make_hparams
from xrl_jax.config import AgentConfig, TrainConfig
from xrl_jax.ppo import make_ppo_agent, make_ppo_hparams
from xrl_jax.train import on_policy
from xrl_jax.train.step import MemberParts, new_buffer, sample_and_update, tree_all_finite, vector_step


class AlgorithmFamily:
    """One family of algorithms (``xrl_jax.config.ALGOS`` or ``ON_POLICY_ALGOS``), answering:

    * the agent: :meth:`make_agent`, :meth:`hparams` (its traced constants), :meth:`metric_shapes`
      (what its updates report);
    * the member's state: :meth:`initial_buffer` (a replay buffer, or none);
    * the chunk: :meth:`chunk_step` (one scan iteration and the vector steps it covers),
      :meth:`chunk_metrics` (the family's own metrics of a chunk);
    * the memory estimate: :meth:`update_rows` (the rows one update takes, and the rollout's).
    """

    name: str = ""

    def make_agent(self, config: AgentConfig, obs_example, actions: int):
        raise NotImplementedError

    def hparams(self, config: AgentConfig, agent):
        """The agent's traced hyper-parameters of ``config`` (one member's)."""
        raise NotImplementedError

    def metric_shapes(self, parts: MemberParts):
        """Shapes of one update's metrics (the chunk report's names and dtypes)."""
        raise NotImplementedError

    def initial_buffer(self, parts: MemberParts):
        return None

    def chunk_step(self, parts: MemberParts) -> tuple[Any, int]:
        """``(step, stride)``: ``step(state, t) -> (state, outputs)`` advances the member by ``stride``
        vector steps from vector step ``t``; every output has a leading axis of ``stride`` (per vector
        step: ``reward_sum``, ``reward_count``, ``metrics``, ``updates``, ``env_nonfinite`` and the
        kind's own)."""
        raise NotImplementedError

    def chunk_metrics(self, state, metrics: dict, has_data: dict) -> None:
        """Add the family's own metrics of a chunk (read from the member's state at its end)."""
        del state, metrics, has_data

    def update_rows(self, cfg: TrainConfig, slots: int) -> tuple[int, int]:
        """``(rows of one update's batch, transitions a rollout holds in the chunk's temporaries)``
        for the memory estimate, ``slots`` actors per env."""
        raise NotImplementedError


class OffPolicy(AlgorithmFamily):
    """SAC, DSAC, XSAC, XDSAC: every transition into the replay buffer, one sampled update per
    transition after the warm-up (the scenario kind's vector step)."""

    name = "off_policy"

    def make_agent(self, config: AgentConfig, obs_example, actions: int):
        return make_agent(config, obs_example, actions)

    def hparams(self, config: AgentConfig, agent):
        return make_hparams(config, agent.action_size)

    def metric_shapes(self, parts: MemberParts):
        cfg = parts.cfg
        abstract_agent = jax.eval_shape(parts.agent.init, jax.random.PRNGKey(0), parts.obs_example)
        rows = max(cfg.batch_size, math.prod(parts.actors))
        abstract_buffer = jax.eval_shape(lambda: new_buffer(parts, rows))
        update = functools.partial(sample_and_update, parts)
        return jax.eval_shape(update, abstract_agent, abstract_buffer, jax.random.PRNGKey(0))[1]

    def initial_buffer(self, parts: MemberParts):
        return new_buffer(parts, parts.cfg.buffer_size)

    def chunk_step(self, parts: MemberParts):
        step = with_env_check(vector_step(parts))

        def one_vector_step(state, t):
            state, outs = step(state, t)
            return state, jax.tree.map(lambda x: x[None], outs)

        return one_vector_step, 1

    def chunk_metrics(self, state, metrics: dict, has_data: dict) -> None:
        metrics["train/ent_coef"] = jnp.exp(state.agent.log_alpha)  # the current α: always there
        has_data.pop("train/ent_coef", None)
        metrics["buffer/stored_rows"] = state.buffer.filled_rows

    def update_rows(self, cfg: TrainConfig, slots: int) -> tuple[int, int]:
        return cfg.batch_size, 0


class OnPolicy(AlgorithmFamily):
    """PPO, DPPO, XPPO, XDPPO: a rollout of ``rollout_steps`` vector steps with the current policy,
    then its updates (:mod:`xrl_jax.train.on_policy`); no replay buffer."""

    name = "on_policy"

    def make_agent(self, config: AgentConfig, obs_example, actions: int):
        return make_ppo_agent(config, obs_example, actions)

    def hparams(self, config: AgentConfig, agent):
        return make_ppo_hparams(config)

    def metric_shapes(self, parts: MemberParts):
        return on_policy.iteration_metric_shapes(parts)

    def chunk_step(self, parts: MemberParts):
        return functools.partial(on_policy.member_iteration, parts), parts.cfg.agent.rollout_steps

    def update_rows(self, cfg: TrainConfig, slots: int) -> tuple[int, int]:
        """A minibatch of the rollout, and the rollout."""
        a = cfg.agent
        transitions = a.rollout_steps * cfg.num_envs * slots
        return transitions // a.ppo_minibatches, transitions


OFF_POLICY, ON_POLICY = OffPolicy(), OnPolicy()


def algorithm_family(config: AgentConfig | TrainConfig) -> AlgorithmFamily:
    """The family of a run's (or an agent's) algorithm."""
    agent = config.agent if isinstance(config, TrainConfig) else config
    return ON_POLICY if agent.is_on_policy else OFF_POLICY


def with_env_check(step):
    """The vector step with one more output, ``env_nonfinite``: whether the env's outputs that training
    takes in were non-finite (1: the reward, as summed for the metrics; 2: the next observations; 0:
    neither). It only reads them: the training numbers are unchanged."""

    def checked(state, t):
        state, out = step(state, t)
        reward = (~jnp.isfinite(out["reward_sum"])).astype(jnp.int32)
        return state, out | {"env_nonfinite": reward + 2 * (~tree_all_finite(state.obs)).astype(jnp.int32)}

    return checked
