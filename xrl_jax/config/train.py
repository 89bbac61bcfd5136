"""The run's configuration: everything about a run except the agent's hyper-parameters, which it
holds as an :class:`~xrl_jax.config.agent.AgentConfig`; the sweep it trains is validated with it."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping
from typing import Any

from xrl_jax.config.agent import AgentConfig
from xrl_jax.config.checks import ConfigError, check_choice, check_known, is_int, is_number, require, setting
from xrl_jax.config.names import (
    ACTOR_TWIN,
    CONTINUOUS_ALGOS,
    HOST_ONLY_FIELDS,
    ON_POLICY_TRACED_FIELDS,
    PRESETS,
    SWEEPABLE_FIELDS,
    TRAINED_ALGOS,
)
from xrl_jax.config.scenarios import Scenario, scenario


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything about a run except the agent's hyper-parameters (``agent``); validated on creation.

    Step counts are environment transitions *per seed*. ``log_interval`` is also the length of one
    compiled chunk; evaluation and checkpoint intervals are multiples of it so that every host-side
    event happens at a chunk boundary (which is what makes resuming exact).
    """

    env: str = setting("tracking", "scenario (--env)")
    algo: str = setting("xsac", "agent (--algo)")
    preset: str = setting("paper", "preset (--preset)")
    num_seeds: int = setting(1, "seeds trained at once (--seeds)")
    seed: int = setting(0, "base seed: seed i of the run uses fold_in(PRNGKey(seed), i)")
    total_steps: int = setting(1_000_000, "environment steps per seed (--steps)")
    num_envs: int = setting(4, "envs per seed stepping in lock-step")
    warmup_steps: int = setting(256, "random-action steps before the first update")
    batch_size: int = setting(256, "transitions per update")
    buffer_size: int = setting(1_000_000, "replay-buffer capacity (transitions per seed)")
    log_interval: int = setting(2_000, "steps per compiled chunk and metrics line")
    eval_interval: int = setting(100_000, "steps between evaluations (a multiple of log_interval)")
    eval_episodes: int = setting(100, "evaluation episodes (fixed tracks)")
    checkpoint_interval: int = setting(100_000, "steps between checkpoints (a multiple of log_interval)")
    train_tracks: int = setting(
        0, "0 = a fresh track for every training episode, as the original; N = a fixed bank of N tracks"
    )
    track_feed_size: int = setting(128, "fresh tracks generated ahead per seed (about 53 KB each)")
    track_seed: int = setting(0, "seed of the training tracks (a fixed bank, or each seed's fresh stream)")
    eval_track_seed: int = setting(
        1, "seed of the evaluation tracks, disjoint from the training tracks (a user's env: of its resets)"
    )
    reinit_steps: int = setting(
        0, "re-initialise the agent (not the buffer) every this many steps; 0 = never"
    )
    max_group_size: int = setting(0, "seeds per group at most; 0 = as many as the memory budget allows")
    memory_budget_gb: float = setting(0.0, "0 = 90 % of the device memory (host RAM within any cgroup limit)")
    checkpoint_minutes: float = setting(30.0, "also checkpoint by wall time (costing at most 2 %); 0 = off")
    num_devices: int = setting(
        0, "devices the members are spread over (--devices); 0 = every device JAX sees"
    )
    sweep: tuple = setting(
        (), "swept agent settings, ((name, (value, ...)), ...) (--sweep); the grid is their product"
    )
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)

    def __post_init__(self) -> None:
        _validate_train(self)

    @property
    def scenario(self) -> Scenario:
        return scenario(self.env)

    @property
    def env_name(self) -> str:
        """The registry name: on a built-in scenario, discrete agents use the 12-way action variant;
        a user's env is one env with one action space."""
        both = self.scenario.actions == "both"
        return self.env + ("_discrete" if both and self.agent.is_discrete else "")

    @property
    def fresh_tracks(self) -> bool:  # racing trains on fresh tracks unless a fixed bank is asked for
        return self.train_tracks == 0 and self.scenario.on_tracks

    @property
    def buffer_layout(self) -> str:
        """One transition per env and step keeps each observation once ("compact", truncations
        dropped); packed transitions (several agent slots per env, a varying number acting per step)
        and kept truncations store next_obs ("explicit")."""
        compact = self.agent.truncation == "drop" and self.scenario.agent_slots == 1
        return "compact" if compact else "explicit"

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

    def evaluates_at(self, step: int) -> bool:  # every eval_interval steps, and at the end
        return step % self.eval_interval == 0 or step == self.total_steps

    def checkpoints_at(self, step: int) -> bool:  # by steps; time-based checkpoints come on top
        return step % self.checkpoint_interval == 0 or step == self.total_steps

    def replace(self, **changes: Any) -> TrainConfig:
        return dataclasses.replace(self, **changes)

    # ---- sweep points and members -------------------------------------------------------------
    @property
    def sweep_points(self) -> list[dict[str, float]]:
        """The swept values of every point of the grid (the product of the swept lists, the first
        field varying slowest); one empty point for a plain run."""
        names = [name for name, _ in self.sweep]
        return [
            dict(zip(names, values, strict=True)) for values in itertools.product(*(v for _, v in self.sweep))
        ]

    @property
    def num_points(self) -> int:
        return math.prod(len(values) for _, values in self.sweep)

    @property
    def num_members(self) -> int:
        """Sweep points x seeds: the rows of the one vmapped axis the run trains."""
        return self.num_points * self.num_seeds

    def member_point_seed(self, member: int) -> tuple[int, int]:
        """``(point, seed)`` of member ``member`` (members are point-major: point p, seed s is
        member p * num_seeds + s)."""
        return divmod(int(member), self.num_seeds)

    def point_members(self, point: int) -> range:
        """The members of sweep point ``point``, in seed order."""
        return range(point * self.num_seeds, (point + 1) * self.num_seeds)

    def point_agent(self, point: int) -> AgentConfig:
        """The agent config of sweep point ``point`` (validated, like any config)."""
        return self.agent.replace(**self.sweep_points[point])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the train fields and the agent config, both fully resolved."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "agent"}
        out["sweep"] = [[name, list(values)] for name, values in self.sweep]
        out["agent"] = dataclasses.asdict(self.agent)
        return out

    def results_fields(self) -> dict[str, Any]:
        """:meth:`to_dict` without the settings that only the host loop reads (``HOST_ONLY_FIELDS``):
        what shapes the compiled program and the results. The one place that strips them, for the
        checkpoints' config fingerprint and the trainer's cache key (:meth:`without_host_settings`)."""
        fields = self.to_dict()
        for name in HOST_ONLY_FIELDS:
            fields.pop(name)
        return fields

    def without_host_settings(self) -> TrainConfig:
        """The same run with the host-only settings at their defaults."""
        return TrainConfig.from_dict(self.results_fields())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        data = dict(data)
        data["sweep"] = tuple((name, tuple(values)) for name, values in data.get("sweep", ()))
        agent = dict(data.pop("agent"))
        agent.setdefault("neutral_flag", agent.get("neutral_object", False))  # older runs flagged the row
        agent = AgentConfig(**agent)
        check_known(data, train_field_names(), "TrainConfig")
        return cls(agent=agent, **data)


