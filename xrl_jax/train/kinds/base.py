"""What a scenario kind answers: the questions on which racing on tracks, the multi-agent Intersection
and a user's env differ, asked by the trainer, the evaluation, the report, the explanation figures and
the campaign instead of branching on the kind. Each answer has a default here where two kinds share
it; a kind overrides the rest (:mod:`.racing`, :mod:`.multi_agent`, :mod:`.user_env`).

The shared default of the vector step is the single-agent one (racing and a user's env step alike):
one transition per env and step, stored in the env's own buffer column, then one gradient step per
transition.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from envs.core import VmapWrapper, vmap_env
from xrl_jax.buffer import buffer_add
from xrl_jax.config import TrainConfig
from xrl_jax.runs.folder import RunFolderError
from xrl_jax.train.step import (
    MemberParts,
    RunState,
    act_and_step,
    episode_bookkeeping,
    sample_and_update,
    zero_metrics,
)


class StepRecord(NamedTuple):
    """What one vector step's env outputs mean to the learner and the episode bookkeeping, per actor
    (env, or env x agent slot): the kind reads them (:meth:`ScenarioKind.read_step`), so that both
    algorithm families store, bootstrap and count alike."""

    reward: jax.Array  # 0 where the actor did not act
    acted: jax.Array  # whether the actor took a step (an empty agent slot did not)
    terminated: jax.Array  # acted, and its episode ended without a value to bootstrap
    truncated: jax.Array  # acted, and its episode was cut off (bootstrapped)
    velocity: Any  # what the rollout window logs beside the return (broadcast over the actors)

    @property
    def done(self) -> jax.Array:
        return self.terminated | self.truncated


class ScenarioKind:
    """One kind of scenario (its name is :attr:`xrl_jax.config.Scenario.kind`), answering:

    * envs: :meth:`make_envs` (the env, its training and evaluation params), :meth:`vector_env` (how
      ended episodes restart);
    * the vector step: :meth:`agent_slots` (the actor batch after the env axis), :meth:`buffer_columns`
      (the replay buffer's layout; :attr:`TrainConfig.buffer_layout` is the config's, from the
      scenario's facts), :meth:`vector_step` (act, store, update), :meth:`read_step` (what a step's
      env outputs mean per actor), :meth:`step_outputs` and :meth:`chunk_metrics` (a chunk's
      metrics), :attr:`rollout_velocity` (what the rollout window logs beside returns);
    * evaluation: :meth:`make_evaluate` (the protocol of its runs), :meth:`check_reevaluation`
      (whether ``evaluate.py`` can drive its runs again on tracks), :attr:`seeded_evaluation`;
    * the campaign: :meth:`updates_per_env_step` (its cost);
    * the report and the explanation: :attr:`pairs_figure`, :attr:`endings`, :attr:`figure`,
      :attr:`slots_explained`.
    """

    name: str = ""
    # The rollout window's velocity metric; None: the env reports no velocity and no early termination.
    rollout_velocity: str | None = None
    # Whether eval_track_seed picks the evaluation's episodes (tracks, resets); False: they are fixed.
    seeded_evaluation: bool = True
    # The report's figure of learning curves per agent pair (the paper's Fig. 7).
    pairs_figure: bool = False
    # The explanation figure (xrl_jax.explain.run_figures): "track" (the bird view of one car on an
    # evaluation track), "slots" (the bird view following one agent slot) or "set" (the objects of a
    # user's env by weight).
    figure: str = ""
    # The agent slots an explanation can follow (--slot); 0: one agent, no slot to choose.
    slots_explained: int = 0
    # Whether the training episodes score what the evaluation does, so that the learning curve can
    # draw them beside it (False on the Intersection: one car's episodes against the whole scene's).
    training_episodes_like_evaluation: bool = True
    # CPU devices per core when a run splits a CPU host (xrl_jax.train.cpu_devices): members that
    # share a device run in lockstep, which costs where their work per step differs.
    cpu_devices_per_core: int = 1
    # Whether an actor may sit a step out (an empty agent slot): the on-policy losses then weigh only
    # the steps that were taken (xrl_jax.train.on_policy.rollout_batch).
    idle_actors: bool = False
    # Whether vector_step reads the run's length (cfg.total_steps): if not, runs of any length share
    # one compiled chunk (xrl_jax.train.chunk.get_trainer).
    steps_read_run_length: bool = False
    # The report's table of how the final evaluation's episodes end: (column, evaluation record key,
    # decimals shown), means over seeds in ``ending_unit``; none: the evaluation records no ending.
    endings: tuple[tuple[str, str, int], ...] = ()
    ending_unit: str = "share of episodes"

    # ---- envs ------------------------------------------------------------------------------------
    def make_envs(self, cfg: TrainConfig) -> tuple[Any, Any, Any]:
        """``(env, train_params, eval_params)`` of a run."""
        raise NotImplementedError

    def vector_env(self, cfg: TrainConfig, env) -> VmapWrapper:
        """The ``num_envs`` envs of one training member; by default each restarts from its own reset
        (auto-reset)."""
        return vmap_env(env, cfg.num_envs)

    # ---- the vector step -------------------------------------------------------------------------
    def agent_slots(self, env) -> tuple[int, ...]:
        """The actor axes after the env axis: () for one agent per env. Observations, actions and
        rewards carry them; the agent sees one slot's observation."""
        del env
        return ()

    def buffer_columns(self, cfg: TrainConfig) -> int:
        """Columns of the replay buffer: one per env (a row per vector step)."""
        return cfg.num_envs

    def vector_step(self, parts: MemberParts, state: RunState, t):
        """One vector step of the member's envs: ``(state, outputs)``."""
        return single_agent_step(parts, state, t)

    def read_step(self, reward, terminated, truncated, info) -> StepRecord:
        """The env step's outputs per actor: one agent per env, every one acting."""
        # A user's env reports no velocity.
        velocity = info.get("avg_track_velocity", jnp.zeros((), reward.dtype))
        return StepRecord(reward, jnp.ones(reward.shape, bool), terminated, truncated, velocity)

    def step_outputs(self, record: StepRecord, info) -> dict[str, jax.Array]:
        """One vector step's outputs that the chunk report sums: the reward and how many steps it
        counts (the truncated steps left out: the step reward averages the steps that were learned
        from in full), and whatever the kind's :meth:`chunk_metrics` reads."""
        del info
        return {
            "reward_sum": jnp.sum(jnp.where(record.truncated, 0.0, record.reward)),
            "reward_count": jnp.sum(~record.truncated, dtype=jnp.int32),
        }

    def initial_owed_updates(self):
        """The run state's count of gradient steps owed at the start (``RunState.owed_updates``):
        None for kinds that pay every step's updates in that step."""
        return None

    def chunk_metrics(self, outs, metrics: dict, average) -> None:
        """Add the kind's own metrics of a chunk to ``metrics`` from the vector steps' ``outs``
        (``average(name, total, count)`` writes an average that has data only when ``count`` > 0)."""
        del outs, metrics, average

    # ---- evaluation ------------------------------------------------------------------------------
    def make_evaluate(self, cfg: TrainConfig, env, eval_params, agent):
        """``evaluate(key, agent_state) -> per-episode arrays``: the protocol of the kind's runs."""
        raise NotImplementedError

    def check_reevaluation(self, cfg: TrainConfig, run, tracks: str) -> None:
        """Raise :class:`RunFolderError` (one line) when the run cannot be driven again on its
        ``tracks`` ("train" or "eval", ``experiments/evaluate.py``)."""
        del run, tracks
        raise RunFolderError(
            f"{cfg.env} runs have no tracks; their evaluation episodes are in the run's eval/"
        )

    # ---- the campaign ------------------------------------------------------------------------------
    def updates_per_env_step(self, cfg: TrainConfig, occupancy: dict) -> float:
        """Gradient updates per env step and seed after the warm-up (one per stored transition), by the
        measured ``occupancy`` table where they vary."""
        del cfg, occupancy
        return 1


