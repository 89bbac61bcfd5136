"""``envs.make(name, **overrides) -> (env, params)``: the single entry point to the scenarios
(``envs.action_space(name)``: a scenario's action space, without building its params).

Names:

* ``"country_road"`` / ``"country_road_discrete"``: cone track (original ``racing``), Box(-1, 1, (3,))
  or Discrete(12) actions.
* ``"tracking"`` / ``"tracking_discrete"``: centre-line lookahead (original ``racing_tracking`` with
  the paper's 25 points 2 m apart), Box(-1, 1, (3,)) or Discrete(12) actions.
* ``"intersection"`` / ``"intersection_discrete"``: the multi-agent crossing (8 slots; per-agent
  Box(-1, 1, (3,)) or Discrete(12) actions); overrides are the fields of
  :class:`envs.intersection.IntersectionParams` (``max_vehicles``, ``episode_steps``, the quirk
  flags ...).

Overrides (keyword arguments):

* any numeric field of :class:`envs.racing.RacingParams` (``k_forwards``, ``max_steps``,
  ``track_width``, ``lookahead_spacing`` ...) and ``vehicle`` (a ``VehicleParams``);
* ``track_source``: ``"bank"`` (default: reset draws uniformly from a bank generated once, here, on
  the host) or ``"generate"`` (reset generates a fresh track; slow under auto-reset + vmap);
* ``track_bank_size`` (default :data:`DEFAULT_BANK_SIZE`) and ``track_seed`` (default 0): the bank;
  the same (seed, size) gives the same bank (cached per process);
* ``track``: a single ``Track`` (e.g. from ``track_from_arrays``) used for every episode, or a bank
  of tracks (a ``Track`` with a leading axis, e.g. ``envs.racing.stack_tracks([...])``);
* ``lookahead_points`` (tracking only, default 25).

Unknown names or overrides raise ``ValueError`` listing the valid ones.

A user's env joins with ``register(name, factory)`` (``factory(**overrides) -> (env, params)``); then
``make(name)``, ``action_space(name)`` and ``envs.gymnax.make(name)`` (if its params hold
``max_steps``) serve it like a scenario. ``xrl_jax.register_env`` registers it here and, for the
trainer, its observation layout.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from envs.core import Environment, Space
from envs.country_road import CountryRoad
from envs.intersection import IntersectionEnv, IntersectionParams
from envs.racing import RacingEnv
from envs.racing_params import (
    DEFAULT_BANK_SIZE,
    RESET_CACHE_FIELDS,
    RacingParams,
    track_bank,
    with_bank,
    with_track,
)
from envs.track import Track
from envs.tracking import Tracking
from envs.vehicle_state import VehicleParams

_SCENARIOS = {
    "country_road": (CountryRoad, False),
    "country_road_discrete": (CountryRoad, True),
    "tracking": (Tracking, False),
    "tracking_discrete": (Tracking, True),
}
_MULTI_AGENT = {"intersection": False, "intersection_discrete": True}
MULTI_AGENT_ENV_NAMES = tuple(_MULTI_AGENT)
ENV_NAMES = tuple(_SCENARIOS) + MULTI_AGENT_ENV_NAMES

_PARAM_FIELDS = tuple(
    f.name
    for f in dataclasses.fields(RacingParams)
    if f.name not in ("tracks", "tables", *RESET_CACHE_FIELDS)
)
_BUILD_OPTIONS = ("track_bank_size", "track_seed", "track")
_TRACKING_OPTIONS = ("lookahead_points",)


_USER_FACTORIES: dict[str, Callable[..., tuple[Environment, Any]]] = {}


def register(name: str, factory: Callable[..., tuple[Environment, Any]]) -> None:
    """Make ``make(name, **overrides)`` call ``factory(**overrides)``; registering a name again
    replaces its factory. The built-in names cannot be taken."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"an env name is a Python identifier (letters, digits, _), got {name!r}")
    if name in ENV_NAMES:
        raise ValueError(f"{name!r} is a built-in scenario; register your env under another name")
    if not callable(factory):
        raise ValueError(f"the factory of {name!r} must be callable, returning (env, params)")
    _USER_FACTORIES[name] = factory


def unregister(name: str) -> None:
    """Forget a user's env (built-in scenarios stay)."""
    _USER_FACTORIES.pop(name, None)


