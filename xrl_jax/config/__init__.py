"""Every configuration of xrl-jax in one jax-free package: the names, the two config dataclasses, the
presets as tables, and the one typed parser behind ``--set`` (docs/algorithms.md §5.7).

* :class:`AgentConfig` (:mod:`~xrl_jax.config.agent`): architecture sizes and switches (static: they
  fix shapes and control flow) and optimisation constants (traced: copied into the agent state by
  :func:`xrl_jax.agents.make_agent` so that sweeps can ``vmap`` over them; :data:`TRACED_FIELDS`).
* :class:`TrainConfig` (:mod:`~xrl_jax.config.train`): everything else about a run; it holds its
  :class:`AgentConfig` and validates its sweep.
* :func:`resolve_config` (:mod:`~xrl_jax.config.resolve`): preset (:mod:`~xrl_jax.config.presets`),
  explicit arguments, then ``--set`` overrides (:mod:`~xrl_jax.config.overrides`), validated.
* :data:`SCENARIOS` (:mod:`~xrl_jax.config.scenarios`): each scenario's facts in one table
  (observation layout, multi-agent, reported metrics, yardstick).
* :mod:`~xrl_jax.config.names`: the shared names and constants; :mod:`~xrl_jax.config.checks`:
  :class:`ConfigError` and the checks both configs use.

Every field carries its documentation (``help`` metadata), from which :func:`settings_help` writes
the CLI's list of settings. Configs are frozen and validated on construction, so a bad value fails
in one line where it is written rather than deep inside a jitted update. Adding a field touches its
config's module only; adding a preset, the presets module only.
"""

from xrl_jax.config.agent import AgentConfig, field_names
from xrl_jax.config.checks import ConfigError
from xrl_jax.config.names import (
    ACTOR_TWIN,
    ALGOS,
    BASELINES,
    CONTINUOUS_ALGOS,
    CRITIC_LOSSES,
    DISCRETE_ALGOS,
    ENVS,
    FEATURE_EXTRACTORS,
    HOST_ONLY_FIELDS,
    LOG_STD_MAX,
    MAX_VEHICLES,
    MIXTURE_ALGOS,
    MIXTURE_LOG_STD_MIN,
    ON_POLICY_ALGOS,
    ON_POLICY_TRACED_FIELDS,
    PRESETS,
    SAC_LOG_STD_MIN,
    SWEEPABLE_FIELDS,
    TRACED_FIELDS,
    TRAINED_ALGOS,
    TRUNCATION_MODES,
)
from xrl_jax.config.overrides import apply_overrides, parse_overrides, parse_sweep, parse_value
from xrl_jax.config.presets import (
    COUNTRY_ROAD_PACKED_ROWS,
    INTERSECTION_ALPHA,
    INTERSECTION_PACKED_ROWS,
    QUICK_INTERSECTION_OPTIMISATION,
    QUICK_RACING_OPTIMISATION,
    QUICK_SIZES,
    SMOKE_SIZES,
    TRAIN_PRESETS,
    preset,
    preset_train_fields,
)
from xrl_jax.config.resolve import resolve_config, settings_help
from xrl_jax.config.scenarios import SCENARIOS, Scenario, scenario
from xrl_jax.config.train import TrainConfig, train_field_names, unused_sweep_reason

__all__ = [
    "ACTOR_TWIN",
    "ALGOS",
    "BASELINES",
    "CONTINUOUS_ALGOS",
    "COUNTRY_ROAD_PACKED_ROWS",
    "CRITIC_LOSSES",
    "DISCRETE_ALGOS",
    "ENVS",
    "FEATURE_EXTRACTORS",
    "HOST_ONLY_FIELDS",
    "INTERSECTION_ALPHA",
    "INTERSECTION_PACKED_ROWS",
    "LOG_STD_MAX",
    "MAX_VEHICLES",
    "MIXTURE_ALGOS",
    "MIXTURE_LOG_STD_MIN",
    "ON_POLICY_ALGOS",
    "ON_POLICY_TRACED_FIELDS",
    "PRESETS",
    "QUICK_INTERSECTION_OPTIMISATION",
    "QUICK_RACING_OPTIMISATION",
    "QUICK_SIZES",
    "SAC_LOG_STD_MIN",
    "SCENARIOS",
    "SMOKE_SIZES",
    "SWEEPABLE_FIELDS",
    "TRACED_FIELDS",
    "TRAINED_ALGOS",
    "TRAIN_PRESETS",
    "TRUNCATION_MODES",
    "AgentConfig",
    "ConfigError",
    "Scenario",
    "TrainConfig",
    "apply_overrides",
    "field_names",
    "parse_overrides",
    "parse_sweep",
    "parse_value",
    "preset",
    "preset_train_fields",
    "resolve_config",
    "scenario",
    "settings_help",
    "train_field_names",
    "unused_sweep_reason",
]
