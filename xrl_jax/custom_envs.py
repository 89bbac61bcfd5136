"""A user's own JAX env trained like a built-in scenario: :func:`register_env` reads the observation
layout the mixture agents need off the env, registers the env with :func:`envs.register` and its
facts with the trainer's scenario table, after which ``resolve_config(env=name, ...)``, the run
folder, checkpoints, evaluation, summary, report and explanation figures all work on it.

The env is an :class:`envs.core.Environment` (gymnax-style ``reset_env`` / ``step_env`` on explicit
state and params; it ends its own episodes with ``terminated`` / ``truncated``) whose observation is

    {"state": (S,), "<name>_set": (O, F)}

with the objects in the ``O`` rows of the set, column 0 of a row 1 when the object is present and 0
when the slot is empty: the mixture has one component per present object. Its action space is
``Box(-1, 1, (A,))`` (SAC, XSAC: the policies squash into [-1, 1]) or ``Discrete(N)`` (DSAC, XDSAC).
docs/ecosystem.md shows a whole example.
"""

from __future__ import annotations

import inspect
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from envs import registry as env_registry
from envs.core import Box, Dict, Discrete, Environment
from xrl_jax.config import ConfigError, user_envs
from xrl_jax.config.scenarios import (
    BUILT_IN,
    Scenario,
    custom_scenario,
    register_scenario,
    unregister_scenario,
)

STATE_KEY = "state"
SET_SUFFIX = "_set"
RESETS_CHECKED = 8  # real resets register_env looks at (one jitted, vmapped call)


def register_env(
    name: str,
    factory: Callable[..., tuple[Environment, Any]],
    max_episode_steps: int | None = None,
    object_xy: tuple[int, int] | None = None,
) -> Scenario:
    """Register ``factory() -> (env, params)`` as scenario ``name`` and return its facts.

    ``max_episode_steps`` bounds an evaluation episode (the evaluation truncates it there if the env
    has not ended it); without it, the env's own time limit (``env.max_episode_steps(params)``).
    ``object_xy``: the columns of an object's row that hold its position relative to the agent, if
    any; the explanation figure then draws the objects where they are. Registering a name again
    replaces it. A few real resets are checked (column 0 of the set is the present flag, 0 or 1;
    everything finite). Raises :class:`ConfigError` (one line) for an env the agents cannot train
    on, saying what is wrong.

    A run records the calling module, the layout, the action space and ``max_episode_steps``
    (:mod:`xrl_jax.config.user_envs`): a resume or a reader with other ones is refused.
    """
    module = _module_name(sys._getframe(1).f_globals)  # the module a script --imports
    if name in BUILT_IN or name in env_registry.ENV_NAMES:
        raise ConfigError(f"{name!r} is a built-in scenario; register your env under another name")
    env, params = _made(name, factory)
    layout = _layout(name, env, params)
    _check_resets(name, env, params, layout[0])
    max_episode_steps = _time_limit(name, env, params, max_episode_steps)
    features = layout[2]
    if object_xy is not None:
        columns = tuple(object_xy)
        if len(columns) != 2 or not all(isinstance(c, int) and 1 <= c < features for c in columns):
            raise ConfigError(
                f"object_xy must be two feature columns in 1..{features - 1} (0 is the present flag), "
                f"got {object_xy!r}"
            )
        object_xy = columns
    facts = custom_scenario(name, *layout, max_episode_steps, object_xy)
    try:
        env_registry.register(name, factory)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    register_scenario(facts)
    space = env.observation_space(params)
    shapes = {key: space[key].shape for key in (STATE_KEY, layout[0])}
    user_envs.remember(
        name, user_envs.make_record(module, shapes, repr(env.action_space(params)), max_episode_steps)
    )
    return facts


def unregister_env(name: str) -> None:
    """Forget a user's env (for tests and notebooks that register several versions)."""
    env_registry.unregister(name)
    unregister_scenario(name)
    user_envs.forget(name)


def _module_name(namespace: dict) -> str | None:
    """The name ``--import`` gives the module that ``namespace`` belongs to: its own, or for a script
    run as ``__main__``, its ``-m`` name or its file's stem (``--import path/name.py`` names it so)."""
    name = namespace.get("__name__")
    if name != "__main__":
        return name
    spec = namespace.get("__spec__")
    if spec is not None and getattr(spec, "name", None):
        return spec.name
    return Path(namespace["__file__"]).stem if namespace.get("__file__") else name


def _made(name: str, factory) -> tuple[Environment, Any]:
    """``factory()``'s ``(env, params)``, or a one-line error saying what the factory got wrong."""
    if not callable(factory):
        raise ConfigError(f"the factory of {name!r} must be callable, returning (env, params)")
    try:
        inspect.signature(factory).bind()
    except TypeError as err:
        raise ConfigError(f"the factory of {name!r} must take no required argument: {err}") from None
    except ValueError:  # no signature to read (a builtin): let the call say
        pass
    made = factory()
    if not (isinstance(made, tuple) and len(made) == 2):
        raise ConfigError(
            f"the factory of {name!r} must return a pair (env, params), got {type(made).__name__}"
            + (" (the env alone? return (env, env.default_params))" if isinstance(made, Environment) else "")
        )
    return made


