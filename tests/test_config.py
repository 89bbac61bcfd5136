"""Agent configs: the paper presets of docs/algorithms.md §5.7 / §4.7, validation with clear errors."""

import dataclasses
import math

import pytest

from xrl_jax.config import (
    ALGOS,
    ENVS,
    MAX_VEHICLES,
    PRESETS,
    AgentConfig,
    ConfigError,
    TrainConfig,
    apply_overrides,
    parse_overrides,
    parse_sweep,
    preset,
    resolve_config,
)


def test_every_preset_combination_exists():
    for name in PRESETS:
        for env in ENVS:
            for algo in ALGOS:
                assert preset(name, env, algo).algo == algo


def test_the_vehicle_slot_count_matches_the_intersection_env():
    from envs.intersection import MAX_AGENTS

    assert MAX_VEHICLES == MAX_AGENTS


@pytest.mark.parametrize(
    "env, algo, lr, actor_depth, critic_depth, extractor",
    [
        ("country_road", "sac", 1e-4, 2, 2, "deepset"),
        ("country_road", "dsac", 1e-4, 2, 2, "deepset"),
        ("country_road", "xsac", 1e-4, 3, 2, "deepset"),
        ("country_road", "xdsac", 1e-4, 3, 2, "deepset"),
        ("tracking", "sac", 3e-4, 3, 3, "flat_pe"),
        ("tracking", "dsac", 1e-4, 3, 3, "flat_pe"),
        ("tracking", "xsac", 3e-4, 3, 3, "flat_pe"),
        ("tracking", "xdsac", 1e-4, 3, 3, "flat_pe"),
    ],
)
def test_paper_table(env, algo, lr, actor_depth, critic_depth, extractor):
    cfg = preset("paper", env, algo)
    assert cfg.actor_lr == cfg.critic_lr == lr
    assert cfg.resolved_alpha_lr() == lr  # α uses the critic lr
    assert (cfg.actor_depth, cfg.critic_depth, cfg.actor_width, cfg.critic_width) == (
        actor_depth,
        critic_depth,
        256,
        256,
    )
    assert cfg.feature_extractor == extractor and cfg.fe_width == 128 and cfg.fourier_scale == 30.0
    assert (cfg.gamma, cfg.tau, cfg.init_alpha, cfg.n_critics) == (0.95, 0.005, 0.1, 2)
    assert cfg.critic_loss == "huber" and cfg.clip_norm is None and cfg.auto_alpha
    if cfg.is_mixture:
        assert cfg.kappa == 1e-3 and cfg.components_per_object == 1 and cfg.weight_depth is None
    if cfg.is_discrete:
        assert cfg.resolved_target_entropy(12) == 1.24
        assert cfg.resolved_epsilon_random() == 0.05
    else:
        assert cfg.resolved_target_entropy(3) == -3.0
        assert cfg.resolved_epsilon_random() == 0.0
    expected_log_std_min = -5.0 if algo == "xsac" else -20.0
    assert cfg.resolved_log_std_min() == expected_log_std_min


def test_target_entropy_defaults_when_unset():
    assert AgentConfig(algo="dsac").resolved_target_entropy(12) == pytest.approx(0.9 * math.log(12))
    assert AgentConfig(algo="xdsac").resolved_target_entropy(12) == pytest.approx(0.5 * math.log(12))
    assert AgentConfig(algo="xsac").resolved_target_entropy(2) == -2.0
    # an explicit 0.0 is honoured (the reference's truthiness quirk is not reproduced)
    assert AgentConfig(algo="xdsac", target_entropy=0.0).resolved_target_entropy(12) == 0.0


def test_smoke_preset_is_tiny_with_paper_optimisation():
    cfg = preset("smoke", "tracking", "xsac")
    assert cfg.actor_width < 64 and cfg.actor_lr == 3e-4 and cfg.gamma == 0.95


