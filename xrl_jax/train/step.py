"""One member's part of the compiled chunk: its run state, its start, and the pieces every vector step
is made of (act, step the envs, episode bookkeeping, sample and update). How a step stores its
transitions and owes its updates is the scenario kind's (:mod:`xrl_jax.train.kinds`: one transition
per env, or the packed transitions of every agent slot that acted). The functions take the member's
fixed pieces (:class:`MemberParts`) first; :mod:`xrl_jax.train.chunk` scans them, vmaps them over
members and spreads them over devices.

The envs come as one vector env (the kind's ``vector_env``) whatever restarts their episodes:
auto-reset on a fixed track bank or from a user's env's own reset, a fresh-track feed, or the
multi-agent env itself.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from flax import struct

from envs.core import VmapWrapper, action_size
from envs.track_feed import join_states, split_states
from xrl_jax.agents import Agent, AgentState
from xrl_jax.buffer import ReplayBuffer, buffer_init, buffer_sample
from xrl_jax.config import TrainConfig
from xrl_jax.evaluation import EARLY_TERMINATION_REWARD
from xrl_jax.train.episodes import EpisodeWindow, window_add, window_init


@struct.dataclass
class RunState:
    """One member's whole training state (a leading member axis when batched).

    The vector env's state (:attr:`venv_state`) is kept in two fields, the envs' own states and, on
    fresh tracks, the feed they share: the layout checkpoints have always had, so that earlier runs
    still restore (orbax matches the fields by name)."""

    agent: AgentState
    buffer: ReplayBuffer
    env_state: Any  # the vector env's per-env states
    obs: Any
    key: jax.Array
    eval_key: jax.Array
    episode_return: jax.Array  # (actors,) running return of the current episodes
    episode_length: jax.Array  # (actors,)
    window: EpisodeWindow
    feed: Any = None  # on fresh tracks: the envs' track feed (envs.track_feed.FreshTrackEnvs)
    # On the Intersection: gradient steps owed for transitions already stored (int32; None elsewhere,
    # so that the racing runs' checkpoints keep their layout). xrl_jax.train.kinds.multi_agent.
    owed_updates: Any = None

    # Fields that checkpoints of older versions lack and that restore as zeros (xrl_jax.checkpoint):
    # those versions paid every update in the step of its transition, so they never owed one.
    FIELDS_ADDED_LATER: ClassVar[tuple[str, ...]] = ("owed_updates",)

    @property
    def venv_state(self):
        """The vector env's state, whole."""
        return join_states(self.env_state, self.feed)

    def with_venv_state(self, venv_state, **changes) -> RunState:
        env_state, feed = split_states(venv_state)
        return self.replace(env_state=env_state, feed=feed, **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class MemberParts:
    """What one member's steps are built from: the config, its scenario kind (:mod:`xrl_jax.train.kinds`)
    and algorithm family (:mod:`xrl_jax.train.families`), its vector env and the params it steps
    with, the agent, and the shapes that the steps' branches must agree on."""

    cfg: TrainConfig
    kind: Any  # the scenario kind: how a vector step stores and updates (xrl_jax.train.kinds.ScenarioKind)
    family: Any  # the algorithm family: its agent, buffer and chunk step (xrl_jax.train.families)
    venv: VmapWrapper
    params: Any
    agent: Agent
    obs_example: Any  # one agent's observation (zeros)
    actors: tuple[int, ...]  # the batch shape of one acting step: envs, or envs x vehicle slots
    float_dtype: Any
    metric_shapes: Any = None  # the update's metrics


def member_parts(cfg: TrainConfig, kind, family, env, params) -> MemberParts:
    """The agent and the vector env for ``env`` of scenario kind ``kind`` under ``cfg``, the agent
    built by its algorithm family ``family`` (:mod:`xrl_jax.train.families`)."""
    obs_shapes = jax.eval_shape(env.reset, jax.random.PRNGKey(0), params)[0]
    # Actors: envs, and per env the kind's agent slots, whose observations carry those leading axes;
    # the agent sees one agent's view.
    slots = kind.agent_slots(env)
    actors = (cfg.num_envs, *slots)
    obs_shapes = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape[len(slots) :], s.dtype), obs_shapes)
    obs_example = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), obs_shapes)
    agent = family.make_agent(cfg.agent, obs_example, action_size(env.action_space(params)))
    venv = kind.vector_env(cfg, env)
    float_dtype = jnp.result_type(float)
    parts = MemberParts(cfg, kind, family, venv, params, agent, obs_example, actors, float_dtype)
    return dataclasses.replace(parts, metric_shapes=family.metric_shapes(parts))


def new_buffer(parts: MemberParts, capacity: int) -> ReplayBuffer:
    """An empty replay buffer of the kind's columns (one per env, or packed transitions one per row)."""
    cfg = parts.cfg
    columns = parts.kind.buffer_columns(cfg)
    action_example = parts.agent.random_action(jax.random.PRNGKey(0))
    return buffer_init(parts.obs_example, action_example, capacity, columns, layout=cfg.buffer_layout)


