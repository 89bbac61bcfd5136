"""Pure-JAX re-implementation of the CarEnv driving simulator (jittable, vmappable).

Quick start::

    import jax, envs
    env, params = envs.make("tracking")            # or "country_road", "intersection", "*_discrete"
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

Batched training loop: ``envs.vmap_env(env, num_envs)`` (auto-reset + vmap; see ``envs.core``).
Gymnasium users: ``envs.gym.GymEnv`` / ``envs.gym.GymVectorEnv``.

This package never imports ``xrl_jax``: dependencies point one way (experiments -> xrl_jax -> envs).
"""

__version__ = "0.1.0"

import importlib

# Public names -> defining module. Loaded lazily (PEP 562) so that ``import envs.track`` stays light.
_EXPORTS = {
    "AutoResetWrapper": "envs.core",
    "Box": "envs.core",
    "Dict": "envs.core",
    "Discrete": "envs.core",
    "Environment": "envs.core",
    "VmapWrapper": "envs.core",
    "action_size": "envs.core",
    "vmap_env": "envs.core",
    "CountryRoad": "envs.country_road",
    "IntersectionEnv": "envs.intersection",
    "IntersectionParams": "envs.intersection",
    "IntersectionState": "envs.intersection",
    "MULTI_AGENT_ENV_NAMES": "envs.registry",
    "DONE_REASONS": "envs.racing",
    "IDLING": "envs.racing",
    "LEFT_TRACK": "envs.racing",
    "MAX_TIME": "envs.racing",
    "NONFINITE_ACTION": "envs.racing",
    "RacingParams": "envs.racing_params",
    "RacingState": "envs.racing",
    "with_track": "envs.racing_params",
    "with_bank": "envs.racing_params",
    "stack_tracks": "envs.racing_params",
    "GymEnv": "envs.gym",
    "GymVectorEnv": "envs.gym",
    "ENV_NAMES": "envs.registry",
    "action_space": "envs.registry",
    "make": "envs.registry",
    "register": "envs.registry",
    "registered": "envs.registry",
    "track_bank": "envs.racing_params",
    "Track": "envs.track",
    "track_from_arrays": "envs.track",
    "Tracking": "envs.tracking",
}


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'envs' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


__all__ = ["__version__", *sorted(_EXPORTS)]  # one list: the lazily loaded names above
