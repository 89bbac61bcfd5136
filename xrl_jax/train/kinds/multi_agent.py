"""The multi-agent Intersection (docs/carenv-intersection.md §8): every vehicle slot of an env is an
actor driven by the one agent; the env restarts its own episodes (spawning, the 60 s restart); every
agent that acted stores its transition, packed one per buffer row, and is followed by one gradient
step; the evaluation replays fixed episodes with 8 vehicles (:mod:`xrl_jax.evaluation.multiagent`)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

import envs
from envs.core import VmapWrapper
from envs.intersection import MAX_AGENTS
from xrl_jax.buffer import buffer_add_packed
from xrl_jax.config import TrainConfig
from xrl_jax.evaluation import make_evaluate_multiagent
from xrl_jax.train.kinds.base import ScenarioKind
from xrl_jax.train.step import (
    MemberParts,
    RunState,
    act_and_step,
    episode_bookkeeping,
    sample_and_update,
    zero_metrics,
)


class MultiAgent(ScenarioKind):
    name = "multi_agent"
    rollout_velocity = "rollout/avg_mean_velocity"  # the windows hold per-agent episodes
    seeded_evaluation = False  # episode i always replays the env randomness of key (0, i)
    pairs_figure = True
    figure = "slots"
    slots_explained = MAX_AGENTS

    def make_envs(self, cfg: TrainConfig):
        """The curriculum for training, 8 vehicles for evaluation (docs/carenv-intersection.md §8.8)."""
        env, params = envs.make(cfg.env_name)
        return env, params, params.replace(max_vehicles=8)

    def vector_env(self, cfg: TrainConfig, env) -> VmapWrapper:
        """The env restarts itself."""
        return VmapWrapper(env, cfg.num_envs)

    def agent_slots(self, env) -> tuple[int, ...]:
        return (int(env.num_agents),)

    def buffer_columns(self, cfg: TrainConfig) -> int:
        """Packed transitions, one per row: a varying number of agents acts per step."""
        return 1

    def vector_step(self, parts: MemberParts, state: RunState, t):
        return multi_agent_step(parts, state, t)

    def chunk_metrics(self, outs, metrics: dict, average) -> None:
        """Episodes of whole envs (every slot restarted) and, per such episode, the completed trips and
        the early terminations (vehicles off the road or collided)."""
        episodes = jnp.sum(outs["episodes_ended"])
        metrics["rollout/env_episodes"] = episodes
        average("rollout/trips_per_episode", jnp.sum(outs["trips"]), episodes)
        average("rollout/early_terminations_per_episode", jnp.sum(outs["early_terminations"]), episodes)

    def make_evaluate(self, cfg: TrainConfig, env, eval_params, agent):
        return make_evaluate_multiagent(env, eval_params, agent, cfg.eval_episodes)

    def updates_per_env_step(self, cfg: TrainConfig, occupancy: dict) -> float:
        """One update per acting vehicle: as many as measured per env step."""
        return occupancy[cfg.env]["acting_vehicles_per_env_step"]


def multi_agent_step(parts: MemberParts, state: RunState, t):
    """One step of E multi-agent envs: every agent alive at the start of the step acts; its
    transition is stored (packed) and, after warm-up, followed by one gradient step
    (docs/carenv-intersection.md §8.5: updates = agent transitions, 0..8 per env step, as an exact
    ``while_loop``)."""
    key, update_key, agent_state, action, warm_env, step = act_and_step(parts, state, t)
    next_obs, venv_state, reward, terminated, truncated, info = step
    acted = info["acted"]

    def flat(x):
        return x.reshape((math.prod(parts.actors), *x.shape[2:]))

    buffer = buffer_add_packed(
        state.buffer,
        jax.tree.map(flat, state.obs),
        flat(action),
        flat(reward),
        flat(terminated & acted),  # 60 s restarts stay bootstrapped (docs/carenv-intersection.md §9 Q8)
        jax.tree.map(flat, info["final_obs"]),
        flat(acted),
    )
    owed = jnp.sum(acted & ~warm_env[:, None], dtype=jnp.int32)

    def keep_updating(carry):
        return carry[0] < owed

    def one_update(carry):
        count, agent_state, key, totals = carry
        key, sub = jax.random.split(key)
        agent_state, metrics = sample_and_update(parts, agent_state, buffer, sub)
        return count + 1, agent_state, key, jax.tree.map(jnp.add, totals, metrics)

    _, agent_state, _, metric_sums = jax.lax.while_loop(
        keep_updating, one_update, (jnp.zeros((), jnp.int32), agent_state, update_key, zero_metrics(parts))
    )
    reward = jnp.where(acted, reward, 0.0)
    agent_done = acted & (terminated | truncated)
    ended = info["episode_end"]
    new_state = state.with_venv_state(
        venv_state, agent=agent_state, buffer=buffer, obs=next_obs, key=key,
        **episode_bookkeeping(parts, state, reward, acted, agent_done, terminated,
                              info["mean_velocity"][:, None]),
    )  # fmt: skip
    out = {
        "reward_sum": jnp.sum(reward),
        "reward_count": jnp.sum(acted, dtype=jnp.int32),
        "metrics": metric_sums,
        "updates": owed,
        "episodes_ended": jnp.sum(ended, dtype=jnp.int32),
        "trips": jnp.sum(jnp.where(ended, info["trips_completed"], 0)),
        "early_terminations": jnp.sum(
            jnp.where(ended, info["come_off_vehicles"] + info["collided_vehicles"], 0)
        ),
    }
    return new_state, out


KIND = MultiAgent()
