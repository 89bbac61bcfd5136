"""The agent's configuration (docs/algorithms.md §5.7): architecture sizes and switches (static: they
fix shapes and control flow) and optimisation constants (traced: copied into the agent state by
:func:`xrl_jax.agents.make_agent` so that sweeps can ``vmap`` over them; ``TRACED_FIELDS``),
validated on construction."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from xrl_jax.config.checks import check_choice, check_known, is_int, is_number, require, setting
from xrl_jax.config.names import (
    ACTOR_TWIN,
    ALGOS,
    CRITIC_LOSSES,
    DISCRETE_ALGOS,
    FEATURE_EXTRACTORS,
    LOG_STD_MAX,
    MIXTURE_ALGOS,
    MIXTURE_LOG_STD_MIN,
    ON_POLICY_ALGOS,
    SAC_LOG_STD_MIN,
    TRUNCATION_MODES,
)


@dataclasses.dataclass(frozen=True)
class AgentConfig:
    """Hyper-parameters of one agent; defaults are the common values of §5.7 (racing SAC shapes)."""

    algo: str = setting("sac", "agent: sac, dsac, xsac, xdsac; xrl_jax.ppo: ppo, dppo, xppo, xdppo")
    # --- architecture (static) ---
    actor_width: int = setting(256, "actor hidden width")
    actor_depth: int = setting(2, "actor hidden layers")
    critic_width: int = setting(256, "critic hidden width")
    critic_depth: int = setting(2, "critic hidden layers")
    n_critics: int = setting(2, "critics in the ensemble (the minimum is the target)")
    feature_extractor: str = setting("deepset", "critic (and baseline actor) extractor: deepset | flat_pe")
    fe_width: int = setting(128, "Deep Set width and state-encoder width")
    fe_item_depth: int = setting(3, "Deep Set item-encoder layers (Fourier / first Dense included)")
    fe_set_depth: int = setting(2, "Deep Set set-encoder layers after the sum")
    fourier_scale: float | None = setting(30.0, "learned Fourier features scale b; none = plain Dense")
    pe_freqs: int = setting(4, "positional-encoding frequencies of the tracking extractor")
    duelling: bool = setting(True, "duelling discrete critics (XDSAC always, §2.4)")
    components_per_object: int = setting(1, "mixture components per object (X agents)")
    neutral_object: bool = setting(
        False, "X agents: an always-present all-zero object (a state-only component, Appendix A)"
    )
    neutral_flag: bool = setting(False, "the neutral row's present column: 0 as the original, or 1 (true)")
    weight_depth: int | None = setting(None, "φ_d: hidden layer feeding the mixture weights; none = last")
    uniform_mixture: bool = setting(False, "ablation §3.1.6: uniform weights over present objects")
    packed_rows: float | None = setting(
        None,
        "per-object layers on the present objects only, packed into this many rows per set on average "
        "over a call (more present objects: that call computes on every slot); none = every slot "
        "(docs/performance.md)",
    )
    dense_sets: bool = setting(False, "per-object layers on every slot even with packed_rows (comparison)")
    log_std_min: float | None = setting(None, "lower log σ bound; none = SAC −20, XSAC −5 (§7.1)")
    log_std_max: float = setting(LOG_STD_MAX, "upper log σ bound")
    # --- optimisation (static switches) ---
    critic_loss: str = setting("huber", "critic loss: huber (δ = 1, every paper config) | l2")
    clip_norm: float | None = setting(None, "global gradient-norm clipping; none = off")
    auto_alpha: bool = setting(True, "learn the entropy coefficient α")
    epsilon_random: float | None = setting(None, "random-action probability; none = 0.05 discrete, 0")
    truncation: str = setting(
        "drop",
        "truncated transitions: drop (paper) | bootstrap | terminal (on-policy only: the time limit valued "
        "as an end, as PureJaxRL and rejax take it); the on-policy family keeps every step and bootstraps "
        "under drop and bootstrap",
    )
    lr_decay_updates: int = setting(0, "linear decay of the learning rates to zero over this many updates")
    # --- optimisation (traced) ---
    actor_lr: float = setting(1e-4, "actor learning rate")
    critic_lr: float = setting(1e-4, "critic learning rate")
    alpha_lr: float | None = setting(None, "α learning rate; none = critic_lr (§1.3)")
    gamma: float = setting(0.95, "discount")
    tau: float = setting(0.005, "Polyak factor of the target critics")
    kappa: float = setting(1e-3, "mixture-entropy weight κ of eq. 10 (X agents; may be negative)")
    init_alpha: float = setting(0.1, "initial (or fixed) entropy coefficient α")
    target_entropy: float | None = setting(None, "none = −A (continuous), 0.9 ln N (DSAC), 0.5 ln N (XDSAC)")
    # --- the on-policy family (ppo, dppo, xppo, xdppo; xrl_jax.ppo) ---
    rollout_steps: int = setting(128, "PPO: vector steps per rollout, before its epochs of updates")
    ppo_epochs: int = setting(4, "PPO: passes over each rollout")
    ppo_minibatches: int = setting(4, "PPO: minibatches per pass")
    clip_eps: float = setting(0.2, "PPO: clipping ε of the probability ratio")
    value_clip_eps: float | None = setting(None, "PPO: clipping of the value's move per rollout; none = off")
    ent_coef: float = setting(0.01, "PPO: weight of the policy-entropy bonus")
    gae_lambda: float = setting(0.95, "PPO: λ of generalised advantage estimation")

    def __post_init__(self) -> None:
        _validate_agent(self)

    @property
    def is_discrete(self) -> bool:
        return ACTOR_TWIN.get(self.algo, self.algo) in DISCRETE_ALGOS

    @property
    def is_mixture(self) -> bool:
        return ACTOR_TWIN.get(self.algo, self.algo) in MIXTURE_ALGOS

    @property
    def is_on_policy(self) -> bool:
        return self.algo in ON_POLICY_ALGOS

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
        check_known(changes, field_names(), "AgentConfig")
        return dataclasses.replace(self, **changes)


def field_names() -> list[str]:
    return [f.name for f in dataclasses.fields(AgentConfig)]


def _validate_agent(cfg: AgentConfig) -> None:
    def check(condition: bool, message: str) -> None:
        require(condition, f"AgentConfig: {message}")

    for name, choices in (
        ("algo", (*ALGOS, *ON_POLICY_ALGOS)),
        ("feature_extractor", FEATURE_EXTRACTORS),
        ("critic_loss", CRITIC_LOSSES),
        ("truncation", TRUNCATION_MODES),
    ):
        check_choice("AgentConfig: ", name, getattr(cfg, name), choices)
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
        "rollout_steps",
        "ppo_epochs",
        "ppo_minibatches",
    ):
        check(is_int(getattr(cfg, name), 1), f"{name} must be a positive integer, got {getattr(cfg, name)!r}")
    for name in ("lr_decay_updates", "pe_freqs"):
        check(
            is_int(getattr(cfg, name), 0),
            f"{name} must be a non-negative integer, got {getattr(cfg, name)!r}",
        )
    for name in ("duelling", "neutral_object", "neutral_flag", "uniform_mixture", "auto_alpha", "dense_sets"):
        check(isinstance(getattr(cfg, name), bool), f"{name} must be a bool, got {getattr(cfg, name)!r}")
    if cfg.weight_depth is not None:
        check(
            is_int(cfg.weight_depth, 1) and cfg.weight_depth <= cfg.actor_depth,
            f"weight_depth (φ_d) must lie in 1..actor_depth={cfg.actor_depth}, got {cfg.weight_depth}",
        )
    check(
        cfg.truncation != "terminal" or cfg.is_on_policy,
        f"truncation=terminal applies to the on-policy family (ppo, dppo, xppo, xdppo); {cfg.algo} drops "
        "or bootstraps a truncated transition",
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
    positive += ["packed_rows", "clip_eps", "value_clip_eps"]
    signed = ["kappa", "gamma", "tau", "target_entropy", "log_std_max", "log_std_min", "ent_coef"]
    for name in [*signed, *positive]:
        value = getattr(cfg, name)
        if value is None:
            continue
        check(is_number(value), f"{name} must be a finite number, got {value!r}")
        check(name not in positive or value > 0, f"{name} must be positive, got {value}")
    check(0.0 <= cfg.gamma <= 1.0, f"gamma must lie in [0, 1], got {cfg.gamma}")
    check(0.0 < cfg.tau <= 1.0, f"tau must lie in (0, 1], got {cfg.tau}")
    check(is_number(cfg.gae_lambda) and 0.0 <= cfg.gae_lambda <= 1.0,
          f"gae_lambda must lie in [0, 1], got {cfg.gae_lambda!r}")  # fmt: skip
    if cfg.epsilon_random is not None:
        check(
            is_number(cfg.epsilon_random) and 0.0 <= cfg.epsilon_random <= 1.0,
            f"epsilon_random must lie in [0, 1], got {cfg.epsilon_random}",
        )
    low = cfg.resolved_log_std_min()
    check(low < cfg.log_std_max, f"log_std_min ({low}) must be below log_std_max ({cfg.log_std_max})")
