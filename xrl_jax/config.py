"""Every configuration of xrl-jax in one jax-free module: the names, the two config dataclasses, the
presets as tables, and the one typed parser behind ``--set`` (docs/algorithms.md §5.7).

* :class:`AgentConfig`: architecture sizes and switches (static: they fix shapes and control flow)
  and optimisation constants (traced: copied into the agent state by
  :func:`xrl_jax.agents.make_agent` so that sweeps can ``vmap`` over them; :data:`TRACED_FIELDS`).
* :class:`TrainConfig`: everything else about a run; it holds its :class:`AgentConfig`.
* :func:`resolve_config`: preset, explicit arguments, then ``--set`` overrides, validated.

Every field carries its documentation (``help`` metadata), from which :func:`settings_help` writes
the CLI's list of settings. Configs are frozen and validated on construction, so a bad value fails
in one line where it is written rather than deep inside a jitted update. Adding a field or a
preset touches this file only.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import textwrap
import typing
from collections.abc import Mapping
from typing import Any

ALGOS = ("sac", "dsac", "xsac", "xdsac")
ENVS = ("country_road", "tracking", "intersection")
PRESETS = ("paper", "quick", "smoke")
MULTI_AGENT_ENVS = ("intersection",)
CONTINUOUS_ALGOS = ("sac", "xsac")
DISCRETE_ALGOS = ("dsac", "xdsac")
MIXTURE_ALGOS = ("xsac", "xdsac")
FEATURE_EXTRACTORS = ("deepset", "flat_pe")  # names of xrl_jax.networks.make_extractor
CRITIC_LOSSES = ("huber", "l2")
TRUNCATION_MODES = ("drop", "bootstrap")
MIXTURE_LOG_STD_MIN = -5.0  # lower log σ clip of the mixture policies (§2.3: σ ≥ e^-5 keeps densities sane)
SAC_LOG_STD_MIN = -20.0  # lower log σ clip of the baseline SAC actor (§2.1)
LOG_STD_MAX = 2.0  # upper log σ clip of every Gaussian policy (§2.1, §2.3)
MAX_VEHICLES = 8  # vehicle slots of the intersection env (envs.intersection.MAX_AGENTS; a test checks)

# Fields that become traced leaves of the agent state (``AgentState.hparams``; can differ per vmapped
# seed / sweep member). init_alpha only sets the initial ``AgentState.log_alpha``, itself a traced leaf.
TRACED_FIELDS = ("actor_lr", "critic_lr", "alpha_lr", "gamma", "tau", "kappa", "target_entropy")
# What ``--sweep`` may vary within one compiled program: the traced fields and the initial α.
SWEEPABLE_FIELDS = (*TRACED_FIELDS, "init_alpha")
# Settings that only the host loop reads: they change neither the compiled code nor the results.
HOST_ONLY_FIELDS = ("max_group_size", "memory_budget_gb", "checkpoint_minutes", "num_devices")


class ConfigError(ValueError):
    """An invalid configuration; the message is one line naming the allowed values."""


def _field(default: Any, help: str, **kwargs: Any) -> Any:
    return dataclasses.field(default=default, metadata={"help": help}, **kwargs)


# ---- The agent ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Hyper-parameters of one agent; defaults are the common values of §5.7 (racing SAC shapes)."""

    algo: str = _field("sac", "agent: sac, dsac, xsac, xdsac")
    # --- architecture (static) ---
    actor_width: int = _field(256, "actor hidden width")
    actor_depth: int = _field(2, "actor hidden layers")
    critic_width: int = _field(256, "critic hidden width")
    critic_depth: int = _field(2, "critic hidden layers")
    n_critics: int = _field(2, "critics in the ensemble (the minimum is the target)")
    feature_extractor: str = _field("deepset", "critic (and baseline actor) extractor: deepset | flat_pe")
    fe_width: int = _field(128, "Deep Set width and state-encoder width")
    fe_item_depth: int = _field(3, "Deep Set item-encoder layers (Fourier / first Dense included)")
    fe_set_depth: int = _field(2, "Deep Set set-encoder layers after the sum")
    fourier_scale: float | None = _field(30.0, "learned Fourier features scale b; none = plain Dense")
    pe_freqs: int = _field(4, "positional-encoding frequencies of the tracking extractor")
    duelling: bool = _field(True, "duelling discrete critics (XDSAC always, §2.4)")
    components_per_object: int = _field(1, "mixture components per object (X agents)")
    neutral_object: bool = _field(
        False, "X agents: an always-present all-zero object (a state-only component, Appendix A)"
    )
    neutral_flag: bool = _field(False, "the neutral row's present column: 0 as the original, or 1 (true)")
    weight_depth: int | None = _field(None, "φ_d: hidden layer feeding the mixture weights; none = last")
    uniform_mixture: bool = _field(False, "ablation §3.1.6: uniform weights over present objects")
    packed_rows: float | None = _field(
        None,
        "per-object layers on the present objects only, packed into this many rows per set on average "
        "over a call (more present objects: that call computes on every slot); none = every slot "
        "(docs/performance.md)",
    )
    dense_sets: bool = _field(False, "per-object layers on every slot even with packed_rows (comparison)")
    log_std_min: float | None = _field(None, "lower log σ bound; none = SAC −20, XSAC −5 (§7.1)")
    log_std_max: float = _field(LOG_STD_MAX, "upper log σ bound")
    # --- optimisation (static switches) ---
    critic_loss: str = _field("huber", "critic loss: huber (δ = 1, every paper config) | l2")
    clip_norm: float | None = _field(None, "global gradient-norm clipping; none = off")
    auto_alpha: bool = _field(True, "learn the entropy coefficient α")
    epsilon_random: float | None = _field(None, "random-action probability; none = 0.05 discrete, 0")
    truncation: str = _field("drop", "truncated transitions: drop (paper) | bootstrap")
    lr_decay_updates: int = _field(0, "linear decay of the learning rates to zero over this many updates")
    # --- optimisation (traced) ---
    actor_lr: float = _field(1e-4, "actor learning rate")
    critic_lr: float = _field(1e-4, "critic learning rate")
    alpha_lr: float | None = _field(None, "α learning rate; none = critic_lr (§1.3)")
    gamma: float = _field(0.95, "discount")
    tau: float = _field(0.005, "Polyak factor of the target critics")
    kappa: float = _field(1e-3, "mixture-entropy weight κ of eq. 10 (X agents; may be negative)")
    init_alpha: float = _field(0.1, "initial (or fixed) entropy coefficient α")
    target_entropy: float | None = _field(None, "none = −A (continuous), 0.9 ln N (DSAC), 0.5 ln N (XDSAC)")

    def __post_init__(self) -> None:
        _validate_agent(self)

    @property
    def is_discrete(self) -> bool:
        return self.algo in DISCRETE_ALGOS

    @property
    def is_mixture(self) -> bool:
        return self.algo in MIXTURE_ALGOS

    def resolved_log_std_min(self) -> float:
        if self.log_std_min is not None:
            return float(self.log_std_min)
        return MIXTURE_LOG_STD_MIN if self.algo == "xsac" else SAC_LOG_STD_MIN

    def resolved_alpha_lr(self) -> float:
        return float(self.critic_lr if self.alpha_lr is None else self.alpha_lr)

    def resolved_epsilon_random(self) -> float:
        if self.epsilon_random is not None:
            return float(self.epsilon_random)
        return 0.05 if self.is_discrete else 0.0

    def resolved_target_entropy(self, action_size: int) -> float:
        """Target entropy; `action_size` is A (continuous) or N (discrete). Defaults of §1.3."""
        if self.target_entropy is not None:  # an explicit 0.0 is honoured (the reference's quirk is not)
            return float(self.target_entropy)
        if not self.is_discrete:
            return -float(action_size)
        scale = 0.9 if self.algo == "dsac" else 0.5
        return scale * math.log(action_size)

    def replace(self, **changes: Any) -> AgentConfig:
        """A validated copy with some fields changed (unknown names raise)."""
        _check_known(changes, field_names(), "AgentConfig")
        return dataclasses.replace(self, **changes)