def test_quick_racing_rows_train_longer_and_widen_tracking_but_xdsac():
    """Tracking's and Country Road's own rows refine the racing one (240k and 320k steps, evaluated
    every 40k); the rest of the racing row stays. Width 128 for every Tracking agent but XDSAC, which
    passed the controller at width 64; Country Road keeps width 64."""
    tracking = {algo: resolve_config("tracking", algo, "quick", num_seeds=1) for algo in ALGOS}
    country_road = {algo: resolve_config("country_road", algo, "quick", num_seeds=1) for algo in ALGOS}
    assert {cfg.total_steps for cfg in tracking.values()} == {240_000}
    assert {cfg.total_steps for cfg in country_road.values()} == {320_000}
    assert {cfg.eval_interval for cfg in [*tracking.values(), *country_road.values()]} == {40_000}
    assert country_road["dsac"].batch_size == tracking["sac"].batch_size == 128  # the racing row
    assert country_road["dsac"].checkpoint_interval == 10_000
    widths = {algo: (cfg.agent.actor_width, cfg.agent.critic_width) for algo, cfg in tracking.items()}
    assert widths == {"sac": (128, 128), "dsac": (128, 128), "xsac": (128, 128), "xdsac": (64, 64)}
    assert {cfg.agent.actor_width for cfg in country_road.values()} == {64}


@pytest.mark.parametrize("env", ["country_road", "tracking"])
@pytest.mark.parametrize("algo", ALGOS)
def test_quick_racing_agents_differ_from_the_paper_only_in_sizes_and_optimisation(env, algo):
    """The quick preset shrinks the networks and retunes the optimiser on the racing scenarios, and
    nothing else: the Intersection's settings (every slot computed, no packing) must not leak in."""
    quick, paper = preset("quick", env, algo), preset("paper", env, algo)
    fields = [f.name for f in dataclasses.fields(AgentConfig)]
    changed = {name for name in fields if getattr(quick, name) != getattr(paper, name)}
    sizes = {"actor_width", "critic_width", "fe_width", "actor_depth", "critic_depth"}
    optimisation = {"init_alpha", "alpha_lr", "actor_lr", "critic_lr", "gamma"}
    assert changed <= sizes | optimisation, changed - sizes - optimisation
    assert (quick.gamma, quick.alpha_lr) == (0.98, 1e-3)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"algo": "a2c"}, "unknown algo 'a2c'; allowed: sac, dsac, xsac, xdsac, ppo, dppo, xppo, xdppo"),
        ({"gae_lambda": 1.5}, "gae_lambda must lie in \\[0, 1\\]"),
        ({"ppo_minibatches": 0}, "ppo_minibatches must be a positive integer"),
        ({"clip_eps": 0.0}, "clip_eps must be positive"),
        ({"actor_lr": -1e-4}, "actor_lr must be positive"),
        ({"critic_lr": 0.0}, "critic_lr must be positive"),
        ({"alpha_lr": float("nan")}, "alpha_lr must be a finite number"),
        ({"gamma": 1.5}, "gamma must lie in"),
        ({"tau": 0.0}, "tau must lie in"),
        ({"kappa": float("inf")}, "kappa must be a finite number"),
        ({"init_alpha": -0.1}, "init_alpha must be positive"),
        ({"actor_width": 0}, "actor_width must be a positive integer"),
        ({"feature_extractor": "cnn"}, "allowed: deepset, flat_pe"),
        ({"critic_loss": "l1"}, "allowed: huber, l2"),
        ({"truncation": "ignore"}, "allowed: drop, bootstrap, terminal"),
        ({"algo": "xdsac", "truncation": "terminal"}, "truncation=terminal applies to the on-policy family"),
        ({"algo": "xsac", "actor_depth": 2, "weight_depth": 3}, "weight_depth"),
        ({"algo": "xdsac", "duelling": False}, "duelling"),
        ({"epsilon_random": 2.0}, "epsilon_random"),
        ({"log_std_min": 3.0}, "log_std_min"),
        ({"algo": "sac", "neutral_object": True}, "neutral_object only applies"),
        ({"algo": "dsac", "neutral_object": True}, "neutral_object only applies"),
        ({"algo": "xsac", "neutral_object": 1}, "neutral_object must be a bool"),
        ({"algo": "xsac", "neutral_flag": True}, "neutral_flag needs neutral_object"),
        ({"fe_item_depth": 0}, "fe_item_depth must be a positive integer"),
        ({"fe_set_depth": 0}, "fe_set_depth must be a positive integer"),
        ({"lr_decay_updates": -1}, "lr_decay_updates must be a non-negative integer"),
        ({"lr_decay_updates": 2.5}, "lr_decay_updates must be a non-negative integer"),
    ],
)
def test_validation_errors_are_clear(changes, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        AgentConfig(**changes)


def test_negative_kappa_is_allowed_for_the_fig8_sweep():
    assert AgentConfig(algo="xdsac", kappa=-1e-3).kappa == -1e-3


def test_unknown_preset_env_or_field():
    with pytest.raises(ValueError, match="unknown preset 'huge'; allowed: paper, quick, smoke"):
        preset("huge", "tracking", "sac")
    with pytest.raises(ValueError, match="unknown scenario 'moon'; known: country_road"):
        preset("paper", "moon", "sac")
    with pytest.raises(ValueError, match="unknown algo 'td3'; allowed"):
        preset("paper", "tracking", "td3")
    with pytest.raises(ValueError, match="unknown field"):
        preset("paper", "tracking", "sac").replace(learning_rate=1.0)


def test_overrides_from_text():
    cfg = apply_overrides(
        preset("paper", "country_road", "xdsac"),
        {
            "kappa": "-0.01",
            "auto_alpha": "false",
            "clip_norm": "none",
            "actor_width": "64",
            "critic_loss": "l2",
        },
    )
    assert cfg.kappa == -0.01 and cfg.auto_alpha is False and cfg.clip_norm is None
    assert cfg.actor_width == 64 and cfg.critic_loss == "l2"
    with pytest.raises(ValueError, match="cannot parse"):
        apply_overrides(cfg, {"actor_width": "wide"})
    with pytest.raises(ValueError, match="unknown field"):
        apply_overrides(cfg, {"lr": "1"})
    with pytest.raises(ValueError, match="actor_lr must be positive"):
        apply_overrides(cfg, {"actor_lr": "-1"})


def test_a_setting_given_twice_is_refused_rather_than_the_last_value_winning():
    assert parse_overrides(["gamma=0.9", "agent.kappa=0.1"]) == {"gamma": "0.9", "agent.kappa": "0.1"}
    for items in (
        ["gamma=0.9", "gamma=0.8"],
        ["gamma=0.9", "agent.gamma=0.9"],
        ["agent.gamma=1", " gamma =1"],
    ):
        with pytest.raises(ConfigError, match="--set gamma is given twice") as info:
            parse_overrides(items)
        assert repr(items[0]) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="--set num_envs is given twice"):
        parse_overrides(["num_envs=2", "batch_size=16", "num_envs=4"])