def _time_limit(name: str, env: Environment, params, given: int | None) -> int:
    """``given``, or the env's own time limit; a positive integer, else a one-line error."""
    steps = env.max_episode_steps(params) if given is None else given
    if steps is None:
        raise ConfigError(
            f"{name!r}: give max_episode_steps (where an evaluation episode stops), or let the env say "
            "it (max_episode_steps(params), or params.max_steps)"
        )
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ConfigError(f"max_episode_steps must be a positive integer, got {steps!r}")
    return int(steps)


def _check_resets(name: str, env: Environment, params, set_key: str) -> None:
    """A few real resets: finite observations and a present flag (0 or 1) in column 0 of the set, as
    the agents read it (``x[..., 0] > 0`` masks the mixture's components). Present rows may be in any
    slots: the agents mask rather than count."""
    keys = jax.random.split(jax.random.PRNGKey(0), RESETS_CHECKED)
    try:
        obs = jax.device_get(jax.jit(jax.vmap(env.reset_env, in_axes=(0, None)))(keys, params)[0])
    except Exception as err:  # the user's code: whatever it raises is reported in one line
        raise _reset_failed(name, err) from None
    for key in (STATE_KEY, set_key):
        if not np.all(np.isfinite(np.asarray(obs[key], dtype=np.float64))):
            raise ConfigError(f"{name!r}: reset_env's observation {key!r} holds NaN or infinite values")
    flags = np.asarray(obs[set_key])[..., 0]
    bad = np.unique(flags[(flags != 0) & (flags != 1)])
    if bad.size:
        raise ConfigError(
            f"{name!r}: column 0 of {set_key!r} must be the present flag (1: an object, 0: an empty slot), "
            f"but {RESETS_CHECKED} resets hold {', '.join(f'{v:.4g}' for v in bad[:4])} there: put the flag "
            "first in every row"
        )


def _layout(name: str, env, params) -> tuple[str, int, int, int, str]:
    """``(set_key, objects, features, state_dim, actions)`` of the env, or a one-line error."""
    if not isinstance(env, Environment):
        raise ConfigError(
            f"{name!r}: the factory must return (env, params) with env an envs.core.Environment"
        )
    space = env.observation_space(params)
    sets = [key for key in getattr(space, "spaces", {}) if key.endswith(SET_SUFFIX)]
    if not isinstance(space, Dict) or set(space.spaces) != {STATE_KEY, *sets} or len(sets) != 1:
        raise ConfigError(
            f"{name!r}: the observation space must be Dict({{'state': Box (S,), '<name>_set': Box (O, F)}}), "
            f"got {space!r}"
        )
    state, objects = space[STATE_KEY], space[sets[0]]
    if not (isinstance(state, Box) and len(state.shape) == 1):
        raise ConfigError(f"{name!r}: observation 'state' must be a Box of shape (S,), got {state!r}")
    if not (isinstance(objects, Box) and len(objects.shape) == 2 and objects.shape[1] >= 2):
        raise ConfigError(
            f"{name!r}: observation {sets[0]!r} must be a Box of shape (O, F) with F >= 2 "
            f"(column 0 the present flag), got {objects!r}"
        )
    actions = env.action_space(params)
    if isinstance(actions, Discrete):
        kind = "discrete"
    elif isinstance(actions, Box) and len(actions.shape) == 1 and _is_unit_box(actions):
        kind = "continuous"
    else:
        raise ConfigError(
            f"{name!r}: the action space must be Discrete(N) or Box(-1, 1, (A,)) (the policies squash "
            f"into [-1, 1]), got {actions!r}"
        )
    try:
        obs = jax.eval_shape(env.reset_env, jax.random.PRNGKey(0), params)[0]
    except Exception as err:  # the user's code: whatever it raises is reported in one line
        raise _reset_failed(name, err) from None
    shapes = {key: tuple(obs[key].shape) for key in (STATE_KEY, sets[0])} if isinstance(obs, dict) else None
    if shapes != {STATE_KEY: state.shape, sets[0]: objects.shape}:
        raise ConfigError(f"{name!r}: reset_env's observation {shapes} does not match its space {space!r}")
    return sets[0], objects.shape[0], objects.shape[1], state.shape[0], kind


def _reset_failed(name: str, error: Exception) -> ConfigError:
    lines = str(error).strip().splitlines()
    return ConfigError(f"{name!r}: reset_env failed: {type(error).__name__}: {lines[0] if lines else ''}")


def _is_unit_box(space: Box) -> bool:
    return bool(np.all(space.low == -1) and np.all(space.high == 1))