def field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(AgentConfig)]


def _check_known(changes: Mapping[str, Any], known: list[str], what: str) -> None:
    unknown = sorted(set(changes) - set(known))
    if unknown:
        raise ConfigError(f"{what}: unknown field(s) {unknown}; valid fields: {sorted(known)}")


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def _is_int(value: Any, minimum: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_choice(what: str, name: str, value: Any, choices: tuple[str, ...]) -> None:
    _require(value in choices, f"{what}unknown {name} {value!r}; allowed: {', '.join(choices)}")


def _validate_agent(cfg: AgentConfig) -> None:
    def check(condition: bool, message: str) -> None:
        _require(condition, f"AgentConfig: {message}")

    for name, choices in (
        ("algo", ALGOS),
        ("feature_extractor", FEATURE_EXTRACTORS),
        ("critic_loss", CRITIC_LOSSES),
        ("truncation", TRUNCATION_MODES),
    ):
        _check_choice("AgentConfig: ", name, getattr(cfg, name), choices)
    for name in (
        "actor_width",
        "actor_depth",
        "critic_width",
        "critic_depth",
        "fe_width",
        "fe_item_depth",
        "fe_set_depth",
        "n_critics",
        "components_per_object",
    ):
        check(
            _is_int(getattr(cfg, name), 1), f"{name} must be a positive integer, got {getattr(cfg, name)!r}"
        )
    for name in ("lr_decay_updates", "pe_freqs"):
        check(
            _is_int(getattr(cfg, name), 0),
            f"{name} must be a non-negative integer, got {getattr(cfg, name)!r}",
        )
    for name in ("duelling", "neutral_object", "neutral_flag", "uniform_mixture", "auto_alpha", "dense_sets"):
        check(isinstance(getattr(cfg, name), bool), f"{name} must be a bool, got {getattr(cfg, name)!r}")
    if cfg.weight_depth is not None:
        check(
            _is_int(cfg.weight_depth, 1) and cfg.weight_depth <= cfg.actor_depth,
            f"weight_depth (φ_d) must lie in 1..actor_depth={cfg.actor_depth}, got {cfg.weight_depth}",
        )
    check(
        not cfg.neutral_object or cfg.is_mixture,
        f"neutral_object only applies to the mixture actors (xsac, xdsac); {cfg.algo} has no object slots",
    )
    check(not cfg.neutral_flag or cfg.neutral_object, "neutral_flag needs neutral_object")
    check(
        cfg.algo != "xdsac" or cfg.duelling,
        "XDSAC always uses a duelling critic (docs/algorithms.md §2.4); duelling=False is only for DSAC",
    )
    positive = ["actor_lr", "critic_lr", "init_alpha", "alpha_lr", "clip_norm", "fourier_scale"]
    positive.append("packed_rows")
    for name in ["kappa", "gamma", "tau", "target_entropy", "log_std_max", "log_std_min", *positive]:
        value = getattr(cfg, name)
        if value is None:
            continue
        check(_is_number(value), f"{name} must be a finite number, got {value!r}")
        check(name not in positive or value > 0, f"{name} must be positive, got {value}")
    check(0.0 <= cfg.gamma <= 1.0, f"gamma must lie in [0, 1], got {cfg.gamma}")
    check(0.0 < cfg.tau <= 1.0, f"tau must lie in (0, 1], got {cfg.tau}")
    if cfg.epsilon_random is not None:
        check(
            _is_number(cfg.epsilon_random) and 0.0 <= cfg.epsilon_random <= 1.0,
            f"epsilon_random must lie in [0, 1], got {cfg.epsilon_random}",
        )
    low = cfg.resolved_log_std_min()
    check(low < cfg.log_std_max, f"log_std_min ({low}) must be below log_std_max ({cfg.log_std_max})")


# ---- The run -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything about a run except the agent's hyper-parameters (``agent``); validated on creation.

    Step counts are environment transitions *per seed*. ``log_interval`` is also the length of one
    compiled chunk; evaluation and checkpoint intervals are multiples of it so that every host-side
    event happens at a chunk boundary (which is what makes resuming exact).
    """

    env: str = _field("tracking", "scenario (--env)")
    algo: str = _field("xsac", "agent (--algo)")
    preset: str = _field("paper", "preset (--preset)")
    num_seeds: int = _field(1, "seeds trained at once (--seeds)")
    seed: int = _field(0, "base seed: seed i of the run uses fold_in(PRNGKey(seed), i)")
    total_steps: int = _field(1_000_000, "environment steps per seed (--steps)")
    num_envs: int = _field(4, "envs per seed stepping in lock-step")
    warmup_steps: int = _field(256, "random-action steps before the first update")
    batch_size: int = _field(256, "transitions per update")
    buffer_size: int = _field(1_000_000, "replay-buffer capacity (transitions per seed)")
    log_interval: int = _field(2_000, "steps per compiled chunk and metrics line")
    eval_interval: int = _field(100_000, "steps between evaluations (a multiple of log_interval)")
    eval_episodes: int = _field(100, "evaluation episodes (fixed tracks)")
    checkpoint_interval: int = _field(100_000, "steps between checkpoints (a multiple of log_interval)")
    train_tracks: int = _field(
        0, "0 = a fresh track for every training episode, as the original; N = a fixed bank of N tracks"
    )
    track_feed_size: int = _field(128, "fresh tracks generated ahead per seed (about 53 KB each)")
    track_seed: int = _field(0, "seed of the training tracks (a fixed bank, or each seed's fresh stream)")
    eval_track_seed: int = _field(1, "seed of the evaluation tracks, disjoint from the training tracks")
    reinit_steps: int = _field(0, "re-initialise the agent (not the buffer) every this many steps; 0 = never")
    max_group_size: int = _field(0, "seeds per group at most; 0 = as many as the memory budget allows")
    memory_budget_gb: float = _field(0.0, "0 = 90 % of the device memory (host RAM within any cgroup limit)")
    checkpoint_minutes: float = _field(30.0, "also checkpoint by wall time (costing at most 2 %); 0 = off")
    num_devices: int = _field(0, "devices the members are spread over (--devices); 0 = every device JAX sees")
    sweep: tuple = _field(
        (), "swept agent settings, ((name, (value, ...)), ...) (--sweep); the grid is their product"
    )
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)

    def __post_init__(self) -> None:
        _validate_train(self)

    @property
    def env_name(self) -> str:
        """The registry name: discrete agents use the 12-way action variant."""
        return self.env + ("_discrete" if self.agent.is_discrete else "")

    @property
    def multi_agent(self) -> bool:
        return self.env in MULTI_AGENT_ENVS

    @property
    def fresh_tracks(self) -> bool:  # racing trains on fresh tracks unless a fixed bank is asked for
        return self.train_tracks == 0 and not self.multi_agent

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

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        data = dict(data)
        data["sweep"] = tuple((name, tuple(values)) for name, values in data.get("sweep", ()))
        agent = dict(data.pop("agent"))
        agent.setdefault("neutral_flag", agent.get("neutral_object", False))  # older runs flagged the row
        agent = AgentConfig(**agent)
        _check_known(data, train_field_names(), "TrainConfig")
        return cls(agent=agent, **data)


def train_field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(TrainConfig) if f.name != "agent"]


def _validate_train(cfg: TrainConfig) -> None:
    for name, choices in (("env", ENVS), ("algo", ALGOS), ("preset", PRESETS)):
        _check_choice("", name, getattr(cfg, name), choices)
    _require(
        isinstance(cfg.agent, AgentConfig), f"agent must be an AgentConfig, got {type(cfg.agent).__name__}"
    )
    _require(cfg.agent.algo == cfg.algo, f"agent.algo ({cfg.agent.algo}) differs from algo ({cfg.algo})")
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
        "warmup_steps",
    ):
        _require(
            _is_int(getattr(cfg, name), 1), f"{name} must be a positive integer, got {getattr(cfg, name)!r}"
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
        _require(_is_int(value, 0), f"{name} must be a non-negative integer, got {value!r}")
    _require(
        _is_number(cfg.memory_budget_gb) and cfg.memory_budget_gb >= 0,
        f"memory_budget_gb must be >= 0 (0 = automatic), got {cfg.memory_budget_gb!r}",
    )
    _require(
        _is_number(cfg.checkpoint_minutes) and cfg.checkpoint_minutes >= 0,
        f"checkpoint_minutes must be a number >= 0 (0 = by steps only), got {cfg.checkpoint_minutes!r}",
    )
    e = cfg.num_envs
    _require(cfg.total_steps % e == 0, f"steps ({cfg.total_steps}) must be a multiple of num_envs ({e})")
    _require(
        cfg.log_interval % e == 0, f"log_interval ({cfg.log_interval}) must be a multiple of num_envs ({e})"
    )
    for name in ("eval_interval", "checkpoint_interval"):
        _require(
            getattr(cfg, name) % cfg.log_interval == 0,
            f"{name} ({getattr(cfg, name)}) must be a multiple of log_interval ({cfg.log_interval})",
        )
    _require(cfg.warmup_steps >= e, f"warmup_steps ({cfg.warmup_steps}) must be at least num_envs ({e})")
    _require(
        cfg.fresh_tracks or cfg.multi_agent or cfg.track_seed != cfg.eval_track_seed,
        f"track_seed and eval_track_seed are both {cfg.track_seed}: "
        "the evaluation tracks would be training tracks",
    )
    _require(
        cfg.track_feed_size >= 2 * e,
        f"track_feed_size ({cfg.track_feed_size}) must be at least 2 x num_envs ({2 * e}): every env "
        "starts on a fresh track and half the feed is refilled at a time",
    )
    _require(
        cfg.buffer_size >= cfg.batch_size,
        f"buffer_size ({cfg.buffer_size}) must be at least batch_size ({cfg.batch_size})",
    )
    _validate_sweep(cfg)
    if cfg.multi_agent:
        _require(
            cfg.buffer_size >= MAX_VEHICLES * e,
            f"buffer_size ({cfg.buffer_size}) must hold one step of all agents ({MAX_VEHICLES * e})",
        )


def unused_sweep_reason(agent: AgentConfig, name: str) -> str | None:
    """Why ``agent`` would ignore swept field ``name`` (None when it uses it): a sweep over a value
    the algorithm never reads would train identical members and report noise as an effect."""
    if name == "kappa" and not agent.is_mixture:
        return f"{agent.algo} has no mixture (kappa weighs the mixture entropy of xsac and xdsac)"
    if name in ("alpha_lr", "target_entropy") and not agent.auto_alpha:
        return f"the entropy coefficient is fixed (auto_alpha false), so {name} is never used"
    return None


def _validate_sweep(cfg: TrainConfig) -> None:
    sweep = cfg.sweep
    _require(isinstance(sweep, tuple), f"sweep must be a tuple of (name, values) pairs, got {sweep!r}")
    names = []
    for entry in sweep:
        _require(
            isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[1], tuple),
            f"sweep entries must be (name, (value, ...)) pairs, got {entry!r}",
        )
        name, values = entry
        _require(name not in names, f"--sweep {name} is given twice; give all its values in one list")
        names.append(name)
        _require(
            name in SWEEPABLE_FIELDS,
            f"cannot sweep {name}: only traced settings can vary within one program "
            f"(sweepable: {', '.join(SWEEPABLE_FIELDS)}); run one process per value of a static setting",
        )
        _require(len(values) > 0, f"--sweep {name} has no values")
        _require(
            all(_is_number(v) and math.isfinite(v) for v in values),
            f"--sweep {name}: values must be finite numbers",
        )
        _require(len(set(values)) == len(values), f"--sweep {name} repeats a value: {list(values)}")
        reason = unused_sweep_reason(cfg.agent, name)
        _require(reason is None, f"cannot sweep {name}: {reason}")
    for point in cfg.sweep_points:  # every point must be a valid agent on its own
        try:
            cfg.agent.replace(**point)
        except ConfigError as err:
            raise ConfigError(f"sweep point {point}: {err}") from None


def parse_sweep(items: list[str] | tuple[str, ...]) -> tuple:
    """``["kappa=-0.01,0,0.01", ...]`` (``--sweep``, repeatable) -> ``(("kappa", (-0.01, 0.0, 0.01)),
    ...)``; text that is not a list of numbers raises :class:`ConfigError` in one line. Which
    fields may be swept is checked with the config (:func:`_validate_sweep`)."""
    out = []
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip().removeprefix("agent.")
        if not sep or not name:
            raise ConfigError(f"--sweep expects FIELD=V1,V2,..., got {item!r}")
        if name not in field_names() and name not in train_field_names():
            raise ConfigError(f"--sweep {name}: unknown setting; sweepable: {', '.join(SWEEPABLE_FIELDS)}")
        words = [w.strip() for w in text.split(",")]
        if not text.strip() or not all(words):
            raise ConfigError(f"--sweep {name}: expected a comma-separated list of numbers, got {text!r}")
        try:
            values = tuple(float(w) for w in words)
        except ValueError:
            raise ConfigError(f"--sweep {name}: {text!r} is not a list of numbers") from None
        out.append((name, values))
    return tuple(out)


# ---- Presets: agent hyper-parameters per (env, algo), train-loop settings per (preset, scenario) ----

INTERSECTION_ALPHA = 0.015  # fixed entropy coefficient of all four intersection agents (§8.7 there)
# Rows reserved per set for the present objects (xrl_jax.sets). Country Road's sets hold 28.9 cones on
# average (p99 47 of 100 slots, docs/set_occupancy.json); the Intersection's training buffer held 1.48
# other vehicles per observation (sd 0.87) after 3,000 quick-preset steps, three times the random-driver
# rollouts of docs/set_occupancy.json. A batch of 128 sets then leaves over 6 standard deviations of
# its total spare; docs/performance.md shows the choice.
COUNTRY_ROAD_PACKED_ROWS = 32.0
INTERSECTION_PACKED_ROWS = 2.0

# The quick preset's optimisation constants on the racing scenarios, chosen for a budget of tens of
# thousands of steps: the paper starts at α = 0.1 and moves log α slowly, so over a short run the
# entropy bonus (0.1·ln 12 per step) outweighs the reward (≤ ~0.1 per step) and the policy stays
# nearly uniform. Actor and critic rates decay to zero over the run (resolve_config); the README's
# Results section holds what these choices gave.
QUICK_RACING_OPTIMISATION = {
    "init_alpha": 0.005,
    "alpha_lr": 1e-3,
    "actor_lr": 6e-4,
    "critic_lr": 6e-4,
    "gamma": 0.98,  # 0.95 learns to drive fast but crashes; 0.99 learns to stand still
}
# The quick preset's constants on the Intersection (every agent), chosen on XDSAC over 20k steps, 4
# seeds: with the paper's fixed α = 0.015 the entropy bonus (0.015 · ln 12 ≈ 0.037 per step) matches the
# progress reward of a car at 8 m/s (0.04), and the policy stayed near uniform (entropy 2.0 of 2.48 at
# 18k steps; cars at 1-2 m/s in the evaluation); α = 0.005 with learning rates 6e-4 had it drive (5-7 m/s,
# entropy 0.9) by 15k steps. docs/quick_preset_tuning.md keeps the measurements.
QUICK_INTERSECTION_OPTIMISATION = {"init_alpha": 0.005, "actor_lr": 6e-4, "critic_lr": 6e-4}
QUICK_SIZES = {"actor_width": 64, "critic_width": 64, "fe_width": 32, "actor_depth": 2, "critic_depth": 2}
SMOKE_SIZES = dict(actor_width=16, actor_depth=2, critic_width=16, critic_depth=1, fe_width=16, pe_freqs=2)

# Train-loop settings by (preset, scenario); unset fields keep TrainConfig's defaults, which are the
# paper's racing protocol (§5.7: 1e6 steps, buffer 1e6, evaluation every 1e5 steps on 100 tracks).
# Intersection steps are multi-agent env steps (docs/carenv-intersection.md §8): every alive agent's
# transition is stored and followed by one update; paper = the released configs (§8.7 there, 2 envs
# as the reference's 2 workers).
# fmt: off
TRAIN_PRESETS: dict[tuple[str, str], dict[str, Any]] = {
    ("paper", "racing"): {},
    ("quick", "racing"): dict(
        total_steps=80_000, batch_size=128, log_interval=1_000, eval_interval=5_000,
        checkpoint_interval=10_000, warmup_steps=1_000),
    ("smoke", "racing"): dict(
        total_steps=192, num_envs=4, warmup_steps=64, batch_size=16, buffer_size=256, log_interval=64,
        eval_interval=192, checkpoint_interval=64, eval_episodes=3, train_tracks=3),
    ("paper", "intersection"): dict(
        total_steps=5_000_000, num_envs=2, warmup_steps=2_000, batch_size=512, buffer_size=15_000_000,
        log_interval=2_000, eval_interval=100_000, eval_episodes=20, checkpoint_interval=100_000,
        reinit_steps=500_001),
    ("quick", "intersection"): dict(  # the buffer keeps every agent transition (~2.7 per env step)
        total_steps=200_000, num_envs=2, warmup_steps=2_000, batch_size=128, buffer_size=600_000,
        log_interval=1_000, eval_interval=10_000, eval_episodes=10, checkpoint_interval=10_000),
    ("smoke", "intersection"): dict(
        total_steps=128, num_envs=2, warmup_steps=64, batch_size=16, buffer_size=512, log_interval=64,
        eval_interval=128, eval_episodes=2, checkpoint_interval=64),
}
# fmt: on


def _paper_agent(env: str, algo: str) -> AgentConfig:
    """§5.7 / §4.7 (country_road = the paper's racing) and, for the intersection, the released marl
    configs (§8.7 of docs/carenv-intersection.md; docs/algorithms.md Appendix A)."""
    is_x = algo in MIXTURE_ALGOS
    if env == "intersection":
        # Fixed α; lr 3e-4 (DSAC 1e-4); clip 10 but for SAC; X actors 3 × 256 per object with the
        # neutral object; 2 × 256 critics on a width-256 Deep Set without Fourier features.
        lr = 1e-4 if algo == "dsac" else 3e-4
        return AgentConfig(
            algo=algo,
            actor_depth=3 if is_x else 2,
            fe_width=256,
            fourier_scale=None,
            neutral_object=is_x,
            clip_norm=None if algo == "sac" else 10.0,
            auto_alpha=False,
            init_alpha=INTERSECTION_ALPHA,
            actor_lr=lr,
            critic_lr=lr,
            packed_rows=INTERSECTION_PACKED_ROWS,
        )
    racing = env == "country_road"
    lr = 3e-4 if (not racing and algo in CONTINUOUS_ALGOS) else 1e-4
    depth = 2 if racing else 3
    return AgentConfig(
        algo=algo,
        actor_depth=3 if is_x else depth,
        critic_depth=depth,
        feature_extractor="deepset" if racing else "flat_pe",
        actor_lr=lr,
        critic_lr=lr,
        # All four discrete configs set 1.24 explicitly; continuous ones use the −A default.
        target_entropy=1.24 if algo in DISCRETE_ALGOS else None,
        packed_rows=COUNTRY_ROAD_PACKED_ROWS if racing else None,  # Tracking's 25 points are all present
    )


def preset(name: str, env: str, algo: str) -> AgentConfig:
    """The agent of preset ``name`` for (env, algo): paper; quick = width 64 and, on the racing
    scenarios, the short-budget optimisation constants (on the Intersection, every slot computed);
    smoke = tiny networks."""
    for kind, value, choices in (("preset", name, PRESETS), ("env", env, ENVS), ("algo", algo, ALGOS)):
        _check_choice("", kind, value, choices)
    agent = _paper_agent(env, algo)
    if name == "quick":
        agent = agent.replace(**QUICK_SIZES)
        if env != "intersection":
            agent = agent.replace(**QUICK_RACING_OPTIMISATION)
        else:  # α stays fixed; 8 slots at width 64: packing cost more than it saved (docs/performance.md)
            agent = agent.replace(packed_rows=None, **QUICK_INTERSECTION_OPTIMISATION)
    elif name == "smoke":
        agent = agent.replace(**SMOKE_SIZES)
    return agent


_agent_preset = preset  # resolve_config's parameter ``preset`` (a name) shadows the function


def preset_train_fields(name: str, env: str) -> dict[str, Any]:
    return dict(TRAIN_PRESETS[(name, "intersection" if env == "intersection" else "racing")])


# ---- Text overrides (``--set KEY=VALUE``) and the resolved run ---------------------------------


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


def parse_value(cls: type, name: str, text: str) -> Any:
    """``text`` as the type of field ``name`` of ``cls`` (AgentConfig or TrainConfig): integers also
    as ``1e6``, booleans as true/false/yes/no/on/off/1/0, optional fields as ``none``."""
    hint = typing.get_type_hints(cls)[name]
    args = typing.get_args(hint)
    base = next((a for a in args if a is not type(None)), hint) if args else hint
    if type(None) in args and text.strip().lower() in ("none", "null"):
        return None
    try:
        if base is bool:
            words = {
                "true": True,
                "1": True,
                "yes": True,
                "on": True,
                "false": False,
                "0": False,
                "no": False,
                "off": False,
            }
            return words[text.strip().lower()]
        if base is int:
            value = float(text)
            if not value.is_integer():
                raise ValueError(text)
            return int(value)
        return float(text) if base is float else str(text)
    except (ValueError, KeyError):
        expected = getattr(base, "__name__", str(base))
        raise ConfigError(f"cannot parse {text!r} for {name} (expected {expected})") from None


def apply_overrides(cfg: AgentConfig, overrides: Mapping[str, Any]) -> AgentConfig:
    """Apply ``{field: value}``; string values are parsed with the field's type (for ``--set``)."""
    _check_known(overrides, field_names(), "AgentConfig")
    return cfg.replace(
        **{k: parse_value(AgentConfig, k, v) if isinstance(v, str) else v for k, v in overrides.items()}
    )


def resolve_config(
    env: str = "tracking",
    algo: str = "xsac",
    preset: str = "paper",
    num_seeds: int = 1,
    total_steps: int | None = None,
    overrides: Mapping[str, str] | None = None,
    sweep: tuple = (),
) -> TrainConfig:
    """The fully resolved config: preset, then the explicit arguments, then ``overrides``.

    ``overrides`` keys are :class:`TrainConfig` fields or :class:`AgentConfig` fields (an
    ``agent.`` prefix is accepted); values are text, parsed with the field's type. ``sweep`` is
    :func:`parse_sweep`'s result.
    """
    preset_name = preset
    for kind, value, choices in (("env", env, ENVS), ("algo", algo, ALGOS), ("preset", preset_name, PRESETS)):
        _check_choice("", kind, value, choices)
    fields = preset_train_fields(preset_name, env)
    fields.update(env=env, algo=algo, preset=preset_name, num_seeds=num_seeds, sweep=tuple(sweep))
    if total_steps is not None:
        fields["total_steps"] = total_steps
    agent_changes: dict[str, str] = {}
    train_names, agent_names = set(train_field_names()), set(field_names())
    for key, value in (overrides or {}).items():
        name = key.removeprefix("agent.")
        if name in ("env", "algo", "preset", "agent", "sweep"):
            raise ConfigError(f"{name!r} cannot be changed with --set; use --{name}")
        if key.startswith("agent.") or (name not in train_names and name in agent_names):
            if name not in agent_names:
                raise ConfigError(
                    f"unknown agent setting {name!r}; allowed: {', '.join(sorted(agent_names))}"
                )
            agent_changes[name] = value
        elif name in train_names:
            fields[name] = parse_value(TrainConfig, name, value)
        else:
            allowed = ", ".join(sorted((train_names - {"env", "algo", "preset"}) | agent_names))
            raise ConfigError(f"unknown setting {key!r}; allowed: {allowed}")
    agent = apply_overrides(_agent_preset(preset_name, env, algo), agent_changes)
    if preset_name == "quick" and env != "intersection":  # settings that follow the run's length
        if "buffer_size" not in (overrides or {}):
            # Keep every transition, as the paper's protocol does (buffer = steps = 10⁶).
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


def settings_help(width: int = 100) -> str:
    """Every ``--set`` key with its type, default and documentation, for ``run.py --help``."""
    lines = ["(defaults are the fields' own, which the presets override; § = docs/algorithms.md)"]
    for title, cls, skip in (
        (
            "run settings",
            TrainConfig,
            {"env", "algo", "preset", "agent", "num_seeds", "total_steps", "sweep"},
        ),
        ("agent settings ('agent.' prefix optional)", AgentConfig, {"algo"}),
    ):
        lines.append(f"{title}:")
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if f.name in skip:
                continue
            kind = getattr(hints[f.name], "__name__", None) or str(hints[f.name]).replace("typing.", "")
            entry = f"{f.name} ({kind}, default {f.default}): {f.metadata['help']}"
            lines += textwrap.wrap(entry, width, initial_indent="  ", subsequent_indent="      ")
    return "\n".join(lines)