def test_configs_are_frozen_and_hashable():
    cfg = preset("paper", "tracking", "xsac")
    with pytest.raises(AttributeError):
        cfg.kappa = 0.5  # type: ignore[misc]
    assert hash(cfg) == hash(preset("paper", "tracking", "xsac"))


@pytest.mark.parametrize(
    "algo, lr, actor_depth, clip_norm",
    [("sac", 3e-4, 2, None), ("dsac", 1e-4, 2, 10.0), ("xsac", 3e-4, 3, 10.0), ("xdsac", 3e-4, 3, 10.0)],
)
def test_intersection_paper_table(algo, lr, actor_depth, clip_norm):
    """docs/carenv-intersection.md §8.7; the baseline actors' depth is unspecified there → the critics' 2."""
    cfg = preset("paper", "intersection", algo)
    assert "intersection" in ENVS
    assert cfg.actor_lr == cfg.critic_lr == lr and cfg.clip_norm == clip_norm
    assert (cfg.actor_width, cfg.actor_depth, cfg.critic_width, cfg.critic_depth) == (
        256,
        actor_depth,
        256,
        2,
    )
    assert cfg.auto_alpha is False and cfg.init_alpha == 0.015  # fixed α for all four agents
    assert (cfg.gamma, cfg.tau, cfg.n_critics, cfg.critic_loss) == (0.95, 0.005, 2, "huber")
    assert cfg.feature_extractor == "deepset" and cfg.fe_width == 256 and cfg.fourier_scale is None
    assert (cfg.fe_item_depth, cfg.fe_set_depth) == (3, 2)
    assert cfg.neutral_object is cfg.is_mixture and cfg.duelling
    if cfg.is_mixture:
        assert cfg.kappa == 1e-3 and cfg.components_per_object == 1 and cfg.weight_depth is None
    assert cfg.resolved_epsilon_random() == (0.05 if cfg.is_discrete else 0.0)
    smoke = preset("smoke", "intersection", algo)
    assert smoke.actor_width < 64 and smoke.fe_width < 64
    for field in ("neutral_object", "auto_alpha", "init_alpha", "clip_norm", "actor_lr", "fourier_scale"):
        assert getattr(smoke, field) == getattr(cfg, field)


