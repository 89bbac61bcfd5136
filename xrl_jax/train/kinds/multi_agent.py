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
from xrl_jax.sets import MEMBERS_AXIS, axis_bound
from xrl_jax.train.kinds.base import ScenarioKind, StepRecord
from xrl_jax.train.step import (
    MemberParts,
    RunState,
    act_and_step,
    episode_bookkeeping,
    reinitialises,
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
    endings = (("completed trips", "avg_trips_completed", 1), ("left the road", "avg_come_off_vehicles", 1),
               ("collided", "avg_collided_vehicles", 1))  # fmt: skip
    ending_unit = "cars per episode"
    training_episodes_like_evaluation = False  # one car's episodes; the evaluation scores the scene
    idle_actors = True  # a slot without a vehicle
    steps_read_run_length = True  # the owed updates are all paid at the run's last step
    cpu_devices_per_core = 2  # a member per device: none waits for another's vehicles (cpu_devices)

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

    def read_step(self, reward, terminated, truncated, info) -> StepRecord:
        """The slots that acted; the env's ``terminated`` and ``truncated`` hold for those only, its
        60 s restart truncates (bootstrapped: docs/carenv-intersection.md §9 Q8)."""
        acted = info["acted"]
        velocity = info["mean_velocity"][:, None]  # the env's, for each of its slots
        reward = jnp.where(acted, reward, 0.0)
        return StepRecord(reward, acted, terminated & acted, truncated & acted, velocity)

    def step_outputs(self, record: StepRecord, info) -> dict[str, jax.Array]:
        """The reward of every vehicle that acted, and the whole envs' episodes that ended with their
        trips and early terminations (for :meth:`chunk_metrics`)."""
        ended = info["episode_end"]
        early = info["come_off_vehicles"] + info["collided_vehicles"]
        return {
            "reward_sum": jnp.sum(record.reward),
            "reward_count": jnp.sum(record.acted, dtype=jnp.int32),
            "episodes_ended": jnp.sum(ended, dtype=jnp.int32),
            "trips": jnp.sum(jnp.where(ended, info["trips_completed"], 0)),
            "early_terminations": jnp.sum(jnp.where(ended, early, 0)),
        }

    def chunk_metrics(self, outs, metrics: dict, average) -> None:
        """Episodes of whole envs (every slot restarted) and, per such episode, the completed trips and
        the early terminations (vehicles off the road or collided)."""
        episodes = jnp.sum(outs["episodes_ended"])
        metrics["rollout/env_episodes"] = episodes
        average("rollout/trips_per_episode", jnp.sum(outs["trips"]), episodes)
        average("rollout/early_terminations_per_episode", jnp.sum(outs["early_terminations"]), episodes)

    def make_evaluate(self, cfg: TrainConfig, env, eval_params, agent):
        return make_evaluate_multiagent(env, eval_params, agent, cfg.eval_episodes)

    def initial_owed_updates(self):
        return jnp.zeros((), jnp.int32)

    def updates_per_env_step(self, cfg: TrainConfig, occupancy: dict) -> float:
        """One update per acting vehicle: as many as measured per env step."""
        return occupancy[cfg.env]["acting_vehicles_per_env_step"]


# How many gradient steps a member may fall behind its own transitions while it updates in lockstep
# with the members vmapped beside it. Members update together, so a step computes as many updates as
# the group pays and a member that owes fewer discards the rest: paying every member's transitions
# each step made the group compute the largest member's count (1.7x the useful updates for 4 members
# of 2 envs, whose episodes hold 1 to 8 vehicles for 600 steps at a time). Paying the least owed, and
# more only where a member would fall further behind than this, leaves 1.15x (docs/performance.md,
# "Intersection: members in one program"); 4,096 updates are about two episodes of one env.
MAX_OWED_UPDATES = 4096


def group_least_most(owed) -> tuple[jax.Array, jax.Array]:
    """The least and the most ``owed`` among the members vmapped together (on one device), or the
    member's own when it runs alone."""
    if axis_bound(MEMBERS_AXIS):
        return jax.lax.pmin(owed, MEMBERS_AXIS), jax.lax.pmax(owed, MEMBERS_AXIS)
    return owed, owed


def updates_to_pay(cfg: TrainConfig, owed, t) -> jax.Array:
    """How many gradient steps the member group computes in vector step ``t`` (the same for every
    member): the least owed, or more where a member would owe over :data:`MAX_OWED_UPDATES`; all of
    them before a primacy-bias reset and at the run's last step, so that every transition is
    followed by its gradient step before the agent it belongs to is replaced or the run ends."""
    least, most = group_least_most(owed)
    settle = (t == cfg.total_vector_steps - 1) | reinitialises(cfg, t + 1)
    return jnp.where(settle, most, jnp.maximum(least, most - MAX_OWED_UPDATES))


def multi_agent_step(parts: MemberParts, state: RunState, t):
    """One step of E multi-agent envs: every agent alive at the start of the step acts and its
    transition is stored (packed); after warm-up each stored transition is owed one gradient step
    (docs/carenv-intersection.md §8.5: updates = agent transitions, 0..8 per env step). A member alone
    pays its count every step, exactly as the original; members vmapped together pay
    :func:`updates_to_pay` as one loop, each applying the steps it owes and skipping the rest."""
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
    owed = state.owed_updates + jnp.sum(acted & ~warm_env[:, None], dtype=jnp.int32)
    pay = updates_to_pay(parts.cfg, owed, t)

    def keep_updating(carry):
        return carry[0] < pay

    def one_update(carry):
        count, agent_state, key, totals = carry
        key, sub = jax.random.split(key)
        updated, metrics = sample_and_update(parts, agent_state, buffer, sub)
        due = count < owed  # False only for a member that owes fewer than its group pays
        agent_state = jax.tree.map(lambda new, old: jnp.where(due, new, old), updated, agent_state)
        totals = jax.tree.map(lambda total, m: total + jnp.where(due, m, 0), totals, metrics)
        return count + 1, agent_state, key, totals

    _, agent_state, _, metric_sums = jax.lax.while_loop(
        keep_updating, one_update, (jnp.zeros((), jnp.int32), agent_state, update_key, zero_metrics(parts))
    )
    paid = jnp.minimum(owed, pay)
    record = parts.kind.read_step(reward, terminated, truncated, info)
    new_state = state.with_venv_state(
        venv_state, agent=agent_state, buffer=buffer, obs=next_obs, key=key, owed_updates=owed - paid,
        **episode_bookkeeping(parts, state, record),
    )  # fmt: skip
    out = {**parts.kind.step_outputs(record, info), "metrics": metric_sums, "updates": paid}
    return new_state, out


KIND = MultiAgent()
