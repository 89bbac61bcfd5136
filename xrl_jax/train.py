"""End-to-end vectorised trainer: the whole SAC loop in one compiled ``lax.scan`` chunk, vmapped over seeds.

Per seed (docs/algorithms.md §5, mapped to synchronous vector envs as §5.8 recommends):

* ``num_envs`` = E auto-resetting envs step in lock-step; every vector step collects E transitions;
* the first ``warmup_steps`` transitions use uniformly random actions and trigger no update;
* afterwards every transition is followed by one gradient step (update-to-data ratio 1): E updates
  per vector step, as a ``lax.scan`` over E sampled batches; discrete agents act uniformly at random
  with probability 5 % (inside ``Agent.act``);
* transitions go into the device-resident replay buffer (:mod:`xrl_jax.buffer`); with the paper's
  ``truncation="drop"`` the compact one-copy layout drops truncated transitions, with
  ``"bootstrap"`` the explicit layout keeps them with their true final observation.

A *chunk* is ``log_interval / E`` vector steps inside one jitted ``lax.scan``; the chunk is
``vmap``-ped over seeds and compiled once per configuration, with the run state donated. The
global step counter enters unbatched, so warm-up and end-of-run gating are real ``lax.cond``s and
cost nothing under ``vmap``. A host loop (:func:`train`) between chunks writes JSON-lines metrics,
evaluates on fixed tracks (:mod:`xrl_jax.evaluate`), checkpoints (:mod:`xrl_jax.checkpoint`) and
draws a progress bar. Seeds that do not fit the device memory run in groups (:func:`plan_memory`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from xrl_jax import config as agent_config_mod
from xrl_jax.agents import Agent, AgentState, make_agent
from xrl_jax.buffer import ReplayBuffer, buffer_add, buffer_add_packed, buffer_init, buffer_sample
from xrl_jax.checkpoint import Checkpointer, CorruptCheckpointError
from xrl_jax.config import ALGOS, AgentConfig
from xrl_jax.interrupts import RunInterrupted, StopController
from xrl_jax.resources import (
    backend_summary,
    disk_free_bytes,
    format_bytes,
    format_duration,
    host_memory_available,
)
from xrl_jax.run_folder import (
    RunLock,
    append_lines,
    check_history,
    encode_metric,
    is_disk_full,
    remove_leftovers,
    run_paths,
    truncate_lines,
    write_atomic,
)

ENVS = ("country_road", "tracking", "intersection")
MULTI_AGENT_ENVS = ("intersection",)
PRESETS = ("paper", "quick", "smoke")
EPISODE_WINDOW = 100  # rollout metrics average over the last 100 finished episodes (§6.2)
# Settings that only the host loop reads: they change neither the compiled code nor the results.
HOST_ONLY_FIELDS = ("max_group_size", "memory_budget_gb", "checkpoint_minutes")
EARLY_TERMINATION_REWARD = -0.5  # ETR: terminated with a last reward below this (§6.1)


class ConfigError(ValueError):
    """An invalid training configuration; the message is one line naming the allowed values."""


class MemoryPlanError(RuntimeError):
    """Even one seed does not fit the memory budget."""


# ------------------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything about a run except the agent's hyper-parameters (``agent``); validated on creation.

    Step counts are environment transitions *per seed*. ``log_interval`` is also the length of one
    compiled chunk; evaluation and checkpoint intervals are multiples of it so that every host-side
    event happens at a chunk boundary (which is what makes resuming exact).
    """

    env: str = "tracking"
    algo: str = "xsac"
    preset: str = "paper"
    num_seeds: int = 1
    seed: int = 0  # seed i of the run derives its keys from fold_in(PRNGKey(seed), i)
    total_steps: int = 1_000_000
    num_envs: int = 4
    warmup_steps: int = 256
    batch_size: int = 256
    buffer_size: int = 1_000_000
    log_interval: int = 2_000
    eval_interval: int = 100_000
    eval_episodes: int = 100
    checkpoint_interval: int = 100_000
    train_tracks: int = 256  # size of the training track bank (envs draw from it at every reset)
    track_seed: int = 0  # training bank
    eval_track_seed: int = 1  # the fixed evaluation tracks, disjoint from the training bank
    reinit_steps: int = 0  # re-initialise the whole agent (not the buffer) every this many steps; 0: never
    max_group_size: int = 0  # 0: as many seeds per group as the memory budget allows
    memory_budget_gb: float = 0.0  # 0: 90 % of the device's memory (host RAM on CPU, within any cgroup limit)
    checkpoint_minutes: float = 30.0  # also checkpoint by wall time (costing at most 2 % of it); 0: off
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)

    def __post_init__(self) -> None:
        _validate_train(self)

    # ---- derived values -----------------------------------------------------------------------
    @property
    def env_name(self) -> str:
        """The registry name: discrete agents use the 12-way action variant."""
        return self.env + ("_discrete" if self.agent.is_discrete else "")

    @property
    def multi_agent(self) -> bool:
        return self.env in MULTI_AGENT_ENVS

    @property
    def buffer_layout(self) -> str:
        """Multi-agent transitions are packed (varying count per step), so they store next_obs."""
        return "compact" if self.agent.truncation == "drop" and not self.multi_agent else "explicit"

    @property
    def chunk_vector_steps(self) -> int:
        return self.log_interval // self.num_envs

    @property
    def total_vector_steps(self) -> int:
        return self.total_steps // self.num_envs

    @property
    def num_chunks(self) -> int:
        return -(-self.total_steps // self.log_interval)

    def chunk_end_step(self, chunk: int) -> int:
        """Transitions per seed collected after chunk index ``chunk`` (0-based)."""
        return min((chunk + 1) * self.log_interval, self.total_steps)

    def replace(self, **changes: Any) -> TrainConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the train fields and the agent config, both fully resolved."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "agent"}
        out["agent"] = dataclasses.asdict(self.agent)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        data = dict(data)
        agent = AgentConfig(**data.pop("agent"))
        unknown = sorted(set(data) - set(train_field_names()))
        if unknown:
            raise ConfigError(f"unknown train config field(s) {unknown}")
        return cls(agent=agent, **data)


def train_field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(TrainConfig) if f.name != "agent"]


def _positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{name} must be a positive integer, got {value!r}")