def test_racing_and_tracking_presets_keep_their_deep_set_and_no_neutral_object():
    for env in ("country_road", "tracking"):
        for algo in ALGOS:
            cfg = preset("paper", env, algo)
            assert (cfg.fe_item_depth, cfg.fe_set_depth, cfg.neutral_object) == (3, 2, False)
            assert cfg.auto_alpha and cfg.clip_norm is None


def test_one_parser_for_every_setting():
    """Before, two parsers disagreed: total_steps=1e6 was accepted and lr_decay_updates=1e6 refused."""
    from xrl_jax.config import TrainConfig, parse_value

    assert parse_value(TrainConfig, "total_steps", "1e6") == 1_000_000
    assert parse_value(AgentConfig, "lr_decay_updates", "1e6") == 1_000_000
    assert parse_value(AgentConfig, "weight_depth", "none") is None
    assert parse_value(AgentConfig, "duelling", "off") is False
    for cls, name, text in ((TrainConfig, "num_envs", "2.5"), (AgentConfig, "gamma", "fast"),
                            (AgentConfig, "auto_alpha", "maybe")):  # fmt: skip
        with pytest.raises(ValueError, match=f"cannot parse '{text}' for {name}"):
            parse_value(cls, name, text)


def test_the_cli_help_documents_every_setting_from_the_fields():
    import dataclasses

    from xrl_jax.config import TrainConfig, settings_help

    text = settings_help()
    settable = [f for f in dataclasses.fields(TrainConfig) if f.name not in
                ("env", "algo", "preset", "agent", "num_seeds", "total_steps", "sweep")]  # fmt: skip
    for field in [*settable, *(f for f in dataclasses.fields(AgentConfig) if f.name != "algo")]:
        assert f"  {field.name} (" in text and field.metadata["help"].split()[0] in text


def test_configs_written_before_neutral_flag_keep_their_flagged_neutral_row():
    """Runs written before ``neutral_flag`` existed put 1 into the neutral row's present column; their
    config.json restores that, so an old agent sees the inputs it was trained on."""
    cfg = resolve_config("intersection", "xsac", "smoke")
    old = cfg.to_dict()
    del old["agent"]["neutral_flag"]
    assert TrainConfig.from_dict(old).agent.neutral_flag is True
    assert TrainConfig.from_dict(cfg.to_dict()).agent.neutral_flag is False  # the original's row


@pytest.mark.parametrize("key", ["gamma", "agent.gamma"])
def test_a_setting_both_swept_and_set_is_refused(key):
    """The sweep's values won and config.json held the --set value beside them; now: one line."""
    with pytest.raises(ConfigError, match=r"^gamma is both swept \(--sweep\) and set \(--set\)"):
        sweep = parse_sweep(["gamma=0.95,0.99"])
        resolve_config("tracking", "xsac", "smoke", overrides={key: "0.9"}, sweep=sweep)


def test_the_host_only_settings_are_stripped_in_one_place():
    """The checkpoints' fingerprint and the trainer's cache key both start from results_fields: a
    host-only setting changes neither, any other setting changes the fields."""
    from xrl_jax.config import HOST_ONLY_FIELDS

    cfg = resolve_config("tracking", "xdsac", "smoke")
    host = cfg.replace(max_group_size=3, memory_budget_gb=1.5, checkpoint_minutes=0.0, num_devices=2)
    assert not set(HOST_ONLY_FIELDS) & set(cfg.results_fields())
    assert host.results_fields() == cfg.results_fields()
    assert host.without_host_settings() == cfg.without_host_settings() == cfg
    assert cfg.replace(batch_size=8).results_fields() != cfg.results_fields()
