"""The compiled part of a run: the run state, one chunk of ``log_interval`` transitions per member as
one ``lax.scan`` (vmapped over members), its per-member report and health checks, and evaluation.

Per seed (docs/algorithms.md §5, mapped to synchronous vector envs as §5.8 recommends):

* ``num_envs`` = E envs step in lock-step as one vector env (the scenario kind's ``vector_env``,
  :mod:`xrl_jax.train.kinds`), which restarts ended episodes; every vector step collects E
  transitions (on the Intersection, one per vehicle that acted, each owed one update: a member
  alone pays them in the same step, members vmapped together pay together and may owe a few
  thousand for a while, :mod:`xrl_jax.train.kinds.multi_agent`);
* the first ``warmup_steps`` transitions use uniformly random actions and trigger no update;
* afterwards every transition is followed by one gradient step (update-to-data ratio 1): E updates
  per vector step, as a ``lax.scan`` over E sampled batches; discrete agents act uniformly at random
  with probability 5 % (inside ``Agent.act``);
* racing envs start every episode on a fresh track from the seed's own track feed
  (:class:`envs.track_feed.FreshTrackEnvs`, refilled at the start of a chunk when needed), or with
  ``train_tracks`` > 0 on a track drawn from a fixed bank;
* transitions go into the device-resident replay buffer (:mod:`xrl_jax.buffer`); with the paper's
  ``truncation="drop"`` the compact one-copy layout drops truncated transitions, with
  ``"bootstrap"`` the explicit layout keeps them with their true final observation.

A *chunk* is ``log_interval / E`` vector steps (:mod:`xrl_jax.train.step`) inside one jitted
``lax.scan``; the chunk is
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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from envs.registry import user_factory
from xrl_jax.agents import Agent, HyperParams
from xrl_jax.config import TrainConfig
from xrl_jax.sets import MEMBERS_AXIS
from xrl_jax.train.episodes import window_means
from xrl_jax.train.families import algorithm_family
from xrl_jax.train.kinds import scenario_kind
from xrl_jax.train.step import MemberParts, RunState, init_member, member_parts, tree_all_finite


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
    first_nonfinite_env_step: jax.Array  # transition step of the env's first non-finite output; -1: none
    nonfinite_env_outputs: jax.Array  # which at that step: 1 the reward, 2 the observations, 3 both


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
    """The compiled pieces of one configuration (build with :func:`make_trainer`), over a device mesh.

    * ``init(base_seed, seed_indices, hparams=None) -> RunState`` with a leading member axis: member
      ``j`` starts from ``fold_in(PRNGKey(base_seed), seed_indices[j])`` with hyper-parameters
      ``hparams`` (a :class:`HyperParams` of per-member values; default: the config's), so a member's
      stream depends only on its seed and its values, not on its group or the member count. The same
      seed at two sweep points starts from the same weights and tracks (common random numbers: the
      points differ by their values alone). The member count must be a multiple of the mesh size;
    * ``chunk(state, start_vector_step) -> (state, ChunkReport)``: ``log_interval`` transitions per
      member, the state donated; the report's values are per-member scalars;
    * ``evaluate(state) -> (eval_keys, per_episode)``: the scenario kind's evaluation protocol (§6.1's
      fixed tracks on the racing scenarios).

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
    venv: Any = None  # the vector env the chunk steps (the scenario kind's vector_env)

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
    """:func:`make_trainer` memoised on everything that changes the compiled code (not the seeds, not
    the swept values) and on the devices: runs of the same configuration in one process share
    their compilations."""
    devices = mesh_devices(cfg.num_devices) if devices is None else list(devices)
    # Settings that only the host loop reads; the step count matters only for a partial last chunk,
    # or where the kind's steps read it (the Intersection pays its owed updates at the run's end).
    keeps_length = cfg.total_steps % cfg.log_interval or scenario_kind(cfg).steps_read_run_length
    key = cfg.without_host_settings().replace(
        seed=0,
        num_seeds=1,
        sweep=(),
        eval_interval=cfg.log_interval,
        checkpoint_interval=cfg.log_interval,
        total_steps=cfg.total_steps if keeps_length else cfg.log_interval,
    )
    # A user's env registered again under the same name is another env: its factory is in the key.
    cache_key = (key, cfg.scenario, user_factory(cfg.env), tuple(d.id for d in devices))
    if cache_key not in _TRAINER_CACHE:
        if len(_TRAINER_CACHE) >= 4:
            _TRAINER_CACHE.pop(next(iter(_TRAINER_CACHE)))
        _TRAINER_CACHE[cache_key] = make_trainer(key, devices=devices)
    return _TRAINER_CACHE[cache_key]