def _validate_train(cfg: TrainConfig) -> None:
    if cfg.env not in ENVS:
        raise ConfigError(f"unknown env {cfg.env!r}; allowed: {', '.join(ENVS)}")
    if cfg.algo not in ALGOS:
        raise ConfigError(f"unknown algo {cfg.algo!r}; allowed: {', '.join(ALGOS)}")
    if cfg.preset not in PRESETS:
        raise ConfigError(f"unknown preset {cfg.preset!r}; allowed: {', '.join(PRESETS)}")
    if not isinstance(cfg.agent, AgentConfig):
        raise ConfigError(f"agent must be an AgentConfig, got {type(cfg.agent).__name__}")
    if cfg.agent.algo != cfg.algo:
        raise ConfigError(f"agent.algo ({cfg.agent.algo}) differs from algo ({cfg.algo})")
    for name in (
        "num_seeds", "total_steps", "num_envs", "batch_size", "buffer_size", "log_interval",
        "eval_interval", "eval_episodes", "checkpoint_interval", "train_tracks", "warmup_steps",
    ):  # fmt: skip
        _positive_int(name, getattr(cfg, name))
    for name in ("seed", "track_seed", "eval_track_seed", "max_group_size", "reinit_steps"):
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"{name} must be a non-negative integer, got {value!r}")
    if isinstance(cfg.memory_budget_gb, bool) or not isinstance(cfg.memory_budget_gb, (int, float)):
        raise ConfigError(f"memory_budget_gb must be a number, got {cfg.memory_budget_gb!r}")
    if not (math.isfinite(cfg.memory_budget_gb) and cfg.memory_budget_gb >= 0):
        raise ConfigError(f"memory_budget_gb must be >= 0 (0 = automatic), got {cfg.memory_budget_gb}")
    minutes = cfg.checkpoint_minutes
    if isinstance(minutes, bool) or not isinstance(minutes, (int, float)) or not (
        math.isfinite(minutes) and minutes >= 0
    ):
        raise ConfigError(f"checkpoint_minutes must be a number >= 0 (0 = by steps only), got {minutes!r}")
    e = cfg.num_envs
    if cfg.total_steps % e:
        raise ConfigError(f"steps ({cfg.total_steps}) must be a multiple of num_envs ({e})")
    if cfg.log_interval % e:
        raise ConfigError(f"log_interval ({cfg.log_interval}) must be a multiple of num_envs ({e})")
    for name in ("eval_interval", "checkpoint_interval"):
        if getattr(cfg, name) % cfg.log_interval:
            raise ConfigError(
                f"{name} ({getattr(cfg, name)}) must be a multiple of log_interval ({cfg.log_interval})"
            )
    if cfg.warmup_steps < e:
        raise ConfigError(f"warmup_steps ({cfg.warmup_steps}) must be at least num_envs ({e})")
    if cfg.buffer_size < cfg.batch_size:
        raise ConfigError(f"buffer_size ({cfg.buffer_size}) must be at least batch_size ({cfg.batch_size})")
    if cfg.multi_agent:
        from envs.intersection import MAX_AGENTS

        if cfg.buffer_size < MAX_AGENTS * e:
            raise ConfigError(
                f"buffer_size ({cfg.buffer_size}) must hold one step of all agents ({MAX_AGENTS * e})"
            )


def _preset_train_fields(preset: str, env: str, algo: str) -> dict[str, Any]:
    """Train-loop settings of each preset (the agent part comes from :mod:`xrl_jax.config`)."""
    if env == "intersection":
        return _intersection_train_fields(preset)
    if preset == "paper":  # §5.7: 1e6 steps, buffer 1e6, eval every 1e5 on 100 episodes
        return {}
    if preset == "quick":  # two Tracking XDSAC seeds: 14 min on a 2-core CPU (measured)
        return {
            "total_steps": 80_000,  # buffer_size follows total_steps (resolve_config): every transition kept
            "batch_size": 128,
            "log_interval": 1_000,
            "eval_interval": 5_000,
            "checkpoint_interval": 10_000,
            "warmup_steps": 1_000,
            "train_tracks": 64,
        }
    return {  # smoke: a few hundred steps, tiny everything, for tests
        "total_steps": 192,
        "num_envs": 4,
        "warmup_steps": 64,
        "batch_size": 16,
        "buffer_size": 256,
        "log_interval": 64,
        "eval_interval": 192,
        "checkpoint_interval": 64,
        "eval_episodes": 3,
        "train_tracks": 3,
    }


def _intersection_train_fields(preset: str) -> dict[str, Any]:
    """Intersection (docs/carenv-intersection.md §8): steps are multi-agent env steps; every alive
    agent's transition is stored and followed by one update. Paper: the released configs' values."""
    if preset == "paper":  # docs/carenv-intersection.md §8.7 (released configs); 2 envs = its 2 workers
        return {
            "total_steps": 5_000_000,
            "num_envs": 2,
            "warmup_steps": 2_000,
            "batch_size": 512,
            "buffer_size": 15_000_000,
            "log_interval": 2_000,
            "eval_interval": 100_000,
            "eval_episodes": 20,
            "checkpoint_interval": 100_000,
            "reinit_steps": 500_001,
        }
    if preset == "quick":
        return {
            "total_steps": 20_000,
            "num_envs": 2,
            "warmup_steps": 2_000,
            "batch_size": 128,
            "buffer_size": 100_000,
            "log_interval": 1_000,
            "eval_interval": 10_000,
            "eval_episodes": 5,
            "checkpoint_interval": 10_000,
        }
    return {  # smoke
        "total_steps": 128,
        "num_envs": 2,
        "warmup_steps": 64,
        "batch_size": 16,
        "buffer_size": 512,
        "log_interval": 64,
        "eval_interval": 128,
        "eval_episodes": 2,
        "checkpoint_interval": 64,
    }


# The quick preset's optimisation constants for the racing scenarios, tuned for a short budget
# (measured on Tracking XDSAC at 30k steps, 2 seeds: final evaluation return 14.9 against 4.3 with the
# paper's).
# The paper starts at α = 0.1 and moves log α with lr 1e-4, so for ~20k steps the entropy bonus
# (0.1·ln 12 ≈ 0.25 per step) outweighs the reward (≤ ~0.1 per step) and the policy stays nearly
# uniform; over the paper's 10⁶ steps that start-up phase does not matter, over 50k it is everything.
# Actor and critic start at 6e-4 and decay linearly to zero over the run (``lr_decay_updates``, set in
# resolve_config): with a constant 3e-4 the greedy evaluation policy swung by ±15 between the last
# evaluations (4 Tracking XDSAC seeds, final IQM 24.1); with the decay the last evaluations change
# less and the final IQM was 31.8 on the same seeds (60k steps); with 80k steps it is 38.3 over 14
# runs (README, Results).
QUICK_RACING_OPTIMISATION = {
    "init_alpha": 0.005,
    "alpha_lr": 1e-3,
    "actor_lr": 6e-4,
    "critic_lr": 6e-4,
    "gamma": 0.98,  # 0.95 learns to drive fast but crashes; 0.99 learns to stand still
}