def train_field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(TrainConfig) if f.name != "agent"]


def _validate_train(cfg: TrainConfig) -> None:
    for name, choices in (("algo", TRAINED_ALGOS), ("preset", PRESETS)):
        check_choice("", name, getattr(cfg, name), choices)
    actions = cfg.scenario.actions  # raises for an unknown env, saying how a user's env is registered
    continuous = ACTOR_TWIN.get(cfg.algo, cfg.algo) in CONTINUOUS_ALGOS
    require(
        actions == "both" or continuous == (actions == "continuous"),
        f"{cfg.env} has {actions} actions: train it with "
        + ("sac, xsac, ppo or xppo" if actions == "continuous" else "dsac, xdsac, dppo or xdppo")
        + f", not {cfg.algo}",
    )
    require(
        isinstance(cfg.agent, AgentConfig), f"agent must be an AgentConfig, got {type(cfg.agent).__name__}"
    )
    require(cfg.agent.algo == cfg.algo, f"agent.algo ({cfg.agent.algo}) differs from algo ({cfg.algo})")
    for name in (
        "num_seeds",
        "total_steps",
        "num_envs",
        "batch_size",
        "buffer_size",
        "log_interval",
        "eval_interval",
        "eval_episodes",
        "checkpoint_interval",
        "track_feed_size",
    ):
        require(
            is_int(getattr(cfg, name), 1), f"{name} must be a positive integer, got {getattr(cfg, name)!r}"
        )
    for name in (
        "seed",
        "train_tracks",
        "track_seed",
        "eval_track_seed",
        "max_group_size",
        "reinit_steps",
        "num_devices",
    ):
        value = getattr(cfg, name)
        require(is_int(value, 0), f"{name} must be a non-negative integer, got {value!r}")
    require(
        is_number(cfg.memory_budget_gb) and cfg.memory_budget_gb >= 0,
        f"memory_budget_gb must be >= 0 (0 = automatic), got {cfg.memory_budget_gb!r}",
    )
    require(
        is_number(cfg.checkpoint_minutes) and cfg.checkpoint_minutes >= 0,
        f"checkpoint_minutes must be a number >= 0 (0 = by steps only), got {cfg.checkpoint_minutes!r}",
    )
    e = cfg.num_envs
    require(cfg.total_steps % e == 0, f"steps ({cfg.total_steps}) must be a multiple of num_envs ({e})")
    require(
        cfg.log_interval % e == 0, f"log_interval ({cfg.log_interval}) must be a multiple of num_envs ({e})"
    )
    for name in ("eval_interval", "checkpoint_interval"):
        require(
            getattr(cfg, name) % cfg.log_interval == 0,
            f"{name} ({getattr(cfg, name)}) must be a multiple of log_interval ({cfg.log_interval})",
        )
    if cfg.agent.is_on_policy:
        _validate_on_policy(cfg)
    else:
        warmup = cfg.warmup_steps
        require(is_int(warmup, 1), f"warmup_steps must be a positive integer, got {warmup!r}")
        require(cfg.warmup_steps >= e, f"warmup_steps ({cfg.warmup_steps}) must be at least num_envs ({e})")
    require(
        cfg.fresh_tracks or not cfg.scenario.on_tracks or cfg.track_seed != cfg.eval_track_seed,
        f"track_seed and eval_track_seed are both {cfg.track_seed}: "
        "the evaluation tracks would be training tracks",
    )
    require(
        cfg.track_feed_size >= 2 * e,
        f"track_feed_size ({cfg.track_feed_size}) must be at least 2 x num_envs ({2 * e}): every env "
        "starts on a fresh track and half the feed is refilled at a time",
    )
    require(
        cfg.buffer_size >= cfg.batch_size,
        f"buffer_size ({cfg.buffer_size}) must be at least batch_size ({cfg.batch_size})",
    )
    _validate_sweep(cfg)
    if cfg.scenario.agent_slots > 1 and not cfg.agent.is_on_policy:  # packed transitions, a row per agent
        slots = cfg.scenario.agent_slots
        require(
            cfg.buffer_size >= slots * e,
            f"buffer_size ({cfg.buffer_size}) must hold one step of all agents ({slots * e})",
        )


