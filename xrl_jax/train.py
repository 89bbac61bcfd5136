"""End-to-end vectorised trainer: the whole SAC loop in one compiled ``lax.scan`` chunk, vmapped over seeds.

Per seed (spec/algorithms.md §5, mapped to synchronous vector envs as §5.8 recommends):

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
from xrl_jax.config import ALGOS, AgentConfig

ENVS = ("country_road", "tracking", "intersection")
MULTI_AGENT_ENVS = ("intersection",)
PRESETS = ("paper", "quick", "smoke")
EPISODE_WINDOW = 100  # rollout metrics average over the last 100 finished episodes (spec §6.2)
EARLY_TERMINATION_REWARD = -0.5  # ETR: terminated with a last reward below this (spec §6.1)


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
    memory_budget_gb: float = 0.0  # 0: 90 % of the device's memory (host RAM on CPU)
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
    if preset == "paper":  # spec §5.7: 1e6 steps, buffer 1e6, eval every 1e5 on 100 episodes
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
    """Intersection (spec carenv-intersection.md §8): steps are multi-agent env steps; every alive
    agent's transition is stored and followed by one update. Paper: the released configs' values."""
    if preset == "paper":  # §8.7 "released configs" column; 2 envs as the reference's 2 workers
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
    (Intersection: the curriculum for training, always 8 vehicles for evaluation, spec §8.8)."""
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


def _window_means(window: EpisodeWindow, multi_agent: bool = False) -> dict[str, jax.Array]:
    """Averages over the window; multi-agent windows hold per-agent episodes (termination or the
    60 s restart) and the env's mean velocity instead of the track velocity."""
    filled = jnp.minimum(window.count, EPISODE_WINDOW)
    mask = jnp.arange(EPISODE_WINDOW) < filled
    denom = jnp.where(filled > 0, filled, 1)

    def mean(x):
        value = jnp.sum(jnp.where(mask, x.astype(jnp.float32), 0.0)) / denom
        return jnp.where(filled > 0, value, jnp.nan)

    return {
        "rollout/avg_episode_return": mean(window.returns),
        "rollout/avg_episode_length": mean(window.lengths),
        "rollout/early_termination_rate": mean(window.early),
        ("rollout/avg_mean_velocity" if multi_agent else "rollout/avg_track_velocity"): mean(
            window.track_velocity
        ),
        "rollout/episodes": window.count,
    }


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """The compiled pieces of one configuration (build with :func:`make_train`).

    * ``init(base_seed, seed_indices) -> RunState`` with a leading seed axis (seed ``i`` of a run
      uses ``fold_in(PRNGKey(base_seed), i)``, so a seed's stream does not depend on its group);
    * ``chunk(state, start_vector_step) -> (state, metrics)``: ``log_interval`` transitions per seed,
      the state donated; metrics are per-seed scalars (leading seed axis);
    * ``evaluate(state) -> (eval_keys, per_episode)``: the §6.1 protocol on the fixed tracks.
    """

    config: TrainConfig
    env: Any
    env_params: Any
    eval_params: Any
    agent: Agent
    init: Any
    chunk: Any
    evaluate: Any

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
        max_group_size=0,
        memory_budget_gb=0.0,
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
        """Primacy-bias reset (intersection spec §8.6): a fresh agent (same traced hyper-parameters)
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
        transition is stored (packed) and, after warm-up, followed by one gradient step (intersection
        spec §8.5: updates = agent transitions, 0..8 per env step, done as an exact ``while_loop``)."""
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
            flat(terminated & acted),  # time-limit restarts stay bootstrapped (spec Q8)
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
        denom = jnp.maximum(updates, 1)
        metrics = {
            f"train/{k}": jnp.where(updates > 0, jnp.sum(v) / denom, jnp.nan)
            for k, v in outs["metrics"].items()
        }
        metrics["train/updates"] = state.agent.step
        metrics["train/ent_coef"] = jnp.exp(state.agent.log_alpha)
        count = jnp.sum(outs["reward_count"])
        metrics["rollout/avg_step_reward"] = jnp.where(
            count > 0, jnp.sum(outs["reward_sum"]) / jnp.maximum(count, 1), jnp.nan
        )
        metrics.update(_window_means(state.window, multi))
        if multi:
            episodes = jnp.sum(outs["episodes_ended"])
            per_episode = jnp.maximum(episodes, 1)
            metrics["rollout/env_episodes"] = episodes
            metrics["rollout/trips_per_episode"] = jnp.where(
                episodes > 0, jnp.sum(outs["trips"]) / per_episode, jnp.nan
            )
            metrics["rollout/early_terminations_per_episode"] = jnp.where(
                episodes > 0, jnp.sum(outs["early_terminations"]) / per_episode, jnp.nan
            )
        metrics["buffer/stored_rows"] = state.buffer.filled_rows
        return state, metrics

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
    return Trainer(cfg, env, params, eval_params, agent, init, chunk, evaluate)


