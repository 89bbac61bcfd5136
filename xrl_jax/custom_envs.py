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

from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from envs import registry as env_registry
from envs.core import Box, Dict, Discrete, Environment
from xrl_jax.config import ConfigError
from xrl_jax.config.scenarios import (
    BUILT_IN,
    Scenario,
    custom_scenario,
    register_scenario,
    unregister_scenario,
)

STATE_KEY = "state"
SET_SUFFIX = "_set"


def register_env(
    name: str,
    factory: Callable[..., tuple[Environment, Any]],
    max_episode_steps: int,
    object_xy: tuple[int, int] | None = None,
) -> Scenario:
    """Register ``factory() -> (env, params)`` as scenario ``name`` and return its facts.

    ``max_episode_steps`` bounds an evaluation episode (the evaluation truncates it there if the env
    has not ended it). ``object_xy``: the columns of an object's row that hold its position relative
    to the agent, if any; the explanation figure then draws the objects where they are. Registering
    a name again replaces it. Raises :class:`ConfigError` (one line) for an env the agents cannot
    train on, saying what is wrong.
    """
    if name in BUILT_IN or name in env_registry.ENV_NAMES:
        raise ConfigError(f"{name!r} is a built-in scenario; register your env under another name")
    if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1:
        raise ConfigError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}")
    try:
        env, params = factory()
    except TypeError as err:
        raise ConfigError(f"the factory of {name!r} must take no required argument: {err}") from None
    layout = _layout(name, env, params)
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
    return facts


def unregister_env(name: str) -> None:
    """Forget a user's env (for tests and notebooks that register several versions)."""
    env_registry.unregister(name)
    unregister_scenario(name)


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
    obs = jax.eval_shape(env.reset_env, jax.random.PRNGKey(0), params)[0]
    shapes = {key: tuple(obs[key].shape) for key in (STATE_KEY, sets[0])} if isinstance(obs, dict) else None
    if shapes != {STATE_KEY: state.shape, sets[0]: objects.shape}:
        raise ConfigError(f"{name!r}: reset_env's observation {shapes} does not match its space {space!r}")
    return sets[0], objects.shape[0], objects.shape[1], state.shape[0], kind


def _is_unit_box(space: Box) -> bool:
    return bool(np.all(space.low == -1) and np.all(space.high == 1))
