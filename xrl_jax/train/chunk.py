"""The compiled part of a run: the run state, one chunk of ``log_interval`` transitions per member as
one ``lax.scan`` (vmapped over members), its per-member report and health checks, and evaluation.

Per seed (docs/algorithms.md §5, mapped to synchronous vector envs as §5.8 recommends):

* ``num_envs`` = E auto-resetting envs step in lock-step; every vector step collects E transitions;
* the first ``warmup_steps`` transitions use uniformly random actions and trigger no update;
* afterwards every transition is followed by one gradient step (update-to-data ratio 1): E updates
  per vector step, as a ``lax.scan`` over E sampled batches; discrete agents act uniformly at random
  with probability 5 % (inside ``Agent.act``);
* racing envs start every episode on a fresh track from the seed's own track feed
  (:mod:`envs.track_feed`, refilled at the start of a chunk when needed), or with ``train_tracks`` > 0
  on a track drawn from a fixed bank;
* transitions go into the device-resident replay buffer (:mod:`xrl_jax.buffer`); with the paper's
  ``truncation="drop"`` the compact one-copy layout drops truncated transitions, with
  ``"bootstrap"`` the explicit layout keeps them with their true final observation.

A *chunk* is ``log_interval / E`` vector steps inside one jitted ``lax.scan``; the chunk is
``vmap``-ped over the run's *members* (sweep points x seeds; a plain run is a sweep of one point) and
compiled once per configuration, with the run state donated. A member's swept values are traced
leaves of its agent state (``AgentState.hparams``), so one program trains every point. The global
step counter enters unbatched, so warm-up and end-of-run gating are real ``lax.cond``s and cost
nothing under ``vmap``. Between chunks the host loop (:mod:`xrl_jax.train.loop`) writes metrics,
evaluates, checkpoints and draws the progress bar.

**Devices.** The member axis is spread over a one-axis device mesh (``"member"``) with
``jax.shard_map`` rather than a sharded ``jit``: members never talk to each other, and shard_map
makes that explicit. Each device runs exactly the one-device program on its block of members, so
a member's numbers do not depend on the partitioner's choices (no resharding of the replay
buffer's per-member gathers, no collectives it might insert), and they equal those of any other
multi-device run with as many members per device bit for bit (a one-device mesh compiles without
SPMD partitioning, where XLA reassociates a few divisions: the last bits differ; tests/test_scaling.py
says how much). The only cross-member quantities are two
explicit ``psum``s: whether any member's track feed needs a refill (a real branch, taken by all
devices alike) and how many members are unhealthy (every process of a multi-host run learns that a
member diverged, also one held by another process).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from xrl_jax.agents import Agent, AgentState, HyperParams, make_agent, make_hparams
from xrl_jax.buffer import ReplayBuffer, buffer_add, buffer_add_packed, buffer_init, buffer_sample
from xrl_jax.config import HOST_ONLY_FIELDS, TrainConfig
from xrl_jax.evaluation import make_evaluate, make_evaluate_multiagent
from xrl_jax.sets import MEMBERS_AXIS
from xrl_jax.tracks import make_envs
from xrl_jax.train.episodes import (
    EARLY_TERMINATION_REWARD,
    EpisodeWindow,
    window_add,
    window_init,
    window_means,
)


@struct.dataclass
class RunState:
    """One seed's whole training state (a leading seed axis when batched)."""

    agent: AgentState
    buffer: ReplayBuffer
    env_state: Any
    obs: Any
    key: jax.Array
    eval_key: jax.Array
    episode_return: jax.Array  # (E,) running return of the current episodes
    episode_length: jax.Array  # (E,)
    window: EpisodeWindow
    feed: Any = None  # racing on fresh tracks: this seed's envs.track_feed.TrackFeed


def tree_all_finite(tree) -> jax.Array:
    """True when every floating-point leaf of ``tree`` is finite (one fused reduction)."""
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.bool_(True)


def _update_metric_order(metrics) -> list[str]:
    """The update's metric names, losses first: when a step turns several of them non-finite at
    once, the health check names a loss (the likely cause) rather than, say, a Q-value statistic."""
    return sorted(metrics, key=lambda name: (not name.startswith("loss"), name))