def user_factory(name: str) -> Callable[..., tuple[Environment, Any]] | None:
    """The factory registered as ``name``, or None (a built-in or unknown name)."""
    return _USER_FACTORIES.get(name)


def registered() -> tuple[str, ...]:
    """The users' env names registered in this process."""
    return tuple(_USER_FACTORIES)


def _unknown(name: str) -> ValueError:
    return ValueError(f"unknown env name {name!r}; valid names: {', '.join(ENV_NAMES + registered())}")


def valid_overrides(name: str) -> tuple[str, ...]:
    """The keyword overrides ``make(name, ...)`` accepts."""
    if name in _MULTI_AGENT:
        return tuple(sorted(f.name for f in dataclasses.fields(IntersectionParams)))
    extra = _TRACKING_OPTIONS if _SCENARIOS[name][0] is Tracking else ()
    return tuple(sorted(_PARAM_FIELDS + _BUILD_OPTIONS + extra))


def make(name: str, **overrides) -> tuple[Environment, Any]:
    """Build a scenario and its params; see the module docstring for names and overrides."""
    if name in _USER_FACTORIES:
        return _USER_FACTORIES[name](**overrides)
    if name not in _SCENARIOS and name not in _MULTI_AGENT:
        raise _unknown(name)
    if name in _MULTI_AGENT:
        return _make_intersection(name, overrides)
    cls, discrete = _SCENARIOS[name]
    valid = valid_overrides(name)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown override(s) {unknown} for {name!r}; valid overrides: {', '.join(valid)}")

    env_kwargs = {k: overrides.pop(k) for k in _TRACKING_OPTIONS if k in overrides}
    env = cls(discrete=discrete, **env_kwargs)
    return env, racing_params(env, **overrides)


def action_space(name: str) -> Space:
    """The (per-agent) action space of scenario ``name``, without building its params: no track is
    generated (a user's env is built by its factory)."""
    if name in _USER_FACTORIES:
        env, params = _USER_FACTORIES[name]()
        return env.action_space(params)
    if name in _MULTI_AGENT:
        return IntersectionEnv(discrete=_MULTI_AGENT[name]).action_space()
    if name not in _SCENARIOS:
        raise _unknown(name)
    cls, discrete = _SCENARIOS[name]
    return cls(discrete=discrete).action_space()


def racing_params(env: RacingEnv, **overrides) -> RacingParams:
    """The params of a racing env from ``make``'s overrides (validated by ``make``), prepared for ``env``."""
    user_track = overrides.pop("track", None)
    bank_size = overrides.pop("track_bank_size", DEFAULT_BANK_SIZE)
    seed = overrides.pop("track_seed", 0)
    source = overrides.get("track_source", "bank")
    if source not in ("bank", "generate"):
        raise ValueError(f"track_source must be 'bank' or 'generate', got {source!r}")
    vehicle = overrides.pop("vehicle", None) or VehicleParams()
    if not isinstance(vehicle, VehicleParams):
        raise ValueError(f"vehicle must be a VehicleParams, got {type(vehicle).__name__}")
    max_steps = overrides.get("max_steps", 1)
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps (the time limit) must be a positive integer, got {max_steps!r}")

    params = RacingParams(vehicle=vehicle, tracks=None, **overrides)
    if user_track is not None:
        if not isinstance(user_track, Track):
            raise ValueError(f"track must be an envs.track.Track (track_from_arrays), got {type(user_track)}")
        if source == "generate":
            raise ValueError("a user track and track_source='generate' exclude each other")
        batched = jax.numpy.ndim(user_track.num_points) == 1
        params = with_bank(params, user_track) if batched else with_track(params, user_track)
    elif source == "bank":
        params = with_bank(params, track_bank(seed, bank_size))
    return env.prepare(params)


def _make_intersection(name: str, overrides: dict):
    valid = valid_overrides(name)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown override(s) {unknown} for {name!r}; valid overrides: {', '.join(valid)}")
    vehicle = overrides.get("vehicle", VehicleParams())
    if not isinstance(vehicle, VehicleParams):
        raise ValueError(f"vehicle must be a VehicleParams, got {type(vehicle).__name__}")
    return IntersectionEnv(discrete=_MULTI_AGENT[name]), IntersectionParams(**overrides)
