"""The text forms of settings: ``--set KEY=VALUE`` items, one typed parser for every field of
either config, and ``--sweep FIELD=V1,V2,...`` lists."""

from __future__ import annotations

import typing
from collections.abc import Mapping
from typing import Any

from xrl_jax.config.agent import AgentConfig, field_names
from xrl_jax.config.checks import ConfigError, check_known
from xrl_jax.config.names import SWEEPABLE_FIELDS
from xrl_jax.config.train import train_field_names


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """``["key=value", ...]`` -> dict; a malformed item raises :class:`ConfigError`, and so does a
    setting given twice (``gamma`` and ``agent.gamma`` name the same field): the last value winning
    would silently drop the other one."""
    out: dict[str, str] = {}
    given: dict[str, str] = {}  # field name -> the item that set it
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key or not value.strip():
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        name = key.removeprefix("agent.")
        if name in given:
            raise ConfigError(f"--set {name} is given twice ({given[name]!r} and {item!r}); give it once")
        given[name] = item
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
    check_known(overrides, field_names(), "AgentConfig")
    return cfg.replace(
        **{k: parse_value(AgentConfig, k, v) if isinstance(v, str) else v for k, v in overrides.items()}
    )


def parse_sweep(items: list[str] | tuple[str, ...]) -> tuple:
    """``["kappa=-0.01,0,0.01", ...]`` (``--sweep``, repeatable) -> ``(("kappa", (-0.01, 0.0, 0.01)),
    ...)``; text that is not a list of numbers raises :class:`ConfigError` in one line. Which
    fields may be swept is checked with the config (:mod:`xrl_jax.config.train`)."""
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