def init_member(parts: MemberParts, base_seed, index, hparams) -> RunState:
    """Member ``index`` of a run with base seed ``base_seed``: its keys fold ``index`` into the base
    seed's, its tracks (on fresh tracks) come from a stream of its own, apart from the agent's and
    the envs' keys."""
    cfg = parts.cfg
    key = jax.random.fold_in(jax.random.PRNGKey(base_seed), index)
    agent_key, env_key, run_key, eval_key = jax.random.split(key, 4)
    tracks_key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(cfg.track_seed), base_seed), index)
    obs, venv_state = parts.venv.reset(parts.venv.reset_key(env_key, tracks_key), parts.params)
    env_state, feed = split_states(venv_state)
    return RunState(
        agent=parts.agent.init(agent_key, parts.obs_example, hparams),
        buffer=parts.family.initial_buffer(parts),
        env_state=env_state,
        feed=feed,
        obs=obs,
        key=run_key,
        eval_key=eval_key,
        episode_return=jnp.zeros(parts.actors, parts.float_dtype),
        episode_length=jnp.zeros(parts.actors, jnp.int32),
        window=window_init(parts.float_dtype),
        owed_updates=parts.kind.initial_owed_updates(),
    )


def sample_and_update(parts: MemberParts, agent_state, buffer, key):
    sample_key, update_key = jax.random.split(key)
    data = buffer_sample(buffer, sample_key, parts.cfg.batch_size)
    data["truncated"] = jnp.zeros_like(data["terminated"])  # stored truncations are bootstrapped
    return parts.agent.update(update_key, agent_state, data)


def zero_metrics(parts: MemberParts):
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), parts.metric_shapes)


def reinitialises(cfg: TrainConfig, t) -> jax.Array:
    """Whether vector step ``t`` starts with a primacy-bias reset (docs/carenv-intersection.md §8.6):
    a step counted from 1 in it is a multiple of ``reinit_steps`` (False without resets)."""
    period = cfg.reinit_steps
    if not period:
        return jnp.bool_(False)
    first_transition = t * cfg.num_envs
    last = first_transition + cfg.num_envs - 1
    return (last // period) * period >= jnp.maximum(first_transition, 1)


def maybe_reinitialise(parts: MemberParts, agent_state, t, key):
    """A fresh agent (same traced hyper-parameters) when vector step ``t`` :func:`reinitialises`."""
    if not parts.cfg.reinit_steps:
        return agent_state
    hit = reinitialises(parts.cfg, t)  # unbatched: a real branch
    return jax.lax.cond(
        hit, lambda a: parts.agent.init(key, parts.obs_example, a.hparams), lambda a: a, agent_state
    )


def act_and_step(parts: MemberParts, state: RunState, t):
    """The common start of a vector step: (re-initialise,) act (random during warm-up), step the
    envs. Returns the next run key, the update key, the agent state, the action, which envs are
    still warming up and the env step's outputs."""
    key, act_key, random_key, env_key, update_key, reinit_key = jax.random.split(state.key, 6)
    num_envs, agent = parts.cfg.num_envs, parts.agent
    first_transition = t * num_envs
    agent_state = maybe_reinitialise(parts, state.agent, t, reinit_key)
    policy_action = agent.act(act_key, agent_state, state.obs, "train")
    random_action = agent.random_action(random_key, parts.actors)
    warm_env = first_transition + jnp.arange(num_envs) < parts.cfg.warmup_steps
    warm = warm_env.reshape(warm_env.shape + (1,) * (policy_action.ndim - 1))
    action = jnp.where(warm, random_action, policy_action)
    step = parts.venv.step(env_key, state.venv_state, action, parts.params)
    return key, update_key, agent_state, action, warm_env, step


def tree_all_finite(tree) -> jax.Array:
    """True when every floating-point leaf of ``tree`` is finite (one fused reduction)."""
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.bool_(True)


def episode_bookkeeping(parts: MemberParts, state: RunState, record):
    """Per-actor running episode return and length (actors: envs, or env × vehicle slot) from a
    step's :class:`~xrl_jax.train.kinds.base.StepRecord`; finished episodes enter the rolling window
    and restart from zero."""
    episode_return = state.episode_return + record.reward
    episode_length = state.episode_length + record.acted.astype(jnp.int32)
    done = record.done
    early = record.terminated & (record.reward < EARLY_TERMINATION_REWARD)
    velocity = jnp.broadcast_to(record.velocity, done.shape)
    window = window_add(
        state.window, *(x.reshape(-1) for x in (done, episode_return, episode_length, early, velocity))
    )
    return {
        "episode_return": jnp.where(done, 0.0, episode_return).astype(parts.float_dtype),
        "episode_length": jnp.where(done, 0, episode_length),
        "window": window,
    }


def vector_step(parts: MemberParts):
    """``(state, t) -> (state, outputs)``: one vector step of the member's envs, as its kind steps them."""
    return lambda state, t: parts.kind.vector_step(parts, state, t)
