"""Every scenario as a gymnax 1.0 ``Environment``, for the trainers of that ecosystem (PureJaxRL-style
scripts, rejax, Stoix, gymnax's own wrappers). Needs the ``gymnax`` extra (``pip install
"xrl-jax[gymnax]"``)::

    import jax
    from envs import gymnax as carenv_gymnax

    env, params = carenv_gymnax.make("tracking", flat_obs=True)
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

What gymnax's contract asks, and how the scenarios answer it:

* ``step`` is gymnax's own: it calls :meth:`GymnaxEnv.step_env`, asks :meth:`GymnaxEnv.is_truncated`,
  and on ``terminated | truncated`` returns the first observation of a new episode (``reset_env``),
  keeping the ending one in ``info["final_observation"]``. The scenario decides both flags (leaving
  the track, idling and the 60 s limit), so the state carries the step's ``truncated`` flag and
  ``params.max_steps_in_episode`` is only the bound a trainer's evaluation loop may read.
* Observations are the scenarios' dicts (``{"state": (6,), "<name>_set": (O, F)}``) or, with
  ``flat_obs=True``, one float vector (the state, then the set row by row) for trainers that expect an
  array. gymnax's ``Dict.contains`` reads sub-observations as attributes, so check a dict observation
  key by key against ``observation_space(params).spaces``.
* The Intersection is multi-agent (docs/carenv-intersection.md): observations, rewards and actions
  carry a leading axis of 8 vehicle slots, the spaces are per vehicle, and the episode-level flags are
  scalars: ``terminated`` is always False (cars leave and new ones arrive within an episode) and
  ``truncated`` marks the 60 s end. Per-vehicle flags are in ``info["agent_terminated"]``,
  ``info["agent_truncated"]`` and ``info["acted"]`` (which slots held a car that acted). The new
  episode is gymnax's ``reset_env``, which starts the spawners afresh: the original training loop's
  restart kept their timers (quirk Q1), a difference in when the first cars of each episode appear.
* Trainers written for gymnax's older five-value ``step`` (rejax 0.1) take :func:`legacy_step_api`.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

try:
    from gymnax.environments import environment, spaces
    from gymnax.wrappers import LegacyStepAPIWrapper
except ModuleNotFoundError as error:  # only the extra is missing: say how to install it
    if not (error.name or "").startswith("gymnax"):
        raise
    raise ModuleNotFoundError(
        f"envs.gymnax needs the gymnax extra: pip install 'xrl-jax[gymnax]' (no module {error.name!r})",
        name=error.name,
    ) from None

from envs import core
from envs.registry import make as make_scenario


@struct.dataclass
class GymnaxState(environment.EnvState):
    """gymnax's state (``time``: steps since the reset) around a scenario's own state."""

    inner: Any = None
    truncated: jax.Array | bool = False


@struct.dataclass
class GymnaxParams(environment.EnvParams):
    """gymnax's params around a scenario's own; ``max_steps_in_episode`` is the scenario's time limit
    and ``made_for`` the name of the env they were made for (None: made by hand, not checked)."""

    inner: Any = None
    made_for: str | None = struct.field(pytree_node=False, default=None)


def to_gymnax_space(space: core.Space) -> spaces.Space:
    """The gymnax equivalent of an ``envs.core`` space."""
    if isinstance(space, core.Box):
        return spaces.Box(jnp.asarray(space.low), jnp.asarray(space.high), space.shape, space.dtype)
    if isinstance(space, core.Discrete):
        return spaces.Discrete(space.n)
    if isinstance(space, core.Dict):
        return spaces.Dict({name: to_gymnax_space(sub) for name, sub in space.spaces.items()})
    raise TypeError(f"cannot convert {type(space).__name__} to a gymnax space")


def flatten_observation(obs: dict[str, jax.Array]) -> jax.Array:
    """The state, then the set row by row, as one vector (the last axes; a leading slot axis stays)."""
    state = obs["state"]
    lead = state.shape[:-1]
    sets = [value.reshape(*lead, -1) for name, value in obs.items() if name != "state"]
    return jnp.concatenate([state, *sets], axis=-1)


class GymnaxEnv(environment.Environment):
    """A scenario of :func:`envs.make` behind gymnax's ``Environment`` interface (module docstring)."""

    def __init__(self, scenario: core.Environment, scenario_params: Any, flat_obs: bool = False):
        _check_flat_obs(flat_obs)
        if not isinstance(scenario, core.Environment):  # the adaptor asks it num_agents, max_episode_steps
            raise TypeError(f"envs.gymnax adapts an envs.core.Environment, got {type(scenario).__name__}")
        self.scenario = scenario
        self.scenario_params = scenario_params
        self.flat_obs = bool(flat_obs)
        self.multi_agent = scenario.multi_agent

    # Equal configurations hash equal, so gymnax's jitted step (``self`` is static) is shared between
    # instances built alike; the params are not part of it: they are an argument of every call.
    def _config(self) -> tuple:
        return (self.scenario, self.flat_obs)

    def __eq__(self, other) -> bool:
        return isinstance(other, GymnaxEnv) and self._config() == other._config()

    def __hash__(self) -> int:
        return hash(self._config())

    def __repr__(self) -> str:
        return f"GymnaxEnv({self.scenario!r}, flat_obs={self.flat_obs})"

    @property
    def name(self) -> str:
        return self.scenario.name

    @property
    def default_params(self) -> GymnaxParams:
        params = self.scenario_params
        limit = self.scenario.max_episode_steps(params)
        if limit is None:  # a user's env (envs.register) that does not say
            raise ValueError(
                f"{self.name}: gymnax needs the time limit of an episode: give the env a "
                "max_episode_steps(params) method (envs.core.Environment) or its params a max_steps field"
            )
        if limit < 1:
            raise ValueError(f"{self.name}: an episode's time limit must be at least 1 step, got {limit}")
        return GymnaxParams(max_steps_in_episode=int(limit), inner=params, made_for=self.name)

    def _check_params(self, params: Any) -> Any:
        """The scenario's own params inside ``params``, or a one-line error: params of gymnax's own
        (``EnvParams()``) or of another scenario would otherwise fail deep inside, or run silently."""
        if not isinstance(params, GymnaxParams):
            raise TypeError(
                f"{self.name}: params must be this env's GymnaxParams (envs.gymnax.make returns them, as "
                f"does env.default_params), got {type(params).__name__}"
            )
        made_for = params.made_for
        if made_for is not None and made_for != self.name:
            raise ValueError(f"{self.name}: these params were made for {made_for!r}; use env.default_params")
        expected = type(self.scenario_params)
        if not isinstance(params.inner, expected):
            raise TypeError(
                f"{self.name}: params.inner must be the scenario's {expected.__name__}, "
                f"got {type(params.inner).__name__}"
            )
        return params.inner

    def _check_action(self, action: Any) -> jax.Array:
        """``action`` as an array, or a one-line error when its shape is not the action space's
        (a batch of envs is ``jax.vmap`` of ``step``, not a batch of actions)."""
        action = jnp.asarray(action)
        one = self.action_space().shape
        expected = (self.scenario.num_agents, *one) if self.multi_agent else tuple(one)
        if action.shape != expected:
            per = f" ({self.scenario.num_agents} agent slots)" if self.multi_agent else ""
            raise ValueError(
                f"{self.name}: an action has shape {expected}{per}, got {action.shape}; "
                "for a batch of envs, jax.vmap the step"
            )
        return action

    @property
    def num_actions(self) -> int:
        return core.action_size(self.scenario.action_space())

    def action_space(self, params: GymnaxParams | None = None) -> spaces.Space:
        """Per vehicle on the Intersection."""
        return to_gymnax_space(self.scenario.action_space())

    def observation_space(self, params: GymnaxParams | None = None) -> spaces.Space:
        """Per vehicle on the Intersection."""
        inner = None if params is None else params.inner
        space = self.scenario.observation_space(inner)
        if not self.flat_obs:
            return to_gymnax_space(space)
        parts = [space["state"], *(sub for name, sub in space.spaces.items() if name != "state")]
        low = np.concatenate([np.ravel(part.low) for part in parts])
        high = np.concatenate([np.ravel(part.high) for part in parts])
        return spaces.Box(jnp.asarray(low), jnp.asarray(high), low.shape, jnp.float32)

    def _observe(self, obs: dict[str, jax.Array]) -> Any:
        return flatten_observation(obs) if self.flat_obs else obs

    def reset_env(self, key: jax.Array, params: GymnaxParams) -> tuple[Any, GymnaxState]:
        obs, inner = self.scenario.reset_env(key, self._check_params(params))
        return self._observe(obs), GymnaxState(
            time=jnp.zeros((), jnp.int32), inner=inner, truncated=jnp.zeros((), bool)
        )

    def step_env(self, key: jax.Array, state: GymnaxState, action: Any, params: GymnaxParams):
        obs, inner, reward, terminated, truncated, info = self.scenario.step_env(
            key, state.inner, self._check_action(action), self._check_params(params)
        )
        if self.multi_agent:
            # The scenario restarts itself at the 60 s end; gymnax's step resets instead, from the
            # ending step's observation, which the scenario keeps in info.
            obs = info["final_obs"]
            info = {k: v for k, v in info.items() if k != "final_obs"}
            info.update(agent_terminated=terminated, agent_truncated=truncated)
            terminated, truncated = jnp.zeros((), bool), info["episode_end"]
        next_state = GymnaxState(time=state.time + 1, inner=inner, truncated=truncated)
        return self._observe(obs), next_state, reward, terminated, info

    def is_truncated(self, state: GymnaxState, params: GymnaxParams) -> jax.Array:
        """The scenario's own truncation of the step that led to ``state`` (time limit, idling)."""
        return jnp.asarray(state.truncated)

    def is_terminated(self, state: GymnaxState, params: GymnaxParams) -> jax.Array:
        raise NotImplementedError("the scenario decides termination in step_env; read step's flags")


