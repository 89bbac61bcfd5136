"""What a run records of a user's env (:func:`xrl_jax.register_env`): the module that registered it,
its observation layout, its action space and its evaluation's time limit. None of these is a setting
of the run's config, yet each shapes its results or its checkpoints: a resume or a reader of the
folder compares the record in ``config.json`` with the env registered now, and the checkpoints'
config fingerprint holds it. Jax-free, so that the folder's readers can compare without jax.
"""

from __future__ import annotations

from typing import Any

# The fields of a record, with the words a mismatch is reported in.
RECORD_FIELDS = (
    ("observation", "observation layout"),
    ("actions", "action space"),
    ("max_episode_steps", "max_episode_steps"),
    ("module", "registering module"),
)

_RECORDS: dict[str, dict[str, Any]] = {}


def make_record(
    module: str | None, observation: dict[str, tuple[int, ...]], actions: str, max_episode_steps: int
) -> dict[str, Any]:
    """A record as ``config.json`` holds it (JSON types only, so that a stored one compares equal)."""
    return {
        "module": module,
        "observation": {key: [int(n) for n in shape] for key, shape in observation.items()},
        "actions": str(actions),
        "max_episode_steps": int(max_episode_steps),
    }


def remember(name: str, record: dict[str, Any]) -> None:
    """Keep the record of the env registered as ``name`` (by :func:`xrl_jax.register_env`)."""
    _RECORDS[name] = record


def forget(name: str) -> None:
    _RECORDS.pop(name, None)


def user_env_record(name: str) -> dict[str, Any] | None:
    """The record of the user's env ``name`` registered in this process; None for a built-in scenario
    (its facts are the code's) or a name nobody registered."""
    record = _RECORDS.get(name)
    return None if record is None else dict(record)


def record_differences(stored: dict[str, Any], current: dict[str, Any] | None) -> list[str]:
    """What differs between a run's stored record and the env registered now, in words (empty: none)."""
    if current is None:
        return ["no env of that name is registered with a record"]
    return [
        f"{words} {_shown(key, stored.get(key))} in the run, {_shown(key, current.get(key))} registered now"
        for key, words in RECORD_FIELDS
        if stored.get(key) != current.get(key)
    ]


def _shown(key: str, value: Any) -> str:
    if key == "observation" and isinstance(value, dict):  # "goals_set (8, 3), state (2,)"
        return ", ".join(f"{name} {tuple(shape)}" for name, shape in sorted(value.items()))
    return repr(value)
