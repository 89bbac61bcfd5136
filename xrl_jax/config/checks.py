"""The error every invalid configuration raises and the small checks both configs are validated
with, so that a bad value fails in one line where it is written rather than deep inside a jitted
update."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any


class ConfigError(ValueError):
    """An invalid configuration; the message is one line naming the allowed values."""


def setting(default: Any, help: str, **kwargs: Any) -> Any:
    """A config field carrying its documentation, from which the CLI's list of settings is written."""
    return dataclasses.field(default=default, metadata={"help": help}, **kwargs)


def check_known(changes: Mapping[str, Any], known: list[str], what: str) -> None:
    unknown = sorted(set(changes) - set(known))
    if unknown:
        raise ConfigError(f"{what}: unknown field(s) {unknown}; valid fields: {sorted(known)}")


def require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def is_int(value: Any, minimum: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_choice(what: str, name: str, value: Any, choices: tuple[str, ...]) -> None:
    require(value in choices, f"{what}unknown {name} {value!r}; allowed: {', '.join(choices)}")