def _preset_agent(preset: str, env: str, algo: str) -> AgentConfig:
    if preset == "quick":  # width-64 networks; short-budget optimisation constants on the racing envs
        quick = agent_config_mod.preset("paper", env, algo).replace(
            actor_width=64, critic_width=64, fe_width=32, actor_depth=2, critic_depth=2
        )
        if env != "intersection":  # Intersection keeps its fixed α = 0.015 (no start-up phase)
            quick = quick.replace(**QUICK_RACING_OPTIMISATION)
        return quick
    return agent_config_mod.preset(preset, env, algo)


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """``["key=value", ...]`` -> dict; a malformed item raises :class:`ConfigError`."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key or not value.strip():
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        out[key] = value.strip()
    return out


def _parse_train_value(name: str, text: str) -> Any:
    """Parse ``--set`` text with the type of the field's default (TrainConfig has int, float and
    str fields only)."""
    field = {f.name: f for f in dataclasses.fields(TrainConfig)}[name]
    kind = type(field.default) if field.default is not dataclasses.MISSING else str
    try:
        if kind is int:
            value = float(text)
            if value != int(value):
                raise ValueError(text)
            return int(value)
        if kind is float:
            return float(text)
        return text
    except ValueError:
        raise ConfigError(f"cannot parse {text!r} for {name} (expected {kind.__name__})") from None


def resolve_config(
    env: str = "tracking",
    algo: str = "xsac",
    preset: str = "paper",
    num_seeds: int = 1,
    total_steps: int | None = None,
    overrides: Mapping[str, str] | None = None,
) -> TrainConfig:
    """The fully resolved config: preset, then the explicit arguments, then ``overrides``.

    ``overrides`` keys are :class:`TrainConfig` fields or :class:`AgentConfig` fields (an
    ``agent.`` prefix is accepted); values are text, parsed with the field's type.
    """
    if env not in ENVS:
        raise ConfigError(f"unknown env {env!r}; allowed: {', '.join(ENVS)}")
    if algo not in ALGOS:
        raise ConfigError(f"unknown algo {algo!r}; allowed: {', '.join(ALGOS)}")
    if preset not in PRESETS:
        raise ConfigError(f"unknown preset {preset!r}; allowed: {', '.join(PRESETS)}")
    fields = _preset_train_fields(preset, env, algo)
    fields.update(env=env, algo=algo, preset=preset, num_seeds=num_seeds)
    if total_steps is not None:
        fields["total_steps"] = total_steps
    agent_changes: dict[str, str] = {}
    train_changes: set[str] = set()
    train_names = set(train_field_names())
    agent_names = set(agent_config_mod.field_names())
    for key, value in (overrides or {}).items():
        name = key.removeprefix("agent.")
        if key.startswith("agent.") or (name not in train_names and name in agent_names):
            if name not in agent_names:
                raise ConfigError(
                    f"unknown agent setting {name!r}; allowed: {', '.join(sorted(agent_names))}"
                )
            agent_changes[name] = value
        elif name in ("env", "algo", "preset", "agent"):
            raise ConfigError(f"{name!r} cannot be changed with --set; use --{name}")
        elif name in train_names:
            fields[name] = _parse_train_value(name, value)
            train_changes.add(name)
        else:
            allowed = ", ".join(sorted((train_names - {"env", "algo", "preset"}) | agent_names))
            raise ConfigError(f"unknown setting {key!r}; allowed: {allowed}")
    if "algo" in agent_changes:
        raise ConfigError("'algo' cannot be changed with --set; use --algo")
    try:
        agent = agent_config_mod.apply_overrides(_preset_agent(preset, env, algo), agent_changes)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if preset == "quick" and env != "intersection":  # settings that follow the run's length
        if "buffer_size" not in train_changes:
            # Keep every transition, as the paper's protocol does (buffer = steps = 10⁶). On 4 Tracking
            # XDSAC seeds the evaluation IQM at 50k steps was 27.0 with a FIFO of the latest 30k
            # transitions and 36.0 with all of them (README, Results).
            fields["buffer_size"] = max(fields["total_steps"], fields["batch_size"])
        if "lr_decay_updates" not in agent_changes:
            # The learning rates reach zero at the last update (one update per transition after warm-up).
            updates = fields["total_steps"] - fields.get("warmup_steps", TrainConfig.warmup_steps)
            agent = agent.replace(lr_decay_updates=max(updates, 1))
    try:
        return TrainConfig(agent=agent, **fields)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err)) from None


# ------------------------------------------------------------------------------------------------
# Environments and tracks
# ------------------------------------------------------------------------------------------------


def cache_dir() -> Path:
    """Where generated track banks (and JAX's compilation cache, see run.py) are kept."""
    return Path(os.environ.get("XRL_JAX_CACHE_DIR", Path.home() / ".cache" / "xrl-jax"))


def _generator_fingerprint() -> str:
    import envs.track

    return hashlib.sha256(Path(envs.track.__file__).read_bytes()).hexdigest()[:12]


def track_cache_path(seed: int, size: int) -> Path:
    """The cache file of the bank ``(seed, size)`` for this generator version, backend and dtype."""
    dtype = jnp.result_type(float).name
    name = f"tracks-{_generator_fingerprint()}-{jax.default_backend()}-{dtype}-{seed}-{size}.npz"
    return cache_dir() / "tracks" / name


def cached_track_bank(seed: int, size: int):
    """``size`` generated tracks from ``seed``, cached on disk (generation compiles for ~30 s on CPU).

    The file name carries a hash of the generator's source and the backend, so a changed generator
    never serves stale tracks. Writes are atomic (temporary file + rename).
    """
    from envs.track import Track, make_track_bank

    path = track_cache_path(seed, size)
    fields = [f.name for f in dataclasses.fields(Track)]
    if path.exists():
        try:
            with np.load(path) as data:
                return Track(**{k: jnp.asarray(data[k]) for k in fields})
        except (OSError, KeyError, ValueError):
            pass  # unreadable cache entry: regenerate below
    bank = jax.device_get(make_track_bank(jax.random.PRNGKey(seed), size))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
        np.savez(tmp, **{k: np.asarray(getattr(bank, k)) for k in fields})
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache only costs time
    return jax.tree.map(jnp.asarray, bank)


def make_envs(cfg: TrainConfig):
    """``(env, train_params, eval_params)``: the training bank and the fixed evaluation tracks
    (Intersection: curriculum for training, 8 vehicles for evaluation, docs/carenv-intersection.md §8.8)."""
    import envs

    if cfg.multi_agent:
        env, params = envs.make(cfg.env_name)
        return env, params, params.replace(max_vehicles=8)
    from envs.racing import with_bank

    train_bank = cached_track_bank(cfg.track_seed, cfg.train_tracks)
    eval_bank = cached_track_bank(cfg.eval_track_seed, cfg.eval_episodes)
    first = jax.tree.map(lambda leaf: leaf[0], train_bank)
    env, params = envs.make(cfg.env_name, track=first)  # a user track: no generation here
    attach = jax.jit(with_bank)  # the per-track tables, computed in one compiled call
    return env, attach(params, train_bank), attach(params, eval_bank)


# ------------------------------------------------------------------------------------------------
# Run state and the compiled chunk
# ------------------------------------------------------------------------------------------------


@struct.dataclass
class EpisodeWindow:
    """The last ``EPISODE_WINDOW`` finished episodes (ring), for the rollout metrics of §6.2."""

    returns: jax.Array
    lengths: jax.Array
    early: jax.Array
    track_velocity: jax.Array
    count: jax.Array  # episodes finished so far


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


def _window_init(dtype) -> EpisodeWindow:
    zeros = jnp.zeros((EPISODE_WINDOW,), dtype)
    return EpisodeWindow(zeros, zeros, jnp.zeros((EPISODE_WINDOW,), bool), zeros, jnp.zeros((), jnp.int32))


def _window_add(window: EpisodeWindow, done, returns, lengths, early, velocity) -> EpisodeWindow:
    """Append the finished episodes among E envs (masked scatter; unfinished ones are dropped)."""
    order = jnp.cumsum(done.astype(jnp.int32)) - 1
    slot = jnp.where(done, (window.count + order) % EPISODE_WINDOW, EPISODE_WINDOW)

    def put(store, value):
        return store.at[slot].set(value.astype(store.dtype), mode="drop")

    return EpisodeWindow(
        returns=put(window.returns, returns),
        lengths=put(window.lengths, lengths),
        early=put(window.early, early),
        track_velocity=put(window.track_velocity, velocity),
        count=window.count + jnp.sum(done, dtype=jnp.int32),
    )


def _window_means(window: EpisodeWindow, multi_agent: bool = False) -> tuple[dict[str, jax.Array], jax.Array]:
    """Averages over the window, and whether it holds any episode yet (the averages are 0 until
    then); multi-agent windows hold per-agent episodes (termination or the 60 s restart) and the
    env's mean velocity instead of the track velocity."""
    filled = jnp.minimum(window.count, EPISODE_WINDOW)
    mask = jnp.arange(EPISODE_WINDOW) < filled
    denom = jnp.maximum(filled, 1)

    def mean(x):
        return jnp.sum(jnp.where(mask, x.astype(jnp.float32), 0.0)) / denom

    means = {
        "rollout/avg_episode_return": mean(window.returns),
        "rollout/avg_episode_length": mean(window.lengths),
        "rollout/early_termination_rate": mean(window.early),
        ("rollout/avg_mean_velocity" if multi_agent else "rollout/avg_track_velocity"): mean(
            window.track_velocity
        ),
        "rollout/episodes": window.count,
    }
    return means, filled > 0


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


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """The compiled pieces of one configuration (build with :func:`make_train`).

    * ``init(base_seed, seed_indices) -> RunState`` with a leading seed axis (seed ``i`` of a run
      uses ``fold_in(PRNGKey(base_seed), i)``, so a seed's stream does not depend on its group);
    * ``chunk(state, start_vector_step) -> (state, ChunkReport)``: ``log_interval`` transitions per
      seed, the state donated; the report's values are per-seed scalars (leading seed axis);
    * ``evaluate(state) -> (eval_keys, per_episode)``: the §6.1 protocol on the fixed tracks.

    ``loss_names`` are the update's metrics (losses first) in the order that
    ``ChunkHealth.first_nonfinite_loss`` counts.
    """

    config: TrainConfig
    env: Any
    env_params: Any
    eval_params: Any
    agent: Agent
    init: Any
    chunk: Any
    evaluate: Any
    loss_names: tuple[str, ...] = ()

    def abstract_state(self, num_seeds: int) -> RunState:
        return jax.eval_shape(self.init, jnp.int32(0), jnp.arange(num_seeds, dtype=jnp.int32))


_TRAINER_CACHE: dict[TrainConfig, Trainer] = {}


def get_trainer(cfg: TrainConfig) -> Trainer:
    """:func:`make_train` memoised on everything that changes the compiled code (not the seeds):
    runs of the same configuration in one process share their compilations."""
    # Settings that only the host loop reads; the step count matters only for a partial last chunk.
    key = cfg.replace(
        seed=0,
        num_seeds=1,
        **{name: TrainConfig.__dataclass_fields__[name].default for name in HOST_ONLY_FIELDS},
        eval_interval=cfg.log_interval,
        checkpoint_interval=cfg.log_interval,
        total_steps=cfg.total_steps if cfg.total_steps % cfg.log_interval else cfg.log_interval,
    )
    if key not in _TRAINER_CACHE:
        if len(_TRAINER_CACHE) >= 4:
            _TRAINER_CACHE.pop(next(iter(_TRAINER_CACHE)))
        _TRAINER_CACHE[key] = make_train(key)
    return _TRAINER_CACHE[key]


def make_train(cfg: TrainConfig, env_and_params: tuple | None = None) -> Trainer:
    """Build the agent, the vector env and the jitted init / chunk / evaluate functions for ``cfg``."""
    from envs.core import vmap_env
    from xrl_jax import evaluate as evaluate_mod

    env, params, eval_params = env_and_params if env_and_params is not None else make_envs(cfg)
    num_envs, batch, warmup = cfg.num_envs, cfg.batch_size, cfg.warmup_steps
    multi = cfg.multi_agent
    venv = vmap_env(env, num_envs, auto_reset=not multi)  # the multi-agent env restarts itself
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

    def init_one(base_seed, index):
        key = jax.random.fold_in(jax.random.PRNGKey(base_seed), index)
        agent_key, env_key, run_key, eval_key = jax.random.split(key, 4)
        obs, env_state = venv.reset(env_key, params)
        return RunState(
            agent=agent.init(agent_key, obs_example),
            buffer=new_buffer(cfg.buffer_size),
            env_state=env_state,
            obs=obs,
            key=run_key,
            eval_key=eval_key,
            episode_return=jnp.zeros(actors, float_dtype),
            episode_length=jnp.zeros(actors, jnp.int32),
            window=_window_init(float_dtype),
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
        still warming up, and the env step's outputs."""
        key, act_key, random_key, env_key, update_key, reinit_key = jax.random.split(state.key, 6)
        first_transition = t * num_envs
        agent_state = maybe_reinitialise(state.agent, first_transition, reinit_key)
        policy_action = agent.act(act_key, agent_state, state.obs, "train")
        random_action = agent.random_action(random_key, actors)
        warm_env = first_transition + jnp.arange(num_envs) < warmup
        warm = warm_env.reshape(warm_env.shape + (1,) * (policy_action.ndim - 1))
        action = jnp.where(warm, random_action, policy_action)
        step = venv.step(env_key, state.env_state, action, params)
        return key, update_key, agent_state, action, warm_env, step

    def episode_bookkeeping(state, reward, counted, done, terminated, velocity):
        """Per-actor running episode return and length (actors: envs, or env × vehicle slot);
        finished episodes enter the rolling window and restart from zero."""
        episode_return = state.episode_return + reward
        episode_length = state.episode_length + counted.astype(jnp.int32)
        early = terminated & (reward < EARLY_TERMINATION_REWARD)
        velocity = jnp.broadcast_to(velocity, done.shape)
        window = _window_add(
            state.window, *(x.reshape(-1) for x in (done, episode_return, episode_length, early, velocity))
        )
        return {
            "episode_return": jnp.where(done, 0.0, episode_return).astype(float_dtype),
            "episode_length": jnp.where(done, 0, episode_length),
            "window": window,
        }

    def vector_step(state: RunState, t):
        key, update_key, agent_state, action, _, step = act_and_step(state, t)
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
            agent=agent_state,
            buffer=buffer,
            env_state=env_state,
            obs=next_obs,
            key=key,
            **episode_bookkeeping(
                state, reward, jnp.ones_like(done), done, terminated, info["avg_track_velocity"]
            ),
        )
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
        key, update_key, agent_state, action, warm_env, step = act_and_step(state, t)
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
            agent=agent_state,
            buffer=buffer,
            env_state=env_state,
            obs=next_obs,
            key=key,
            **episode_bookkeeping(
                state, reward, acted, agent_done, terminated, info["mean_velocity"][:, None]
            ),
        )
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
        window_means, window_filled = _window_means(state.window, multi)
        metrics.update(window_means)
        has_data.update({name: window_filled for name in window_means if name != "rollout/episodes"})
        if multi:
            episodes = jnp.sum(outs["episodes_ended"])
            metrics["rollout/env_episodes"] = episodes
            average("rollout/trips_per_episode", jnp.sum(outs["trips"]), episodes)
            average("rollout/early_terminations_per_episode", jnp.sum(outs["early_terminations"]), episodes)
        metrics["buffer/stored_rows"] = state.buffer.filled_rows
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
        evaluate_one = evaluate_mod.make_evaluate_multiagent(env, eval_params, agent, cfg.eval_episodes)
    else:
        evaluate_one = evaluate_mod.make_evaluate(env, eval_params, agent, cfg.eval_episodes)

    def evaluate_seed(state: RunState):
        key, sub = jax.random.split(state.eval_key)
        return key, evaluate_one(sub, state.agent)

    init_jit = jax.jit(jax.vmap(init_one, in_axes=(None, 0)))

    def init(base_seed, seed_indices):
        # Committed to the device, as a state restored from a checkpoint is: jit keys its cache on
        # committedness, so both then share one compiled chunk.
        return jax.device_put(init_jit(base_seed, seed_indices), jax.devices()[0])

    chunk = jax.jit(jax.vmap(chunk_one, in_axes=(0, None)), donate_argnums=0)
    evaluate = jax.jit(jax.vmap(evaluate_seed))
    loss_names = tuple(f"train/{k}" for k in _update_metric_order(metric_shapes))
    return Trainer(cfg, env, params, eval_params, agent, init, chunk, evaluate, loss_names)