def member_hparams(cfg: TrainConfig, agent: Agent, members: list[int]) -> HyperParams:
    """Each member's traced hyper-parameters (its sweep point's values), stacked on a leading axis."""
    family = algorithm_family(cfg)
    per_point = [family.hparams(cfg.point_agent(p), agent) for p in range(cfg.num_points)]
    rows = [per_point[cfg.member_point_seed(m)[0]] for m in members]
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *rows)


def scan_chunk(parts: MemberParts, state: RunState, start_vector_step):
    """``chunk_vector_steps`` vector steps of one member as one ``lax.scan`` of its family's chunk
    steps (a vector step, or a rollout and its updates); with a partial last chunk, the steps past
    the end of the run are skipped (a real ``lax.cond``). Outputs per vector step."""
    cfg = parts.cfg
    step, stride = parts.family.chunk_step(parts)
    count = cfg.chunk_vector_steps // stride

    def body(state, i):
        return step(state, start_vector_step + i * stride)

    if cfg.total_steps % cfg.log_interval:  # the last chunk is partial: gate its tail

        def body(state, i):
            t = start_vector_step + i * stride
            return jax.lax.cond(t < cfg.total_vector_steps, step, skip_step, state, t)

        def skip_step(state, t):
            shapes = jax.eval_shape(step, state, t)[1]
            return state, jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

    state, outs = jax.lax.scan(body, state, jnp.arange(count, dtype=jnp.int32))
    return state, jax.tree.map(lambda x: x.reshape((count * stride, *x.shape[2:])), outs)


def _first_step(flags, start_vector_step, num_envs: int):
    """The transition step at the end of the first vector step whose flag is set (-1: none), and its index."""
    first = jnp.argmax(flags)
    step = jnp.where(jnp.any(flags), (start_vector_step + first + 1) * num_envs, -1).astype(jnp.int32)
    return step, first


def chunk_report(parts: MemberParts, state: RunState, outs, start_vector_step) -> ChunkReport:
    """One member's metrics of a chunk (``outs``: its vector steps' outputs) and health checks."""
    cfg = parts.cfg
    updates = jnp.sum(outs["updates"])
    metrics, has_data = {}, {}

    def average(name, total, count):
        metrics[name] = total / jnp.maximum(count, 1)
        has_data[name] = count > 0

    for k, v in outs["metrics"].items():
        average(f"train/{k}", jnp.sum(v), updates)
    metrics["train/updates"] = state.agent.step
    parts.family.chunk_metrics(state, metrics, has_data)
    average("rollout/avg_step_reward", jnp.sum(outs["reward_sum"]), jnp.sum(outs["reward_count"]))
    rollout, window_filled = window_means(state.window, parts.kind.rollout_velocity)
    metrics.update(rollout)
    has_data.update({name: window_filled for name in rollout if name != "rollout/episodes"})
    parts.kind.chunk_metrics(outs, metrics, average)
    # e.g. on fresh tracks: distinct tracks driven so far, and resets that found the feed empty
    metrics.update({f"rollout/{k}": v for k, v in parts.venv.counters(state.venv_state).items()})
    # The first vector step whose update produced a non-finite loss (and which one), whether the
    # agent's parameters and optimiser states are still finite, and the first step at which the env
    # returned a non-finite reward or observation: the host stops on any.
    bad = jnp.stack([~jnp.isfinite(outs["metrics"][k]) for k in _update_metric_order(outs["metrics"])], 1)
    bad_step = jnp.any(bad, axis=1)
    loss_step, first = _first_step(bad_step, start_vector_step, cfg.num_envs)
    env_step, env_first = _first_step(outs["env_nonfinite"] > 0, start_vector_step, cfg.num_envs)
    health = ChunkHealth(
        first_nonfinite_step=loss_step,
        first_nonfinite_loss=jnp.where(jnp.any(bad_step), jnp.argmax(bad[first]), -1).astype(jnp.int32),
        agent_finite=tree_all_finite(state.agent),
        first_nonfinite_env_step=env_step,
        nonfinite_env_outputs=outs["env_nonfinite"][env_first],
    )
    return ChunkReport(metrics=metrics, has_data=has_data, health=health)


