"""The resolved run (preset, explicit arguments, then ``--set`` overrides, validated) and the CLI's
list of settings, written from the fields' own documentation."""

from __future__ import annotations

import dataclasses
import textwrap
import typing
from collections.abc import Mapping

from xrl_jax.config.agent import AgentConfig, field_names
from xrl_jax.config.checks import ConfigError, check_choice
from xrl_jax.config.names import ON_POLICY_ALGOS, PRESETS, TRAINED_ALGOS
from xrl_jax.config.overrides import apply_overrides, parse_value
from xrl_jax.config.presets import RUN_LENGTH_PRESETS, preset_train_fields
from xrl_jax.config.presets import preset as agent_preset  # resolve_config's ``preset`` is a name
from xrl_jax.config.scenarios import scenario
from xrl_jax.config.train import TrainConfig, train_field_names


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
    scenario(env)  # an unknown env fails here, saying how a user's env is registered
    for kind, value, choices in (("algo", algo, TRAINED_ALGOS), ("preset", preset_name, PRESETS)):
        check_choice("", kind, value, choices)
    fields = preset_train_fields(preset_name, env, on_policy=algo in ON_POLICY_ALGOS)
    if algo in ON_POLICY_ALGOS:
        # The on-policy agents act by their policy from the first step, and keep their agent throughout.
        fields.update(warmup_steps=0, reinit_steps=0)
    fields.update(env=env, algo=algo, preset=preset_name, num_seeds=num_seeds, sweep=tuple(sweep))
    if total_steps is not None:
        fields["total_steps"] = total_steps
    swept = {name for name, _ in sweep}
    both = sorted(swept & {key.removeprefix("agent.") for key in overrides or {}})
    if both:  # the sweep's values would win, and config.json would hold the set value beside them
        raise ConfigError(f"{both[0]} is both swept (--sweep) and set (--set): give it one way")
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
    agent = apply_overrides(agent_preset(preset_name, env, algo), agent_changes)
    if (preset_name, scenario(env).kind) in RUN_LENGTH_PRESETS:  # settings that follow the run's length
        if "buffer_size" not in (overrides or {}):
            # Keep every transition, as the paper's protocol does (buffer = steps = 10⁶).
            fields["buffer_size"] = max(fields["total_steps"], fields["batch_size"])
        if "lr_decay_updates" not in agent_changes:
            # The learning rates reach zero at the last update (one update per transition after warm-up;
            # on-policy: every minibatch of every epoch of every rollout).
            updates = fields["total_steps"] - fields.get("warmup_steps", TrainConfig.warmup_steps)
            if agent.is_on_policy:
                rollout = agent.rollout_steps * fields.get("num_envs", TrainConfig.num_envs)
                updates = fields["total_steps"] // rollout * agent.ppo_epochs * agent.ppo_minibatches
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