@struct.dataclass
class ChunkHealth:
    """What the host checks after every chunk, per seed, before it trusts the new state."""

    first_nonfinite_step: jax.Array  # transition step of the first non-finite update metric; -1: none
    first_nonfinite_loss: jax.Array  # that metric's index in ``Trainer.loss_names``; -1: none
    agent_finite: jax.Array  # every parameter and optimiser state of the agent is finite


@struct.dataclass
class ChunkReport:
    """A chunk's per-seed outputs: metric values, which of them have data yet (an average over no
    update or no finished episode has none, and is written as null), and the health checks."""

    metrics: dict
    has_data: dict
    health: ChunkHealth
    unhealthy_members: jax.Array = 0  # over all devices and processes (replicated): > 0 stops the run


MEMBER_AXIS = "member"


def mesh_devices(count: int = 0) -> list:
    """The devices a run spreads its members over: the first ``count`` devices of every process (0:
    all of them), in the same order on every process."""
    by_process: dict[int, list] = {}
    for device in sorted(jax.devices(), key=lambda d: (d.process_index, d.id)):
        by_process.setdefault(device.process_index, []).append(device)
    local = len(by_process[jax.process_index()])
    if count > local:
        raise ValueError(
            f"--devices {count}: this process sees only {local} {jax.default_backend()} device(s)"
        )
    return [d for devices in by_process.values() for d in (devices[:count] if count else devices)]


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """The compiled pieces of one configuration (build with :func:`make_train`), over a device mesh.

    * ``init(base_seed, seed_indices, hparams=None) -> RunState`` with a leading member axis: member
      ``j`` starts from ``fold_in(PRNGKey(base_seed), seed_indices[j])`` with hyper-parameters
      ``hparams`` (a :class:`HyperParams` of per-member values; default: the config's), so a member's
      stream depends only on its seed and its values, not on its group or the member count. The same
      seed at two sweep points starts from the same weights and tracks (common random numbers: the
      points differ by their values alone). The member count must be a multiple of the mesh size;
    * ``chunk(state, start_vector_step) -> (state, ChunkReport)``: ``log_interval`` transitions per
      member, the state donated; the report's values are per-member scalars;
    * ``evaluate(state) -> (eval_keys, per_episode)``: the §6.1 protocol on the fixed tracks.

    ``loss_names`` are the update's metrics (losses first) in the order that
    ``ChunkHealth.first_nonfinite_loss`` counts.
    """

    config: TrainConfig
    env: Any
    env_params: Any
    eval_params: Any
    agent: Agent
    mesh: Mesh
    init_members: Any  # (base_seed, seed_indices, hparams) -> RunState, sharded over the mesh
    chunk: Any
    evaluate: Any
    loss_names: tuple[str, ...] = ()
    unsharded_init: Any = None  # the same without a mesh, for shapes

    @property
    def num_devices(self) -> int:
        return int(self.mesh.devices.size)

    @property
    def member_sharding(self) -> NamedSharding:
        return NamedSharding(self.mesh, P(MEMBER_AXIS))

    def put_members(self, tree):
        """Host arrays with a leading member axis as global arrays sharded over the mesh (every
        process passes the whole arrays and keeps the rows of its own devices)."""
        sharding = self.member_sharding

        def put(x):
            x = np.asarray(x)
            return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

        return jax.tree.map(put, tree)

    def default_hparams(self, num_members: int) -> HyperParams:
        """The config's own values for every member (the trainer's config holds no sweep)."""
        return member_hparams(self.config, self.agent, [0] * num_members)

    def init(self, base_seed, seed_indices, hparams: HyperParams | None = None) -> RunState:
        seeds = np.asarray(seed_indices, np.int32)
        if seeds.shape[0] % self.num_devices:
            raise ValueError(
                f"{seeds.shape[0]} members cannot be spread evenly over {self.num_devices} devices"
            )
        if hparams is None:
            hparams = self.default_hparams(seeds.shape[0])
        return self.init_members(np.int32(base_seed), *self.put_members((seeds, hparams)))

    def abstract_state(self, num_members: int, sharded: bool = True) -> RunState:
        """Shapes and dtypes of ``num_members`` members' state (nothing allocated); sharded over
        the mesh (a restore target) when the count divides evenly."""
        abstract = jax.eval_shape(
            self.unsharded_init,
            jnp.int32(0),
            jnp.zeros(num_members, jnp.int32),
            self.default_hparams(num_members),
        )
        if not sharded or num_members % self.num_devices:
            return abstract
        sharding = self.member_sharding
        return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sharding), abstract)