# ------------------------------------------------------------------------------------------------
# Memory planning
# ------------------------------------------------------------------------------------------------


def _tree_bytes(tree) -> int:
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape") and hasattr(x, "dtype")]
    return int(sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in leaves))


def device_memory_bytes() -> tuple[int, str]:
    """Usable memory of the default device: the allocator's limit on accelerators; on CPU the
    available RAM, or less where a container's memory limit leaves less."""
    device = jax.devices()[0]
    try:
        stats = device.memory_stats() or {}
    except Exception:
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.device_kind} memory"
    return host_memory_available()


def estimate_seed_bytes(trainer: Trainer) -> dict[str, int]:
    """Device bytes one seed needs: exact sizes of its state (``eval_shape``, nothing allocated)
    plus an estimate of the update's and evaluation's temporary arrays."""
    cfg = trainer.config
    abstract = trainer.abstract_state(1)
    obs = trainer.agent.obs_shape
    objects = obs.num_objects * cfg.agent.components_per_object
    a = cfg.agent
    per_sample = objects * (a.actor_width * a.actor_depth + a.critic_width * a.critic_depth * a.n_critics)
    if a.algo == "xsac":
        per_sample += objects * objects * trainer.agent.action_size  # the B x K x K x A density tensor
    # float32 activations kept for the backward pass, gradients and XLA temporaries: ~4 copies.
    workspace = 4 * 4 * cfg.batch_size * (per_sample + obs.state_dim + obs.object_features * obs.num_objects)
    eval_bytes = 4 * 4 * cfg.eval_episodes * objects * a.actor_width * a.actor_depth
    sizes = {
        "buffer": _tree_bytes(abstract.buffer),
        "agent": _tree_bytes(abstract.agent),
        "env": _tree_bytes((abstract.env_state, abstract.obs)),
        "workspace_estimate": int(workspace + eval_bytes),
    }
    sizes["total"] = sum(sizes.values())
    sizes["bytes_per_transition"] = round(sizes["buffer"] / abstract.buffer.capacity)
    return sizes