def _check_flat_obs(flat_obs: Any) -> None:
    if not isinstance(flat_obs, (bool, np.bool_)):  # "no" would be truthy: take booleans only
        raise ValueError(f"flat_obs must be True or False, got {flat_obs!r}")


def make(name: str, flat_obs: bool = False, **overrides) -> tuple[GymnaxEnv, GymnaxParams]:
    """``gymnax.make`` for the scenarios: ``name`` and ``overrides`` as :func:`envs.make` takes them.
    Raises ``ValueError`` (one line) for a bad ``flat_obs``, name, override or time limit."""
    _check_flat_obs(flat_obs)  # before the scenario is built (a track bank takes a while)
    scenario, scenario_params = make_scenario(name, **overrides)
    env = GymnaxEnv(scenario, scenario_params, flat_obs=flat_obs)
    return env, env.default_params


class LegacyStepAPI(LegacyStepAPIWrapper):
    """gymnax's adapter to the five-value ``step`` (obs, state, reward, done, info), deep-copyable:
    rejax deep-copies the env it is given, and gymnax 1.0.1's adapter then recurses forever in its
    ``__getattr__``. The env holds no mutable state, so the copy is the env itself."""

    def __deepcopy__(self, memo: dict) -> LegacyStepAPI:
        return self


def legacy_step_api(env: GymnaxEnv) -> LegacyStepAPI:
    """``env`` for trainers written against gymnax's older five-value ``step`` (rejax 0.1)."""
    return LegacyStepAPI(env)