_TRAINER_CACHE: dict[tuple, Trainer] = {}


def get_trainer(cfg: TrainConfig, devices: list | None = None) -> Trainer:
    """:func:`make_train` memoised on everything that changes the compiled code (not the seeds, not
    the swept values) and on the devices: runs of the same configuration in one process share
    their compilations."""
    devices = mesh_devices(cfg.num_devices) if devices is None else list(devices)
    # Settings that only the host loop reads; the step count matters only for a partial last chunk.
    key = cfg.replace(
        seed=0,
        num_seeds=1,
        sweep=(),
        **{name: TrainConfig.__dataclass_fields__[name].default for name in HOST_ONLY_FIELDS},
        eval_interval=cfg.log_interval,
        checkpoint_interval=cfg.log_interval,
        total_steps=cfg.total_steps if cfg.total_steps % cfg.log_interval else cfg.log_interval,
    )
    cache_key = (key, tuple(d.id for d in devices))
    if cache_key not in _TRAINER_CACHE:
        if len(_TRAINER_CACHE) >= 4:
            _TRAINER_CACHE.pop(next(iter(_TRAINER_CACHE)))
        _TRAINER_CACHE[cache_key] = make_train(key, devices=devices)
    return _TRAINER_CACHE[cache_key]


def member_hparams(cfg: TrainConfig, agent: Agent, members: list[int]) -> HyperParams:
    """Each member's traced hyper-parameters (its sweep point's values), stacked on a leading axis."""
    per_point = [make_hparams(cfg.point_agent(p), agent.action_size) for p in range(cfg.num_points)]
    rows = [per_point[cfg.member_point_seed(m)[0]] for m in members]
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *rows)