def plan_memory(
    trainer: Trainer, cfg: TrainConfig | None = None, budget_bytes: int | None = None
) -> dict[str, Any]:
    """Seed groups of ``cfg`` (default: the trainer's) that fit the budget.

    Raises :class:`MemoryPlanError` if one seed does not fit."""
    cfg = trainer.config if cfg is None else cfg
    sizes = estimate_seed_bytes(trainer)
    if budget_bytes is None:
        if cfg.memory_budget_gb > 0:
            budget_bytes, source = int(cfg.memory_budget_gb * 1e9), "memory_budget_gb"
        else:
            available, source = device_memory_bytes()
            budget_bytes = int(0.9 * available)
    else:
        source = "given"
    shared = _tree_bytes((trainer.env_params, trainer.eval_params))
    fit = (budget_bytes - shared) // max(sizes["total"], 1)
    if fit < 1:
        raise MemoryPlanError(
            f"one seed needs about {format_bytes(sizes['total'])} (buffer {format_bytes(sizes['buffer'])}) "
            f"but the budget ({source}) is {format_bytes(budget_bytes)}; "
            "reduce buffer_size or the network widths with --set"
        )
    group = min(cfg.num_seeds, int(fit))
    if cfg.max_group_size:
        group = min(group, cfg.max_group_size)
    num_groups = -(-cfg.num_seeds // group)
    group = -(-cfg.num_seeds // num_groups)  # balance the groups
    groups = [list(range(g * group, min((g + 1) * group, cfg.num_seeds))) for g in range(num_groups)]
    return {"per_seed_bytes": sizes, "budget_bytes": budget_bytes, "budget_source": source, "groups": groups}


# ------------------------------------------------------------------------------------------------
# Host loop
# ------------------------------------------------------------------------------------------------


class DivergenceError(RuntimeError):
    """A seed produced a non-finite loss or parameter; the message (one line) names the seed, the
    step and the quantity, and what was kept."""


class DiskFullError(RuntimeError):
    """The disk filled up while the run wrote its results; the last committed checkpoint is intact."""


CHECKPOINT_TIME_SHARE = 0.02  # time-based checkpoints never take more than this share of the run
LONG_RUN_S = 86_400.0  # estimates above a day come with a warning and the faster alternatives


def config_fingerprint(cfg: TrainConfig) -> str:
    """A hash of every setting that shapes the run's results (not the host-only settings); stored
    with each checkpoint so that a resume never continues another configuration's state."""
    fields = cfg.to_dict()
    for host_only in HOST_ONLY_FIELDS:
        fields.pop(host_only)
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True, file=sys.stderr
    )


def _metric_lines(step: int, seeds: list[int], report: ChunkReport) -> list[tuple[int, dict]]:
    """One metrics line per seed: ``null`` where an average has no data yet, non-finite values as
    the strings "nan"/"inf"/"-inf" (see :func:`xrl_jax.run_folder.encode_metric`)."""
    lines = []
    for row, seed in enumerate(seeds):
        line = {"step": step, "seed": seed}
        for name, values in report.metrics.items():
            present = report.has_data.get(name)
            line[name] = encode_metric(values[row]) if present is None or present[row] else None
        lines.append((seed, line))
    return lines


def _first_nonfinite_leaf(tree) -> str:
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(path)
    return "(none found)"


def divergence_message(
    report: ChunkReport, seeds: list[int], chunk_end: int, loss_names: tuple[str, ...], agent_of_row
) -> str | None:
    """None when every seed of the chunk is healthy, else one line naming the first seed to go
    non-finite, the step and the quantity (``agent_of_row(row)`` gives that seed's agent state)."""
    health = report.health
    loss_step = np.asarray(health.first_nonfinite_step)
    bad_rows = [r for r in range(len(seeds)) if loss_step[r] >= 0 or not health.agent_finite[r]]
    if not bad_rows:
        return None
    first_step = {r: int(loss_step[r]) if loss_step[r] >= 0 else chunk_end for r in bad_rows}
    row = min(bad_rows, key=lambda r: (first_step[r], r))
    if loss_step[row] >= 0:
        name = loss_names[int(health.first_nonfinite_loss[row])]
        what = f"{name} became non-finite"
    else:
        what = f"the agent's {_first_nonfinite_leaf(agent_of_row(row))} became non-finite"
    others = len(bad_rows) - 1
    also = f" ({others} other seed{'s' if others > 1 else ''} too)" if others else ""
    return f"seed {seeds[row]} diverged at step {first_step[row]}{also}: {what}"


def _expected_rows(cfg: TrainConfig, next_chunk: int) -> tuple[list[int], list[int]]:
    """The metric and evaluation steps a seed's files must hold when ``next_chunk`` chunks are done."""
    ends = [cfg.chunk_end_step(c) for c in range(next_chunk)]
    evals = [s for s in ends if s % cfg.eval_interval == 0 or s == cfg.total_steps]
    return ends, evals


class _RunClock:
    """Wall-time bookkeeping of the host loop: time-based checkpoints and the run's cost estimate."""

    def __init__(self, cfg: TrainConfig, num_groups: int):
        self.cfg = cfg
        self.num_groups = num_groups
        self.last_save = time.monotonic()
        self.save_s: float | None = None  # the last checkpoint's duration
        self.eval_s: float | None = None  # the last evaluation's duration
        self.chunk_s: float | None = None  # a chunk's duration with an update per transition
        self.estimated = False

    def saved(self, seconds: float) -> None:
        self.save_s = seconds
        self.last_save = time.monotonic()

    def checkpoint_due_by_time(self) -> bool:
        minutes = self.cfg.checkpoint_minutes
        if not minutes:
            return False
        interval = max(60.0 * minutes, (self.save_s or 0.0) / CHECKPOINT_TIME_SHARE)
        return time.monotonic() - self.last_save >= interval

    def expected_chunk_s(self) -> float | None:
        """How long the next chunk and a checkpoint after it should take (None until measured)."""
        if self.chunk_s is None:
            return None
        return self.chunk_s + (self.save_s or 0.0)

    def observe_chunk(self, chunk_index: int, seconds: float) -> None:
        """Learn a chunk's cost from the first one in which at least half the transitions update
        (updates dominate; scaled up to a chunk that updates on every transition)."""
        if self.chunk_s is not None:
            return
        cfg = self.cfg
        first = chunk_index * cfg.log_interval
        last = cfg.chunk_end_step(chunk_index)
        updating = max(last - max(first, cfg.warmup_steps), 0)
        if updating * 2 >= last - first:
            self.chunk_s = seconds * (last - first) / updating

    def remaining_s(self, group_index: int, next_chunk: int) -> float | None:
        """Time left for the whole run (chunks, evaluations, step-interval checkpoints)."""
        if self.chunk_s is None:
            return None
        cfg = self.cfg

        def cost(first_chunk: int) -> float:  # chunks first_chunk.. of one group, with their events
            ends = [cfg.chunk_end_step(c) for c in range(first_chunk, cfg.num_chunks)]
            evals = sum(1 for s in ends if s % cfg.eval_interval == 0 or s == cfg.total_steps)
            saves = sum(1 for s in ends if s % cfg.checkpoint_interval == 0 or s == cfg.total_steps)
            return len(ends) * self.chunk_s + evals * (self.eval_s or 0.0) + saves * (self.save_s or 0.0)

        return cost(next_chunk) + (self.num_groups - group_index - 1) * cost(0)


def _cost_lines(cfg: TrainConfig, elapsed_s: float, remaining_s: float, backend: str) -> list[str]:
    """The estimate of the whole run's time, with a warning and the alternatives beyond a day."""
    total = elapsed_s + remaining_s
    steps = cfg.num_seeds * cfg.total_steps
    finish = time.strftime("%a %H:%M", time.localtime(time.time() + remaining_s))
    lines = [
        f"estimate: the whole run ({cfg.num_seeds} seed(s) x {cfg.total_steps:,} steps) takes "
        f"~{format_duration(total)} on {backend} ({steps / max(total, 1e-9):,.0f} steps/s); "
        f"done around {finish}"
    ]
    if total > LONG_RUN_S:
        lines.append(
            f"warning: this run needs ~{format_duration(total)}; for a result today use --preset quick "
            "(two Tracking XDSAC seeds take ~14 min on a 2-core CPU), fewer --seeds or --steps, or a GPU "
            "(pip install -e '.[cuda]'). Stop with Ctrl-C; --resume continues from the last checkpoint."
        )
    return lines


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    log=print,
    trainer: Trainer | None = None,
    stop_after_chunks: int | None = None,
    stop: StopController | None = None,
    warn=None,
) -> dict[str, Any] | None:
    """Run (or continue) the whole experiment into ``out``; returns the summary.

    Writes (``config.json`` is the caller's, see :func:`xrl_jax.evaluate.config_document`):
    ``plan.json`` (memory plan and seed groups), per seed ``metrics/seed_<i>.jsonl`` (one line per
    chunk) and ``eval/seed_<i>.jsonl`` (one line per evaluation), per group ``checkpoints/group_<g>``
    (the newest two, verified on restore), ``timing.jsonl`` and at the end ``summary.json``. Lines
    written after the newest checkpoint are dropped on resume and recomputed, so a resumed run's
    files equal an uninterrupted run's.

    The folder is locked for the duration (:class:`~xrl_jax.run_folder.RunLock`). Checkpoints are
    written every ``checkpoint_interval`` steps and every ``checkpoint_minutes`` of wall time, never
    after a chunk in which a seed went non-finite: that raises :class:`DivergenceError` with the
    last good checkpoint kept. ``stop`` (installed by the CLI) turns SIGINT/SIGTERM into a stop at a
    chunk boundary with a checkpoint, raising :class:`~xrl_jax.interrupts.RunInterrupted`.
    ``stop_after_chunks`` stops (returning None) after that many chunks of this session, as an
    interruption would; ``resume=True`` continues from the newest good checkpoint of each group.
    ``log`` takes progress lines; ``warn`` (default: standard error, also when ``log`` is silent)
    takes what the user must see: damaged checkpoints, too little disk, a run longer than a day.
    """
    out = Path(out)
    if warn is None:
        warn = functools.partial(print, file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    with RunLock(out):
        remove_leftovers(out)
        try:
            return _HostLoop(cfg, out, trainer, log, warn, progress, stop).run(resume, stop_after_chunks)
        except Exception as err:  # orbax reports a full disk as ValueError("RESOURCE_EXHAUSTED ...")
            if not is_disk_full(err):
                raise
            raise DiskFullError(
                f"the disk of {out} is full (No space left on device); committed checkpoints are intact: "
                f"free some space and continue with --resume {out}"
            ) from None


class _StopAfterChunks(Exception):
    pass


class _HostLoop:
    """The host side of :func:`train`: seed groups one after another, chunk after chunk, and
    between chunks the metric lines, the health check, evaluation and checkpoints."""

    def __init__(self, cfg: TrainConfig, out: Path, trainer: Trainer | None, log, warn, progress: bool, stop):
        self.cfg, self.out, self.log, self.warn, self.stop = cfg, out, log, warn, stop
        self.paths = run_paths(out)
        for key in ("metrics", "eval", "checkpoints"):
            self.paths[key].mkdir(parents=True, exist_ok=True)
        self.start_time = time.perf_counter()
        if stop is not None:
            stop.idle()
        self.backend = backend_summary()
        log(f"backend: {self.backend}")
        self.trainer = get_trainer(cfg) if trainer is None else trainer
        self.progress = progress
        self.bar = None
        self.timing = {"compile_s": 0.0, "train_s": 0.0, "eval_s": 0.0, "checkpoint_s": 0.0, "env_steps": 0}
        self.fingerprint = config_fingerprint(cfg)
        self.chunks_left: int | None = None
        self.saved_step = 0  # the newest checkpoint of the running seed group

    # ---- the run ------------------------------------------------------------------------------
    def run(self, resume: bool, stop_after_chunks: int | None) -> dict[str, Any] | None:
        self.chunks_left = stop_after_chunks
        self.plan = self._plan(resume)
        self.groups = self.plan["groups"]
        self.clock = _RunClock(self.cfg, len(self.groups))
        self.done_steps = 0
        try:
            for group_index, seeds in enumerate(self.groups):
                self._run_group(group_index, seeds, resume)
        except _StopAfterChunks:
            return None
        finally:
            if self.bar is not None:
                self.bar.close()
        if self.stop is not None:
            self.stop.idle()
        return self._summarise()

    def _plan(self, resume: bool) -> dict[str, Any]:
        cfg, paths, log = self.cfg, self.paths, self.log
        plan = plan_memory(self.trainer, cfg)
        if resume and paths["plan"].exists():  # keep the grouping the checkpoints were made with
            plan["groups"] = json.loads(paths["plan"].read_text())["groups"]
        else:
            write_atomic(paths["plan"], json.dumps(plan, indent=2, sort_keys=True) + "\n")
        groups, per_seed = plan["groups"], plan["per_seed_bytes"]
        total, buffer = format_bytes(per_seed["total"]), format_bytes(per_seed["buffer"])
        budget = format_bytes(plan["budget_bytes"])
        log(f"memory: ~{total} per seed (buffer {buffer}), budget {budget} ({plan['budget_source']})")
        if len(groups) > 1:
            log(f"memory: {cfg.num_seeds} seeds do not fit at once; running {len(groups)} groups of up to "
                f"{len(groups[0])} seeds one after another")  # fmt: skip
        # Two checkpoints kept per group, plus the one being written.
        needed = 3 * len(groups[0]) * (per_seed["buffer"] + per_seed["agent"] + per_seed["env"])
        free = disk_free_bytes(self.out)
        if free < needed:
            self.warn(f"warning: {format_bytes(free)} free on the disk of {self.out}, but the checkpoints "
                      f"of a seed group need up to {format_bytes(needed)}")  # fmt: skip
        return plan

    def _above_bar(self, write, line: str) -> None:
        if self.bar is None:
            write(line)
            return
        from tqdm import tqdm

        with tqdm.external_write_mode(file=sys.stderr):
            write(line)

    def _kept(self, step: int, group_index: int) -> str:
        """What a resume would continue from, in words."""
        where = f" (seed group {group_index + 1} of {len(self.groups)})" if len(self.groups) > 1 else ""
        if step <= 0:
            return f"nothing has been checkpointed yet{where}, so a resume starts this group afresh"
        return f"the checkpoint at step {step:,} of {self.cfg.total_steps:,} per seed is kept{where}"

    def _run_group(self, group_index: int, seeds: list[int], resume: bool) -> None:
        cfg, paths, trainer = self.cfg, self.paths, self.trainer
        ckpt = Checkpointer(paths["checkpoints"] / f"group_{group_index}")
        try:
            state, next_chunk = _restore_group(
                cfg, trainer, ckpt, seeds, group_index, self.fingerprint, resume, self.log, self.warn
            )
            resumed_step = cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
            self.saved_step = resumed_step
            metric_steps, eval_steps = _expected_rows(cfg, next_chunk)
            for seed in seeds:  # what the checkpoint continues must still be on disk
                check_history(paths["metrics"] / f"seed_{seed}.jsonl", metric_steps, "metric")
                check_history(paths["eval"] / f"seed_{seed}.jsonl", eval_steps, "evaluation")
            for seed in seeds:  # drop anything written after the checkpoint (or everything, when fresh)
                truncate_lines(paths["metrics"] / f"seed_{seed}.jsonl", resumed_step)
                truncate_lines(paths["eval"] / f"seed_{seed}.jsonl", resumed_step)
            self.done_steps += resumed_step * len(seeds)
            if self.stop is not None:
                self.stop.keep(self._kept(resumed_step, group_index))
            if next_chunk >= cfg.num_chunks:
                return
            if state is None:
                state = trainer.init(jnp.asarray(cfg.seed, jnp.int32), jnp.asarray(seeds, jnp.int32))
            # Committed to the device like a restored state, so both hit the same compiled chunk.
            state = jax.device_put(state, jax.devices()[0])
            self._compile(state, next_chunk)
            if self.bar is None:
                self.bar = _progress_bar(cfg.total_steps * cfg.num_seeds, self.done_steps, self.progress)
            self.clock.last_save = time.monotonic()
            for chunk_index in range(next_chunk, cfg.num_chunks):
                state = self._chunk(state, ckpt, group_index, seeds, chunk_index)
        finally:
            ckpt.close()

    def _compile(self, state: RunState, next_chunk: int) -> None:
        """Compile the chunk ahead of its first call, so that chunk timings are execution alone."""
        tic = time.perf_counter()
        self.log("compiling the training chunk ...")
        start = jnp.asarray(next_chunk * self.cfg.chunk_vector_steps, jnp.int32)
        self.trainer.chunk.lower(state, start).compile()  # jit reuses this executable
        seconds = time.perf_counter() - tic
        self.timing["compile_s"] += seconds
        self.log(f"compiled in {seconds:.0f} s")

    def _chunk(self, state, ckpt, group_index, seeds, chunk_index) -> RunState:
        """Run one chunk and everything the host does after it (``self.saved_step`` follows the
        newest checkpoint of the group)."""
        cfg, paths, stop, clock = self.cfg, self.paths, self.stop, self.clock
        if self.chunks_left is not None:
            if self.chunks_left <= 0:
                raise _StopAfterChunks
            self.chunks_left -= 1
        if stop is not None:
            stop.training(clock.expected_chunk_s())
        tic = time.perf_counter()
        start = jnp.asarray(chunk_index * cfg.chunk_vector_steps, jnp.int32)
        state, report = self.trainer.chunk(state, start)
        report = jax.device_get(report)
        elapsed = time.perf_counter() - tic
        if stop is not None:  # the host work until the next chunk: short, and known once measured
            stop.training((clock.eval_s or 0.0) + (clock.save_s or 0.0))
        step = cfg.chunk_end_step(chunk_index)
        collected = (step - (cfg.chunk_end_step(chunk_index - 1) if chunk_index else 0)) * len(seeds)
        self.timing["train_s"] += elapsed
        self.timing["env_steps"] += collected
        for seed, line in _metric_lines(step, seeds, report):
            append_lines(paths["metrics"] / f"seed_{seed}.jsonl", [line])
        def agent_of_row(row):
            return jax.tree.map(lambda x: x[row], state.agent)

        diverged = divergence_message(report, seeds, step, self.trainer.loss_names, agent_of_row)
        if diverged:
            kept = self._kept(self.saved_step, group_index)
            raise DivergenceError(
                f"{diverged}; stopped, and {kept} (resuming would diverge again: start a new run with "
                "other settings, e.g. lower actor_lr and critic_lr)"
            )
        if step % cfg.eval_interval == 0 or step == cfg.total_steps:
            state = self._evaluate(state, seeds, step)
        due = step % cfg.checkpoint_interval == 0 or step == cfg.total_steps or clock.checkpoint_due_by_time()
        if due or (stop is not None and stop.requested is not None):
            self._save(ckpt, state, seeds, chunk_index, step, group_index)
        if stop is not None and stop.requested is not None and self.saved_step != step:
            # the signal arrived during the evaluation or the save
            self._save(ckpt, state, seeds, chunk_index, step, group_index)
        self.done_steps += collected
        if self.bar is not None:
            name = "rollout/avg_episode_return"
            returns = np.where(report.has_data[name], report.metrics[name], np.nan)
            shown = f" return {np.nanmean(returns):.2f}" if np.any(np.isfinite(returns)) else ""
            self.bar.set_postfix_str(f"group {group_index + 1}/{len(self.groups)}{shown}", refresh=False)
            self.bar.update(collected)
        append_lines(paths["timing"], [{"group": group_index, "step": step, "seconds": elapsed}])
        if stop is not None and stop.requested is not None:
            raise RunInterrupted(stop.requested, self._kept(self.saved_step, group_index))
        clock.observe_chunk(chunk_index, elapsed)
        if not clock.estimated and clock.chunk_s is not None:
            clock.estimated = True
            remaining = clock.remaining_s(group_index, chunk_index + 1)
            so_far = time.perf_counter() - self.start_time
            estimate, *warnings = _cost_lines(cfg, so_far, remaining, self.backend)
            self._above_bar(self.log, estimate)
            for line in warnings:
                self._above_bar(self.warn, line)
        return state

    def _evaluate(self, state: RunState, seeds: list[int], step: int) -> RunState:
        from xrl_jax import evaluate as evaluate_mod

        tic = time.perf_counter()
        eval_keys, episodes = self.trainer.evaluate(state)
        state = state.replace(eval_key=eval_keys)
        episodes = jax.device_get(episodes)
        self.clock.eval_s = time.perf_counter() - tic
        self.timing["eval_s"] += self.clock.eval_s
        for row, seed in enumerate(seeds):
            per_episode = jax.tree.map(lambda x, r=row: np.asarray(x[r]), episodes)
            line = {"step": step, "seed": seed, **evaluate_mod.summarize_episodes(per_episode)}
            append_lines(self.paths["eval"] / f"seed_{seed}.jsonl", [line])
        return state

    def _save(self, ckpt, state, seeds, chunk_index: int, step: int, group_index: int) -> None:
        # A checkpoint can take up to the state's raw size on disk (compression helps only while the
        # buffer is empty). Checked first, because orbax reports a disk that fills during the save
        # from several threads at once.
        needed, free = _tree_bytes(state), disk_free_bytes(ckpt.directory)
        if free < needed:
            raise DiskFullError(
                f"the disk of {self.out} has {format_bytes(free)} free, but the checkpoint at step {step:,} "
                f"needs up to {format_bytes(needed)}; {self._kept(self.saved_step, group_index)}: free some "
                f"space and continue with --resume {self.out}"
            )
        tic = time.perf_counter()
        meta = {"next_chunk": chunk_index + 1, "seeds": seeds, "step": step, "config": self.fingerprint}
        ckpt.save(step, state, meta)
        self.clock.saved(time.perf_counter() - tic)
        self.timing["checkpoint_s"] += self.clock.save_s
        self.saved_step = step
        if self.stop is not None:
            self.stop.keep(self._kept(step, group_index))

    def _summarise(self) -> dict[str, Any]:
        from xrl_jax import evaluate as evaluate_mod

        timing = self.timing
        timing["wall_s"] = time.perf_counter() - self.start_time
        timing["env_steps_per_s"] = timing["env_steps"] / timing["train_s"] if timing["train_s"] > 0 else None
        summary = evaluate_mod.summarize_run(self.out, self.cfg)
        summary["timing_this_session"] = timing
        summary["memory_plan"] = {k: v for k, v in self.plan.items() if k != "groups"} | {
            "groups": len(self.groups)
        }
        write_atomic(self.paths["summary"], json.dumps(summary, indent=2, sort_keys=True) + "\n")
        if summary["curve"]:
            evaluate_mod.plot_learning_curve(summary, self.paths["curve"])
        return summary


def _restore_group(cfg, trainer, ckpt, seeds, group_index, fingerprint, resume, log, warn):
    """``(state or None, next_chunk)`` of a seed group: its newest good checkpoint when resuming."""
    if not resume or ckpt.latest_step() is None:
        return None, 0
    try:
        meta = ckpt.metadata()
    except CorruptCheckpointError:
        meta = None  # a damaged newest checkpoint: restore_newest_good reports it and falls back
    if meta is not None and meta.get("config", fingerprint) != fingerprint:
        raise ConfigError(
            f"checkpoint group {group_index} in {ckpt.directory.parent} was written by another "
            "configuration than config.json describes; start a new run with --out"
        )
    if meta is not None and meta.get("seeds") != seeds:
        raise ConfigError(f"checkpoint group {group_index} holds seeds {meta.get('seeds')}, expected {seeds}")

    def check(state, meta) -> str | None:
        if meta.get("config") != fingerprint or meta.get("seeds") != seeds:
            return "it belongs to another configuration or seed group"
        if not bool(tree_all_finite(state.agent)):
            return f"the agent's {_first_nonfinite_leaf(state.agent)} is not finite"
        return None

    state, meta = ckpt.restore_newest_good(trainer.abstract_state(len(seeds)), check, warn)
    log(f"resuming seed group {group_index + 1} from its checkpoint at step {meta['step']:,}")
    return state, int(meta["next_chunk"])


__all__ = [
    "ENVS",
    "PRESETS",
    "ChunkReport",
    "ConfigError",
    "DiskFullError",
    "DivergenceError",
    "MemoryPlanError",
    "RunState",
    "TrainConfig",
    "Trainer",
    "cached_track_bank",
    "estimate_seed_bytes",
    "get_trainer",
    "make_envs",
    "make_train",
    "parse_overrides",
    "plan_memory",
    "resolve_config",
    "track_cache_path",
    "train",
]