def chunk_member(parts: MemberParts, state: RunState, start_vector_step):
    state, outs = scan_chunk(parts, state, start_vector_step)
    return state, chunk_report(parts, state, outs, start_vector_step)


def any_device(flag) -> jax.Array:
    """Whether ``flag`` holds on any device of the mesh: the same answer on every device."""
    return jax.lax.psum(flag.astype(jnp.int32), MEMBER_AXIS) > 0


def chunk_block(parts: MemberParts, state: RunState, start_vector_step):
    """One device's block of members: the vector env's upkeep (on fresh tracks, refilling the feeds
    once some member, on any device, can take half a feed), then every member's chunk."""
    state = state.with_venv_state(parts.venv.refill(state.venv_state, any_device))
    # Named, so that the members of a block share their packed-or-dense branches (xrl_jax.sets).
    chunk_members = jax.vmap(
        lambda state, start: chunk_member(parts, state, start), in_axes=(0, None), axis_name=MEMBERS_AXIS
    )
    state, report = chunk_members(state, start_vector_step)
    health = report.health
    bad = (health.first_nonfinite_step >= 0) | ~health.agent_finite | (health.first_nonfinite_env_step >= 0)
    unhealthy = jnp.sum(bad, dtype=jnp.int32)
    return state, report.replace(unhealthy_members=jax.lax.psum(unhealthy, MEMBER_AXIS))


def evaluate_block(parts: MemberParts, env, eval_params):
    """One device's block of members through their scenario kind's evaluation protocol (each on a
    fresh evaluation key): §6.1's fixed tracks, the Intersection's fixed episodes, or a user's env's
    fixed resets."""
    evaluate_one = parts.kind.make_evaluate(parts.cfg, env, eval_params, parts.agent)

    def evaluate_member(state: RunState):
        key, sub = jax.random.split(state.eval_key)
        return key, evaluate_one(sub, state.agent)

    return jax.vmap(evaluate_member, axis_name=MEMBERS_AXIS)


def make_trainer(
    cfg: TrainConfig, env_and_params: tuple | None = None, devices: list | None = None
) -> Trainer:
    """The :class:`Trainer` of ``cfg``: the agent, the vector env and the jitted init / chunk / evaluate
    functions, as the run's scenario kind builds and steps them, spread over ``devices`` (default: the
    first device only)."""
    kind = scenario_kind(cfg)
    env, params, eval_params = env_and_params if env_and_params is not None else kind.make_envs(cfg)
    parts = member_parts(cfg, kind, algorithm_family(cfg), env, params)
    mesh = Mesh(np.array(devices if devices is not None else jax.devices()[:1]), (MEMBER_AXIS,))
    members, replicated = P(MEMBER_AXIS), P()
    # check_vma=False: the env and agent code is written for one member and mixes unbatched loop
    # counters with per-member values; the type check would need casts throughout it, and the only
    # cross-device values are the two psums of chunk_block.
    shard_map = functools.partial(jax.shard_map, mesh=mesh, check_vma=False)
    init_block = jax.vmap(functools.partial(init_member, parts), in_axes=(None, 0, 0))
    init_members = jax.jit(shard_map(init_block, in_specs=(replicated, members, members), out_specs=members))
    report_specs = ChunkReport(
        metrics=members, has_data=members, health=members, unhealthy_members=replicated
    )
    chunk = jax.jit(
        shard_map(
            functools.partial(chunk_block, parts),
            in_specs=(members, replicated),
            out_specs=(members, report_specs),
        ),
        donate_argnums=0,
    )
    evaluate = jax.jit(
        shard_map(evaluate_block(parts, env, eval_params), in_specs=members, out_specs=members)
    )
    loss_names = tuple(f"train/{k}" for k in _update_metric_order(parts.metric_shapes))
    return Trainer(
        cfg, env, params, eval_params, parts.agent, mesh, init_members, chunk, evaluate, loss_names,
        unsharded_init=init_block, venv=parts.venv,
    )  # fmt: skip