def make_train(cfg: TrainConfig, env_and_params: tuple | None = None, devices: list | None = None) -> Trainer:
    """Build the agent, the vector env and the jitted init / chunk / evaluate functions for ``cfg``,
    spread over ``devices`` (default: the first device only)."""
    from envs import track_feed
    from envs.core import vmap_env

    env, params, eval_params = env_and_params if env_and_params is not None else make_envs(cfg)
    num_envs, batch, warmup = cfg.num_envs, cfg.batch_size, cfg.warmup_steps
    multi, fresh = cfg.multi_agent, cfg.fresh_tracks
    # The multi-agent env restarts itself; on fresh tracks the feed assigns each new episode's track.
    venv = vmap_env(env, num_envs, auto_reset=not (multi or fresh))
    refill_count = cfg.track_feed_size // 2
    obs_shapes = jax.eval_shape(env.reset, jax.random.PRNGKey(0), params)[0]
    if multi:  # observations carry a leading agent-slot axis; the agent sees one agent's view
        slots = int(env.num_agents)
        obs_shapes = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape[1:], s.dtype), obs_shapes)
    obs_example = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), obs_shapes)
    space = env.action_space(params)
    action_size = int(space.n) if hasattr(space, "n") else int(space.shape[0])
    agent = make_agent(cfg.agent, obs_example, action_size)
    explicit = cfg.buffer_layout == "explicit"
    action_example = agent.random_action(jax.random.PRNGKey(0))
    float_dtype = jnp.result_type(float)
    actors = (num_envs, slots) if multi else (num_envs,)  # the batch shape of one acting step
    buffer_columns = 1 if multi else num_envs  # multi-agent transitions are packed, one per row

    def new_buffer(capacity):
        return buffer_init(obs_example, action_example, capacity, buffer_columns, layout=cfg.buffer_layout)

    def init_one(base_seed, index, hparams):
        key = jax.random.fold_in(jax.random.PRNGKey(base_seed), index)
        agent_key, env_key, run_key, eval_key = jax.random.split(key, 4)
        feed = None
        if fresh:  # seed i's tracks: a stream of its own, apart from the agent's and the envs' keys
            run_tracks = jax.random.fold_in(jax.random.PRNGKey(cfg.track_seed), base_seed)
            feed_key = jax.random.fold_in(run_tracks, index)
            feed = track_feed.init_feed(env, params, feed_key, cfg.track_feed_size, num_envs)
            obs, env_state, feed = track_feed.reset_with_feed(env, feed)
        else:
            obs, env_state = venv.reset(env_key, params)
        return RunState(
            agent=agent.init(agent_key, obs_example, hparams),
            buffer=new_buffer(cfg.buffer_size),
            env_state=env_state,
            obs=obs,
            key=run_key,
            eval_key=eval_key,
            episode_return=jnp.zeros(actors, float_dtype),
            episode_length=jnp.zeros(actors, jnp.int32),
            window=window_init(float_dtype),
            feed=feed,
        )

    def sample_and_update(agent_state, buffer, key):
        sample_key, update_key = jax.random.split(key)
        data = buffer_sample(buffer, sample_key, batch)
        data["truncated"] = jnp.zeros_like(data["terminated"])  # stored truncations are bootstrapped
        return agent.update(update_key, agent_state, data)

    abstract_agent = jax.eval_shape(agent.init, jax.random.PRNGKey(0), obs_example)
    abstract_buffer = jax.eval_shape(lambda: new_buffer(max(cfg.batch_size, math.prod(actors))))
    metric_shapes = jax.eval_shape(sample_and_update, abstract_agent, abstract_buffer, jax.random.PRNGKey(0))[
        1
    ]

    def zero_metrics():
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), metric_shapes)

    def maybe_reinitialise(agent_state, first_transition, key):
        """Primacy-bias reset (docs/carenv-intersection.md §8.6): a fresh agent (same traced hyper-parameters)
        whenever a step counted from 1 in this vector step is a multiple of ``reinit_steps``."""
        if not cfg.reinit_steps:
            return agent_state
        period = cfg.reinit_steps
        last = first_transition + num_envs - 1
        hit = (last // period) * period >= jnp.maximum(first_transition, 1)  # unbatched: a real branch
        return jax.lax.cond(hit, lambda a: agent.init(key, obs_example, a.hparams), lambda a: a, agent_state)

    def act_and_step(state: RunState, t):
        """The common start of a vector step: (re-initialise,) act (random during warm-up), step the
        envs. Returns the next run key, the update key, the agent state, the action, which envs are
        still warming up, the env step's outputs and the track feed."""
        key, act_key, random_key, env_key, update_key, reinit_key = jax.random.split(state.key, 6)
        first_transition = t * num_envs
        agent_state = maybe_reinitialise(state.agent, first_transition, reinit_key)
        policy_action = agent.act(act_key, agent_state, state.obs, "train")
        random_action = agent.random_action(random_key, actors)
        warm_env = first_transition + jnp.arange(num_envs) < warmup
        warm = warm_env.reshape(warm_env.shape + (1,) * (policy_action.ndim - 1))
        action = jnp.where(warm, random_action, policy_action)
        if fresh:
            *step, feed = track_feed.step_with_feed(env, env_key, state.env_state, action, state.feed)
            return key, update_key, agent_state, action, warm_env, tuple(step), feed
        step = venv.step(env_key, state.env_state, action, params)
        return key, update_key, agent_state, action, warm_env, step, state.feed

    def episode_bookkeeping(state, reward, counted, done, terminated, velocity):
        """Per-actor running episode return and length (actors: envs, or env × vehicle slot);
        finished episodes enter the rolling window and restart from zero."""
        episode_return = state.episode_return + reward
        episode_length = state.episode_length + counted.astype(jnp.int32)
        early = terminated & (reward < EARLY_TERMINATION_REWARD)
        velocity = jnp.broadcast_to(velocity, done.shape)
        window = window_add(
            state.window, *(x.reshape(-1) for x in (done, episode_return, episode_length, early, velocity))
        )
        return {
            "episode_return": jnp.where(done, 0.0, episode_return).astype(float_dtype),
            "episode_length": jnp.where(done, 0, episode_length),
            "window": window,
        }

    def vector_step(state: RunState, t):
        key, update_key, agent_state, action, _, step, feed = act_and_step(state, t)
        next_obs, env_state, reward, terminated, truncated, info = step
        first_transition = t * num_envs
        buffer = buffer_add(
            state.buffer, state.obs, action, reward, terminated, truncated,
            next_obs=info["final_obs"] if explicit else None,
        )  # fmt: skip

        def scan_updates(agent_state, inputs):
            j, key = inputs
            active = first_transition + j >= warmup  # unbatched over seeds: a real branch
            agent_state, metrics = jax.lax.cond(
                active,
                lambda a: sample_and_update(a, buffer, key),
                lambda a: (a, zero_metrics()),
                agent_state,
            )
            return agent_state, (metrics, active)

        agent_state, (metrics, updated) = jax.lax.scan(
            scan_updates, agent_state, (jnp.arange(num_envs), jax.random.split(update_key, num_envs))
        )
        done = terminated | truncated
        new_state = state.replace(
            agent=agent_state, buffer=buffer, env_state=env_state, obs=next_obs, key=key, feed=feed,
            **episode_bookkeeping(state, reward, jnp.ones(done.shape, bool), done, terminated,
                                  info["avg_track_velocity"]),
        )  # fmt: skip
        out = {
            "reward_sum": jnp.sum(jnp.where(truncated, 0.0, reward)),
            "reward_count": jnp.sum(~truncated, dtype=jnp.int32),
            "metrics": jax.tree.map(lambda m: jnp.sum(jnp.where(updated, m, 0), axis=0), metrics),
            "updates": jnp.sum(updated, dtype=jnp.int32),
        }
        return new_state, out

    def multi_agent_step(state: RunState, t):
        """One step of E multi-agent envs: every agent alive at the start of the step acts; its
        transition is stored (packed) and, after warm-up, followed by one gradient step
        (docs/carenv-intersection.md §8.5: updates = agent transitions, 0..8 per env step, as an exact
        ``while_loop``)."""
        key, update_key, agent_state, action, warm_env, step, _ = act_and_step(state, t)
        next_obs, env_state, reward, terminated, truncated, info = step
        acted = info["acted"]

        def flat(x):
            return x.reshape((num_envs * slots, *x.shape[2:]))

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
            agent_state, metrics = sample_and_update(agent_state, buffer, sub)
            return count + 1, agent_state, key, jax.tree.map(jnp.add, totals, metrics)

        _, agent_state, _, metric_sums = jax.lax.while_loop(
            keep_updating, one_update, (jnp.zeros((), jnp.int32), agent_state, update_key, zero_metrics())
        )
        reward = jnp.where(acted, reward, 0.0)
        agent_done = acted & (terminated | truncated)
        ended = info["episode_end"]
        new_state = state.replace(
            agent=agent_state, buffer=buffer, env_state=env_state, obs=next_obs, key=key,
            **episode_bookkeeping(state, reward, acted, agent_done, terminated,
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

    step_fn = multi_agent_step if multi else vector_step

    def chunk_one(state: RunState, start_vector_step):
        def body(state, i):
            return step_fn(state, start_vector_step + i)

        if cfg.total_steps % cfg.log_interval:  # the last chunk is partial: gate its tail (a real cond)

            def body(state, i):
                t = start_vector_step + i
                return jax.lax.cond(t < cfg.total_vector_steps, step_fn, skip_step, state, t)

            def skip_step(state, t):
                shapes = jax.eval_shape(step_fn, state, t)[1]
                return state, jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

        state, outs = jax.lax.scan(body, state, jnp.arange(cfg.chunk_vector_steps, dtype=jnp.int32))
        updates = jnp.sum(outs["updates"])
        metrics, has_data = {}, {}

        def average(name, total, count):
            metrics[name] = total / jnp.maximum(count, 1)
            has_data[name] = count > 0

        for k, v in outs["metrics"].items():
            average(f"train/{k}", jnp.sum(v), updates)
        metrics["train/updates"] = state.agent.step
        metrics["train/ent_coef"] = jnp.exp(state.agent.log_alpha)  # the current α: always there
        has_data.pop("train/ent_coef", None)
        average("rollout/avg_step_reward", jnp.sum(outs["reward_sum"]), jnp.sum(outs["reward_count"]))
        rollout, window_filled = window_means(state.window, multi)
        metrics.update(rollout)
        has_data.update({name: window_filled for name in rollout if name != "rollout/episodes"})
        if multi:
            episodes = jnp.sum(outs["episodes_ended"])
            metrics["rollout/env_episodes"] = episodes
            average("rollout/trips_per_episode", jnp.sum(outs["trips"]), episodes)
            average("rollout/early_terminations_per_episode", jnp.sum(outs["early_terminations"]), episodes)
        metrics["buffer/stored_rows"] = state.buffer.filled_rows
        if fresh:  # distinct tracks driven so far, and resets that found the feed empty
            metrics["rollout/tracks_used"] = state.feed.issued
            metrics["rollout/tracks_reused"] = state.feed.reused
        # The first vector step whose update produced a non-finite loss (and which one), and whether
        # the agent's parameters and optimiser states are still finite: the host stops on either.
        bad = jnp.stack([~jnp.isfinite(outs["metrics"][k]) for k in _update_metric_order(outs["metrics"])], 1)
        bad_step = jnp.any(bad, axis=1)
        first = jnp.argmax(bad_step)
        health = ChunkHealth(
            first_nonfinite_step=jnp.where(
                jnp.any(bad_step), (start_vector_step + first + 1) * num_envs, -1
            ).astype(jnp.int32),
            first_nonfinite_loss=jnp.where(jnp.any(bad_step), jnp.argmax(bad[first]), -1).astype(jnp.int32),
            agent_finite=tree_all_finite(state.agent),
        )
        return state, ChunkReport(metrics=metrics, has_data=has_data, health=health)

    if multi:
        evaluate_one = make_evaluate_multiagent(env, eval_params, agent, cfg.eval_episodes)
    else:
        evaluate_one = make_evaluate(env, eval_params, agent, cfg.eval_episodes)

    def evaluate_seed(state: RunState):
        key, sub = jax.random.split(state.eval_key)
        return key, evaluate_one(sub, state.agent)

    def refill_feeds(feed):
        """Generate tracks into every member's free slots once some member, on any device, can take
        half a feed. The condition is the same on every device (a ``psum``), so it is a real branch:
        chunks without a refill generate nothing. Which track an episode gets does not depend on when
        refills happen (envs/track_feed.py); a track costs ~3 ms on a CPU core."""
        room = jnp.any(track_feed.writable(feed, refill_count)[2][..., -1])  # room for all of them
        needed = jax.lax.psum(room.astype(jnp.int32), MEMBER_AXIS) > 0
        return jax.lax.cond(needed, lambda f: track_feed.refill_feed(env, f, refill_count), lambda f: f, feed)

    def chunk_block(state: RunState, start_vector_step):
        """One device's block of members."""
        if fresh:
            state = state.replace(feed=refill_feeds(state.feed))
        # Named, so that the members of a block share their packed-or-dense branches (xrl_jax.sets).
        chunk_members = jax.vmap(chunk_one, in_axes=(0, None), axis_name=MEMBERS_AXIS)
        state, report = chunk_members(state, start_vector_step)
        health = report.health
        unhealthy = jnp.sum((health.first_nonfinite_step >= 0) | ~health.agent_finite, dtype=jnp.int32)
        return state, report.replace(unhealthy_members=jax.lax.psum(unhealthy, MEMBER_AXIS))

    mesh = Mesh(np.array(devices if devices is not None else jax.devices()[:1]), (MEMBER_AXIS,))
    members, replicated = P(MEMBER_AXIS), P()
    # check_vma=False: the env and agent code is written for one member and mixes unbatched loop
    # counters with per-member values; the type check would need casts throughout it, and the only
    # cross-device values are the two psums above.
    shard_map = functools.partial(jax.shard_map, mesh=mesh, check_vma=False)
    init_block = jax.vmap(init_one, in_axes=(None, 0, 0))
    init_members = jax.jit(shard_map(init_block, in_specs=(replicated, members, members), out_specs=members))
    report_specs = ChunkReport(
        metrics=members, has_data=members, health=members, unhealthy_members=replicated
    )
    chunk = jax.jit(
        shard_map(chunk_block, in_specs=(members, replicated), out_specs=(members, report_specs)),
        donate_argnums=0,
    )
    evaluate_block = jax.vmap(evaluate_seed, axis_name=MEMBERS_AXIS)
    evaluate = jax.jit(shard_map(evaluate_block, in_specs=members, out_specs=members))
    loss_names = tuple(f"train/{k}" for k in _update_metric_order(metric_shapes))
    return Trainer(
        cfg, env, params, eval_params, agent, mesh, init_members, chunk, evaluate, loss_names, init_block
    )