def single_agent_step(parts: MemberParts, state: RunState, t):
    """One step of E single-agent envs: E transitions stored, then (after warm-up) one gradient step
    per transition, as a ``lax.scan`` over E sampled batches."""
    num_envs, warmup = parts.cfg.num_envs, parts.cfg.warmup_steps
    key, update_key, agent_state, action, _, step = act_and_step(parts, state, t)
    next_obs, venv_state, reward, terminated, truncated, info = step
    first_transition = t * num_envs
    buffer = buffer_add(
        state.buffer, state.obs, action, reward, terminated, truncated,
        next_obs=info["final_obs"] if parts.cfg.buffer_layout == "explicit" else None,
    )  # fmt: skip

    def scan_updates(agent_state, inputs):
        j, key = inputs
        active = first_transition + j >= warmup  # unbatched over seeds: a real branch
        agent_state, metrics = jax.lax.cond(
            active,
            lambda a: sample_and_update(parts, a, buffer, key),
            lambda a: (a, zero_metrics(parts)),
            agent_state,
        )
        return agent_state, (metrics, active)

    agent_state, (metrics, updated) = jax.lax.scan(
        scan_updates, agent_state, (jnp.arange(num_envs), jax.random.split(update_key, num_envs))
    )
    record = parts.kind.read_step(reward, terminated, truncated, info)
    new_state = state.with_venv_state(
        venv_state, agent=agent_state, buffer=buffer, obs=next_obs, key=key,
        **episode_bookkeeping(parts, state, record),
    )  # fmt: skip
    out = {
        **parts.kind.step_outputs(record, info),
        "metrics": jax.tree.map(lambda m: jnp.sum(jnp.where(updated, m, 0), axis=0), metrics),
        "updates": jnp.sum(updated, dtype=jnp.int32),
    }
    return new_state, out