# ------------------------------------------------------------------------------------------------
# Memory planning
# ------------------------------------------------------------------------------------------------


def _tree_bytes(tree) -> int:
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape") and hasattr(x, "dtype")]
    return int(sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in leaves))


def device_memory_bytes() -> tuple[int, str]:
    """Usable memory of the default device: the allocator's limit on accelerators, available RAM on CPU."""
    device = jax.devices()[0]
    try:
        stats = device.memory_stats() or {}
    except Exception:
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.device_kind} memory"
    import psutil

    return int(psutil.virtual_memory().available), "available host RAM"


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
            f"one seed needs about {sizes['total'] / 1e9:.2f} GB (buffer {sizes['buffer'] / 1e9:.2f} GB) "
            f"but the budget ({source}) is {budget_bytes / 1e9:.2f} GB; "
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


def config_fingerprint(cfg: TrainConfig) -> str:
    """A hash of every setting that shapes the run's results (not the host-only memory settings);
    stored with each checkpoint so that a resume never continues another configuration's state."""
    fields = cfg.to_dict()
    for host_only in ("max_group_size", "memory_budget_gb"):
        fields.pop(host_only)
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def _jsonable(value):
    value = np.asarray(value)
    if value.ndim:
        return [_jsonable(v) for v in value]
    item = value.item()
    if isinstance(item, float) and not math.isfinite(item):
        return None
    return item


