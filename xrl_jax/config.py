"""Typed agent configurations and the paper presets (docs/algorithms.md §5.7).

An :class:`AgentConfig` holds everything an agent needs: architecture sizes and switches (static:
they fix shapes and control flow) and optimisation constants (traced: copied into the agent state
by :func:`xrl_jax.agents.make_agent` so that sweeps can ``vmap`` over them; see
:data:`TRACED_FIELDS`). Configs are frozen and validated on construction, so a bad value fails
where it is written rather than deep inside a jitted update.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any

ALGOS = ("sac", "dsac", "xsac", "xdsac")
ENVS = ("country_road", "tracking", "intersection")
PRESETS = ("paper", "smoke")
CONTINUOUS_ALGOS = ("sac", "xsac")
DISCRETE_ALGOS = ("dsac", "xdsac")
MIXTURE_ALGOS = ("xsac", "xdsac")
FEATURE_EXTRACTORS = ("deepset", "flat_pe")  # names of xrl_jax.networks.make_extractor
CRITIC_LOSSES = ("huber", "l2")
TRUNCATION_MODES = ("drop", "bootstrap")

# Fields that become traced leaves of the agent state (``AgentState.hparams``; can differ per vmapped
# seed / sweep member). init_alpha only sets the initial ``AgentState.log_alpha``, itself a traced leaf.
TRACED_FIELDS = ("actor_lr", "critic_lr", "alpha_lr", "gamma", "tau", "kappa", "target_entropy")


def _error(message: str) -> ValueError:
    return ValueError(f"AgentConfig: {message}")


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Hyper-parameters of one agent. Defaults are the common values of §5.7 (racing SAC shapes).

    Static (shape / control flow): algo, widths, depths, extractor choice, number of critics,
    components per object, branch depth, log σ bounds, loss kind, clipping, exploration ε,
    auto-α switch, truncation handling, learning-rate decay length. Traced: see :data:`TRACED_FIELDS`.
    """

    algo: str = "sac"
    # --- architecture (static) ---
    actor_width: int = 256
    actor_depth: int = 2
    critic_width: int = 256
    critic_depth: int = 2
    n_critics: int = 2
    feature_extractor: str = "deepset"  # critic FE (and the baseline actors' FE): deepset | flat_pe
    fe_width: int = 128  # Deep Set width W and state-encoder width
    fe_item_depth: int = 3  # Deep Set item-encoder layers (the Fourier / first Dense layer included)
    fe_set_depth: int = 2  # Deep Set set-encoder layers after the sum
    fourier_scale: float | None = 30.0  # learned Fourier features scale b; None = plain Dense first layer
    pe_freqs: int = 4  # positional-encoding frequencies of the tracking extractor
    duelling: bool = True  # discrete critics only; XDSAC always duelling (§2.4)
    components_per_object: int = 1  # C; X agents only
    # X agents only: prepend an always-present all-zero "neutral" object (a state-only component), as the
    # multi-agent intersection actors do (Appendix A); the explanation then has O + 1 objects.
    neutral_object: bool = False
    weight_depth: int | None = None  # φ_d (paper Table I): 1-based hidden layer feeding φ; None = last
    uniform_mixture: bool = False  # ablation of §3.1.6: no φ, uniform weights over present objects
    log_std_min: float | None = None  # None = per-algo default: SAC −20, XSAC −5 (§7.1)
    log_std_max: float = 2.0
    # --- optimisation (static switches) ---
    critic_loss: str = "huber"  # §1.1: Huber(δ=1) in every paper config
    clip_norm: float | None = None  # global-norm clipping (none in racing/tracking, §1.4)
    auto_alpha: bool = True
    epsilon_random: float | None = None  # None = 0.05 for discrete agents, 0 for continuous (§5.1)
    truncation: str = "drop"  # how the loss treats `truncated` transitions (see agents.py)
    # Linear decay of every learning rate to zero over this many updates (0 = constant, as the paper).
    # Not in the paper configs (§5.7); the quick preset uses it (README, Results, for what it changed there).
    lr_decay_updates: int = 0
    # --- optimisation (traced) ---
    actor_lr: float = 1e-4
    critic_lr: float = 1e-4
    alpha_lr: float | None = None  # None = critic lr (§1.3)
    gamma: float = 0.95
    tau: float = 0.005
    kappa: float = 1e-3  # X agents only; negative values are allowed (Fig. 8 sweeps them)
    init_alpha: float = 0.1
    target_entropy: float | None = None  # None = −A (continuous), 0.9 ln N (DSAC), 0.5 ln N (XDSAC)

    def __post_init__(self) -> None:
        _validate(self)

    # ---- derived values ---------------------------------------------------------------------
    @property
    def is_discrete(self) -> bool:
        return self.algo in DISCRETE_ALGOS

    @property
    def is_mixture(self) -> bool:
        return self.algo in MIXTURE_ALGOS

    def resolved_log_std_min(self) -> float:
        if self.log_std_min is not None:
            return float(self.log_std_min)
        return -5.0 if self.algo == "xsac" else -20.0

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
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise _error(f"unknown field(s) {unknown}; valid fields: {field_names()}")
        return dataclasses.replace(self, **changes)