def _validate_on_policy(cfg: TrainConfig) -> None:
    """The on-policy family's run: whole rollouts per chunk, minibatches that split a rollout, no
    warm-up (it acts by its policy from the first step) and no primacy-bias resets."""
    agent, e = cfg.agent, cfg.num_envs
    rollout = agent.rollout_steps * e
    first_step = f"{cfg.algo} acts by its policy from its first step"
    require(cfg.warmup_steps == 0, f"{first_step}: warmup_steps must be 0, got {cfg.warmup_steps}")
    require(
        cfg.reinit_steps == 0,
        f"reinit_steps (primacy-bias resets, the Intersection SAC protocol's) is not for {cfg.algo}: "
        f"set it to 0, got {cfg.reinit_steps}",
    )
    for name in ("log_interval", "total_steps"):
        require(
            getattr(cfg, name) % rollout == 0,
            f"{name} ({getattr(cfg, name)}) must be a multiple of one rollout, rollout_steps x num_envs "
            f"= {agent.rollout_steps} x {e} = {rollout}",
        )
    rows = rollout * cfg.scenario.agent_slots  # every agent slot's steps (the empty ones masked out)
    require(
        rows % agent.ppo_minibatches == 0,
        f"a rollout of {rows} transitions cannot be split into ppo_minibatches={agent.ppo_minibatches}",
    )


def sweepable_fields(agent: AgentConfig) -> tuple[str, ...]:
    """What ``--sweep`` may vary for ``agent``'s algorithm: its family's traced settings."""
    return ON_POLICY_TRACED_FIELDS if agent.is_on_policy else SWEEPABLE_FIELDS


def unused_sweep_reason(agent: AgentConfig, name: str) -> str | None:
    """Why ``agent`` would ignore swept field ``name`` (None when it uses it): a sweep over a value
    the algorithm never reads would train identical members and report noise as an effect."""
    if name == "kappa" and not agent.is_mixture:
        return f"{agent.algo} has no mixture (kappa weighs the mixture entropy of xsac, xdsac, xppo, xdppo)"
    if name in ("alpha_lr", "target_entropy") and not agent.auto_alpha:
        return f"the entropy coefficient is fixed (auto_alpha false), so {name} is never used"
    return None


def _validate_sweep(cfg: TrainConfig) -> None:
    sweep = cfg.sweep
    require(isinstance(sweep, tuple), f"sweep must be a tuple of (name, values) pairs, got {sweep!r}")
    names = []
    for entry in sweep:
        require(
            isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[1], tuple),
            f"sweep entries must be (name, (value, ...)) pairs, got {entry!r}",
        )
        name, values = entry
        require(name not in names, f"--sweep {name} is given twice; give all its values in one list")
        names.append(name)
        sweepable = sweepable_fields(cfg.agent)
        require(
            name in sweepable,
            f"cannot sweep {name} for {cfg.algo}: only traced settings can vary within one program "
            f"(sweepable: {', '.join(sweepable)}); run one process per value of a static setting",
        )
        require(len(values) > 0, f"--sweep {name} has no values")
        require(
            all(is_number(v) and math.isfinite(v) for v in values),
            f"--sweep {name}: values must be finite numbers",
        )
        require(len(set(values)) == len(values), f"--sweep {name} repeats a value: {list(values)}")
        reason = unused_sweep_reason(cfg.agent, name)
        require(reason is None, f"cannot sweep {name}: {reason}")
    for point in cfg.sweep_points:  # every point must be a valid agent on its own
        try:
            cfg.agent.replace(**point)
        except ConfigError as err:
            raise ConfigError(f"sweep point {point}: {err}") from None