def _append_lines(path: Path, rows: list[dict]) -> None:
    """Append JSON lines and force them to disk (a crash loses at most the line being written)."""
    with open(path, "a") as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _truncate_lines(path: Path, max_step: int) -> None:
    """Keep only complete lines with ``step <= max_step`` (atomic rewrite), for a resumed run."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a crash
        if row.get("step", 0) <= max_step:
            kept.append(line)
    write_atomic(path, "".join(line + "\n" for line in kept))


def write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True, file=sys.stderr
    )


def run_paths(out: Path) -> dict[str, Path]:
    return {
        "config": out / "config.json",
        "metrics": out / "metrics",
        "eval": out / "eval",
        "checkpoints": out / "checkpoints",
        "summary": out / "summary.json",
        "curve": out / "learning_curve.png",
        "timing": out / "timing.jsonl",
    }


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    log=print,
    trainer: Trainer | None = None,
    stop_after_chunks: int | None = None,
) -> dict[str, Any] | None:
    """Run (or continue) the whole experiment into ``out``; returns the summary.

    Writes (``config.json`` is the caller's, see :func:`xrl_jax.evaluate.config_document`):
    ``plan.json`` (memory plan and seed groups), per seed ``metrics/seed_<i>.jsonl`` (one line per
    chunk) and ``eval/seed_<i>.jsonl`` (one line per evaluation), per group ``checkpoints/group_<g>``,
    ``timing.jsonl`` and at the end ``summary.json``. Lines written after the newest checkpoint are
    dropped on resume and recomputed, so a resumed run's files equal an uninterrupted run's.
    ``stop_after_chunks`` stops (returning None) after that many chunks of this session, as an
    interruption would; ``resume=True`` continues from the newest checkpoint of each group.
    """
    from xrl_jax import evaluate as evaluate_mod
    from xrl_jax.checkpoint import Checkpointer

    out = Path(out)
    paths = run_paths(out)
    for key in ("metrics", "eval", "checkpoints"):
        paths[key].mkdir(parents=True, exist_ok=True)
    start_time = time.perf_counter()
    if trainer is None:
        trainer = get_trainer(cfg)
    plan = plan_memory(trainer, cfg)
    plan_path = out / "plan.json"
    if resume and plan_path.exists():  # keep the grouping the checkpoints were made with
        plan["groups"] = json.loads(plan_path.read_text())["groups"]
    else:
        write_atomic(plan_path, json.dumps(plan, indent=2, sort_keys=True) + "\n")
    groups = plan["groups"]
    per_seed = plan["per_seed_bytes"]
    log(
        f"memory: ~{per_seed['total'] / 1e9:.3f} GB per seed (buffer {per_seed['buffer'] / 1e9:.3f} GB), "
        f"budget {plan['budget_bytes'] / 1e9:.1f} GB ({plan['budget_source']})"
    )
    if len(groups) > 1:
        log(f"memory: {cfg.num_seeds} seeds do not fit at once; running {len(groups)} groups of up to "
            f"{len(groups[0])} seeds one after another")  # fmt: skip

    fingerprint = config_fingerprint(cfg)
    total = cfg.total_steps * cfg.num_seeds
    done_steps = 0
    timing = {"compile_s": 0.0, "train_s": 0.0, "eval_s": 0.0, "checkpoint_s": 0.0, "env_steps": 0}
    bar = None
    chunks_run = 0
    for group_index, seeds in enumerate(groups):
        ckpt = Checkpointer(paths["checkpoints"] / f"group_{group_index}")
        seed_array = jnp.asarray(seeds, jnp.int32)
        next_chunk = 0
        state = None
        if resume and ckpt.latest_step() is not None:
            meta = ckpt.metadata()
            if meta.get("config", fingerprint) != fingerprint:
                raise ConfigError(
                    f"checkpoint group {group_index} in {paths['checkpoints']} was written by another "
                    "configuration than config.json describes; start a new run with --out"
                )
            if meta.get("seeds") != seeds:
                raise ConfigError(
                    f"checkpoint group {group_index} holds seeds {meta.get('seeds')}, expected {seeds}"
                )
            state, meta = ckpt.restore(trainer.abstract_state(len(seeds)))
            next_chunk = int(meta["next_chunk"])
        resumed_step = cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
        for seed in seeds:  # drop anything written after the checkpoint (or everything, when fresh)
            _truncate_lines(paths["metrics"] / f"seed_{seed}.jsonl", resumed_step)
            _truncate_lines(paths["eval"] / f"seed_{seed}.jsonl", resumed_step)
        done_steps += resumed_step * len(seeds)
        if next_chunk >= cfg.num_chunks:
            ckpt.close()
            continue
        if state is None:
            state = trainer.init(jnp.asarray(cfg.seed, jnp.int32), seed_array)
        # Committed to the device like a restored state, so both hit the same compiled chunk.
        state = jax.device_put(state, jax.devices()[0])
        if bar is None:
            bar = _progress_bar(total, done_steps, progress)
        latest_return = float("nan")
        for chunk_index in range(next_chunk, cfg.num_chunks):
            if stop_after_chunks is not None and chunks_run >= stop_after_chunks:
                if bar is not None:
                    bar.close()
                ckpt.close()
                return None
            chunks_run += 1
            tic = time.perf_counter()
            state, metrics = trainer.chunk(
                state, jnp.asarray(chunk_index * cfg.chunk_vector_steps, jnp.int32)
            )
            metrics = jax.device_get(metrics)
            elapsed = time.perf_counter() - tic
            step = cfg.chunk_end_step(chunk_index)
            collected = (step - (cfg.chunk_end_step(chunk_index - 1) if chunk_index else 0)) * len(seeds)
            if chunk_index == next_chunk:
                timing["compile_s"] += elapsed  # the first call of a group includes compilation
            else:
                timing["train_s"] += elapsed
                timing["env_steps"] += collected
            for row, seed in enumerate(seeds):
                line = {"step": step, "seed": seed, **{k: _jsonable(v[row]) for k, v in metrics.items()}}
                _append_lines(paths["metrics"] / f"seed_{seed}.jsonl", [line])
            returns = np.asarray(metrics["rollout/avg_episode_return"])
            if np.any(np.isfinite(returns)):
                latest_return = float(np.nanmean(returns))
            if step % cfg.eval_interval == 0 or step == cfg.total_steps:
                tic = time.perf_counter()
                eval_keys, episodes = trainer.evaluate(state)
                state = state.replace(eval_key=eval_keys)
                episodes = jax.device_get(episodes)
                timing["eval_s"] += time.perf_counter() - tic
                for row, seed in enumerate(seeds):
                    per_episode = jax.tree.map(lambda x, r=row: np.asarray(x[r]), episodes)
                    line = {"step": step, "seed": seed, **evaluate_mod.summarize_episodes(per_episode)}
                    _append_lines(paths["eval"] / f"seed_{seed}.jsonl", [line])
            if step % cfg.checkpoint_interval == 0 or step == cfg.total_steps:
                tic = time.perf_counter()
                meta = {"next_chunk": chunk_index + 1, "seeds": seeds, "step": step, "config": fingerprint}
                ckpt.save(step, state, meta)
                timing["checkpoint_s"] += time.perf_counter() - tic
            done_steps += collected
            if bar is not None:
                bar.set_postfix_str(
                    f"group {group_index + 1}/{len(groups)} return {latest_return:.2f}", refresh=False
                )
                bar.update(collected)
            _append_lines(paths["timing"], [{"group": group_index, "step": step, "seconds": elapsed}])
        ckpt.close()
        del state
    if bar is not None:
        bar.close()
    timing["wall_s"] = time.perf_counter() - start_time
    timing["env_steps_per_s"] = timing["env_steps"] / timing["train_s"] if timing["train_s"] > 0 else None
    summary = evaluate_mod.summarize_run(out, cfg)
    summary["timing_this_session"] = timing
    summary["memory_plan"] = {k: v for k, v in plan.items() if k != "groups"} | {"groups": len(groups)}
    write_atomic(paths["summary"], json.dumps(summary, indent=2, sort_keys=True) + "\n")
    if summary["curve"]:
        evaluate_mod.plot_learning_curve(summary, paths["curve"])
    return summary


__all__ = [
    "ENVS",
    "PRESETS",
    "ConfigError",
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