def field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(AgentConfig)]


def _validate(cfg: AgentConfig) -> None:
    if cfg.algo not in ALGOS:
        raise _error(f"unknown algo {cfg.algo!r}; valid algos: {', '.join(ALGOS)}")
    if cfg.feature_extractor not in FEATURE_EXTRACTORS:
        raise _error(
            f"unknown feature_extractor {cfg.feature_extractor!r}; valid: {', '.join(FEATURE_EXTRACTORS)}"
        )
    if cfg.critic_loss not in CRITIC_LOSSES:
        raise _error(f"unknown critic_loss {cfg.critic_loss!r}; valid: {', '.join(CRITIC_LOSSES)}")
    if cfg.truncation not in TRUNCATION_MODES:
        raise _error(f"unknown truncation {cfg.truncation!r}; valid: {', '.join(TRUNCATION_MODES)}")
    for name in (
        "actor_width",
        "actor_depth",
        "critic_width",
        "critic_depth",
        "fe_width",
        "fe_item_depth",
        "fe_set_depth",
    ):
        value = getattr(cfg, name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise _error(f"{name} must be a positive integer, got {value!r}")
    if not isinstance(cfg.n_critics, int) or cfg.n_critics < 1:
        raise _error(f"n_critics must be a positive integer, got {cfg.n_critics!r}")
    if not isinstance(cfg.components_per_object, int) or cfg.components_per_object < 1:
        raise _error(f"components_per_object must be a positive integer, got {cfg.components_per_object!r}")
    decay = cfg.lr_decay_updates
    if not isinstance(decay, int) or isinstance(decay, bool) or decay < 0:
        raise _error(f"lr_decay_updates must be a non-negative integer, got {cfg.lr_decay_updates!r}")
    if not isinstance(cfg.pe_freqs, int) or cfg.pe_freqs < 0:
        raise _error(f"pe_freqs must be a non-negative integer, got {cfg.pe_freqs!r}")
    if cfg.weight_depth is not None and not 1 <= cfg.weight_depth <= cfg.actor_depth:
        raise _error(
            f"weight_depth (φ_d) must lie in 1..actor_depth={cfg.actor_depth}, got {cfg.weight_depth}"
        )
    if not isinstance(cfg.neutral_object, bool):
        raise _error(f"neutral_object must be a bool, got {cfg.neutral_object!r}")
    if cfg.neutral_object and not cfg.is_mixture:
        raise _error(
            f"neutral_object only applies to the mixture actors (xsac, xdsac); {cfg.algo} has no object slots"
        )
    if cfg.algo == "xdsac" and not cfg.duelling:
        raise _error(
            "XDSAC always uses a duelling critic (docs/algorithms.md §2.4); duelling=False is only for DSAC"
        )
    for name in ("actor_lr", "critic_lr"):
        _check_finite(name, getattr(cfg, name), positive=True)
    if cfg.alpha_lr is not None:
        _check_finite("alpha_lr", cfg.alpha_lr, positive=True)
    _check_finite("init_alpha", cfg.init_alpha, positive=True)
    _check_finite("kappa", cfg.kappa)
    if cfg.target_entropy is not None:
        _check_finite("target_entropy", cfg.target_entropy)
    _check_finite("gamma", cfg.gamma)
    if not 0.0 <= cfg.gamma <= 1.0:
        raise _error(f"gamma must lie in [0, 1], got {cfg.gamma}")
    _check_finite("tau", cfg.tau)
    if not 0.0 < cfg.tau <= 1.0:
        raise _error(f"tau must lie in (0, 1], got {cfg.tau}")
    if cfg.clip_norm is not None:
        _check_finite("clip_norm", cfg.clip_norm, positive=True)
    if cfg.epsilon_random is not None and not 0.0 <= cfg.epsilon_random <= 1.0:
        raise _error(f"epsilon_random must lie in [0, 1], got {cfg.epsilon_random}")
    if cfg.fourier_scale is not None:
        _check_finite("fourier_scale", cfg.fourier_scale, positive=True)
    lo = cfg.resolved_log_std_min()
    if not lo < cfg.log_std_max:
        raise _error(f"log_std_min ({lo}) must be below log_std_max ({cfg.log_std_max})")


def _check_finite(name: str, value: Any, positive: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _error(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise _error(f"{name} must be positive, got {value}")


# ------------------------------------------------------------------------------------------------
# Presets
# ------------------------------------------------------------------------------------------------


def _paper(env: str, algo: str) -> AgentConfig:
    """The resolved configs of §5.7 / §4.7 (country_road = the paper's racing) and, for the multi-agent
    intersection, the released marl configs (docs/carenv-intersection.md §8.7,
    docs/algorithms.md Appendix A)."""
    if env == "intersection":
        return _paper_intersection(algo)
    racing = env == "country_road"
    is_x = algo in MIXTURE_ALGOS
    lr = 3e-4 if (not racing and algo in CONTINUOUS_ALGOS) else 1e-4
    depth = 2 if racing else 3
    return AgentConfig(
        algo=algo,
        actor_width=256,
        actor_depth=3 if is_x else depth,
        critic_width=256,
        critic_depth=depth,
        feature_extractor="deepset" if racing else "flat_pe",
        fe_width=128,
        fourier_scale=30.0,
        pe_freqs=4,
        duelling=True,
        components_per_object=1,
        weight_depth=None,
        actor_lr=lr,
        critic_lr=lr,
        gamma=0.95,
        tau=0.005,
        kappa=1e-3,
        init_alpha=0.1,
        # All four discrete configs set 1.24 explicitly; continuous ones use the −A default.
        target_entropy=1.24 if algo in DISCRETE_ALGOS else None,
    )


# Intersection entropy coefficient: fixed for all four agents (docs/carenv-intersection.md §8.7).
INTERSECTION_ALPHA = 0.015


def _paper_intersection(algo: str) -> AgentConfig:
    """Multi-agent intersection (docs/carenv-intersection.md §8.7).

    Fixed α = 0.015 (no α learning, so the target entropy is unused); lr 3e-4 (DSAC 1e-4); global-norm
    clip 10 for DSAC / XDSAC / XSAC and none for SAC; X actors 3 × 256 per object with the neutral object;
    critics 2 × 256 (duelling for the discrete ones) on a Deep Set of width 256 without Fourier features
    (item encoder 3 layers, set encoder 2) ⊕ Dense(256) of the state. The baseline actors' MLP depth is
    not given there; they use the critics' 2 × 256 on their own copy of that extractor.
    """
    is_x = algo in MIXTURE_ALGOS
    lr = 1e-4 if algo == "dsac" else 3e-4
    return AgentConfig(
        algo=algo,
        actor_width=256,
        actor_depth=3 if is_x else 2,
        critic_width=256,
        critic_depth=2,
        feature_extractor="deepset",
        fe_width=256,
        fe_item_depth=3,
        fe_set_depth=2,
        fourier_scale=None,
        duelling=True,
        components_per_object=1,
        neutral_object=is_x,
        weight_depth=None,
        clip_norm=None if algo == "sac" else 10.0,
        auto_alpha=False,
        init_alpha=INTERSECTION_ALPHA,
        actor_lr=lr,
        critic_lr=lr,
        gamma=0.95,
        tau=0.005,
        kappa=1e-3,
        target_entropy=None,
    )


def _smoke(env: str, algo: str) -> AgentConfig:
    """Tiny networks with the paper's optimisation constants: for tests and CLI smoke runs."""
    return _paper(env, algo).replace(
        actor_width=16,
        actor_depth=2,
        critic_width=16,
        critic_depth=1,
        fe_width=16,
        pe_freqs=2,
    )


_PRESET_BUILDERS = {"paper": _paper, "smoke": _smoke}


def preset(name: str, env: str, algo: str) -> AgentConfig:
    """The named preset for (env, algo); unknown names raise with the valid choices."""
    if name not in _PRESET_BUILDERS:
        raise ValueError(f"unknown preset {name!r}; valid presets: {', '.join(PRESETS)}")
    if env not in ENVS:
        raise ValueError(f"unknown env {env!r}; valid envs: {', '.join(ENVS)}")
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; valid algos: {', '.join(ALGOS)}")
    return _PRESET_BUILDERS[name](env, algo)


def paper_config(env: str, algo: str) -> AgentConfig:
    """Shortcut for ``preset("paper", env, algo)``."""
    return preset("paper", env, algo)


PAPER: dict[tuple[str, str], AgentConfig] = {(e, a): _paper(e, a) for e in ENVS for a in ALGOS}


# ------------------------------------------------------------------------------------------------
# Overrides from text (CLI ``--set key=value``)
# ------------------------------------------------------------------------------------------------


def _parse_value(name: str, text: str) -> Any:
    hint = typing.get_type_hints(AgentConfig)[name]
    args = typing.get_args(hint)
    allows_none = type(None) in args
    base = next((a for a in args if a is not type(None)), hint) if args else hint
    if allows_none and text.strip().lower() in ("none", "null"):
        return None
    try:
        if base is bool:
            lowered = text.strip().lower()
            if lowered in ("true", "1", "yes", "on"):
                return True
            if lowered in ("false", "0", "no", "off"):
                return False
            raise ValueError(text)
        if base is int:
            return int(text)
        if base is float:
            return float(text)
        return str(text)
    except ValueError:
        raise _error(f"cannot parse {text!r} for field {name!r} of type {hint}") from None


def apply_overrides(cfg: AgentConfig, overrides: dict[str, Any]) -> AgentConfig:
    """Apply ``{field: value}``; string values are parsed with the field's type (for ``--set``)."""
    known = set(field_names())
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise _error(f"unknown field(s) {unknown}; valid fields: {sorted(known)}")
    parsed = {k: _parse_value(k, v) if isinstance(v, str) else v for k, v in overrides.items()}
    return cfg.replace(**parsed)
