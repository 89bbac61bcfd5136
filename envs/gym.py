"""Gymnasium adaptors (numpy in / numpy out) so libraries outside JAX can use the scenarios.

* :class:`GymEnv` - one env, ``gymnasium.Env`` API; passes ``gymnasium.utils.env_checker.check_env``.
* :class:`GymVectorEnv` - ``num_envs`` envs stepped by one jitted ``vmap`` call, ``gymnasium.vector``
  API with same-step auto-reset: when an episode ends, the returned observation is the first one of
  the next episode and ``infos["final_obs"]`` holds the ending observation (a dict of arrays over all
  envs; rows with ``infos["_final_obs"] == False`` repeat the returned observation).

Single-agent envs only (a multi-agent one is refused). Actions are validated on the host: anything
outside the action space (wrong shape, a complex dtype, a masked array, NaN or inf, values outside [-1,
1], a discrete index outside [0, 12)) raises ``ValueError`` before the env is touched. ``GymEnv.step``
before ``reset()``, or after an episode has terminated or been truncated, raises :class:`ResetNeeded`
(Gymnasium's order error); the vector env resets by itself. Info values are numpy arrays/scalars (see
``envs.racing`` for the keys). Seeding: ``reset(seed=k)`` restarts the env's key stream at
``PRNGKey(k)``; ``reset()`` continues it.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from envs import core
from envs.racing import RacingEnv, RacingParams, check_action
from envs.registry import make


class ResetNeeded(gymnasium.error.ResetNeeded, RuntimeError):
    """``step`` without a running episode: Gymnasium's error, also a ``RuntimeError`` (as raised
    before for a missing ``reset``) so existing handlers keep working."""


def to_gym_space(space: core.Space) -> gymnasium.spaces.Space:
    """Convert an ``envs.core`` space to its Gymnasium equivalent."""
    if isinstance(space, core.Box):
        return gymnasium.spaces.Box(space.low, space.high, space.shape, np.dtype(space.dtype))
    if isinstance(space, core.Discrete):
        return gymnasium.spaces.Discrete(space.n)
    if isinstance(space, core.Dict):
        return gymnasium.spaces.Dict({k: to_gym_space(v) for k, v in space.spaces.items()})
    raise TypeError(f"cannot convert {type(space).__name__} to a gymnasium space")


def _to_numpy(tree):
    return jax.tree.map(lambda x: np.asarray(x), tree)


def _obs_to_numpy(obs: dict) -> dict:
    return {k: np.asarray(v, dtype=np.float32) for k, v in obs.items()}


def _resolve(env_or_name, params, overrides) -> tuple[RacingEnv, RacingParams]:
    if isinstance(env_or_name, str):
        env, made = make(env_or_name, **overrides)
        env, params = env, made if params is None else params
    elif overrides:
        raise ValueError("overrides are only accepted together with an env name")
    elif params is None:
        raise ValueError("pass params together with an env instance (see envs.make)")
    else:
        env = env_or_name
    if env.multi_agent:  # its observations and actions carry an agent axis that Gymnasium's spaces lack
        raise ValueError(
            f"the Gymnasium adaptors take single-agent envs; {env.name} is multi-agent ({env.num_agents} "
            "agent slots): use the env itself (envs.make) or envs.gymnax"
        )
    return env, params


class GymEnv(gymnasium.Env):
    """A single scenario behind the ``gymnasium.Env`` API (``GymEnv("tracking")`` or ``(env, params)``)."""

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(self, env: RacingEnv | str = "tracking", params: RacingParams | None = None, **overrides):
        self.env, self.params = _resolve(env, params, overrides)
        self.action_space = to_gym_space(self.env.action_space(self.params))
        self.observation_space = to_gym_space(self.env.observation_space(self.params))
        self._reset_fn = jax.jit(self.env.reset)
        self._step_fn = jax.jit(self.env.step)
        self._key = jax.random.PRNGKey(0)
        self._state = None
        self._episode_over = False

    def _next_key(self):
        self._key, key = jax.random.split(self._key)
        return key

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        obs, self._state = self._reset_fn(self._next_key(), self.params)
        self._episode_over = False
        return _obs_to_numpy(obs), {}

    def step(self, action):
        if self._state is None:
            raise ResetNeeded("call reset() before step()")
        if self._episode_over:
            # The ended state would only repeat its ending (e.g. -1 and terminated off the track).
            raise ResetNeeded("the episode has ended (terminated or truncated); call reset() before step()")
        action = check_action(self.env, action)
        obs, self._state, reward, terminated, truncated, info = self._step_fn(
            self._next_key(), self._state, jnp.asarray(action), self.params
        )
        terminated, truncated = bool(terminated), bool(truncated)
        self._episode_over = terminated or truncated
        return _obs_to_numpy(obs), float(reward), terminated, truncated, _to_numpy(info)


class GymVectorEnv(VectorEnv):
    """``num_envs`` copies of a scenario, stepped together (jit + vmap), with same-step auto-reset."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}  # noqa: RUF012

    def __init__(
        self,
        env: RacingEnv | str = "tracking",
        num_envs: int = 8,
        params: RacingParams | None = None,
        **overrides,
    ):
        if int(num_envs) <= 0:
            raise ValueError(f"num_envs must be positive, got {num_envs}")
        self.env, self.params = _resolve(env, params, overrides)
        self.num_envs = int(num_envs)
        self.single_action_space = to_gym_space(self.env.action_space(self.params))
        self.single_observation_space = to_gym_space(self.env.observation_space(self.params))
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        batched = core.VmapWrapper(core.AutoResetWrapper(self.env), self.num_envs)
        self._reset_fn = jax.jit(batched.reset)
        self._step_fn = jax.jit(batched.step)
        self._key = jax.random.PRNGKey(0)
        self._state = None

    def _next_key(self):
        self._key, key = jax.random.split(self._key)
        return key

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            if not isinstance(seed, int | np.integer):
                raise ValueError(f"GymVectorEnv.reset takes a single int seed, got {seed!r}")
            self._key = jax.random.PRNGKey(int(seed))
        obs, self._state = self._reset_fn(self._next_key(), self.params)
        return _obs_to_numpy(obs), {}

    def _check_actions(self, actions) -> np.ndarray:
        if np.ma.isMaskedArray(actions):  # np.asarray would keep the masked entries' values
            raise ValueError(f"actions must be a plain array, got a masked array: {actions!r}")
        actions = np.asarray(actions)
        if actions.shape[:1] != (self.num_envs,):
            raise ValueError(f"expected a batch of {self.num_envs} actions, got shape {actions.shape}")
        return np.stack([check_action(self.env, a) for a in actions])

    def step(self, actions):
        if self._state is None:
            raise ResetNeeded("call reset() before step()")
        actions = self._check_actions(actions)
        obs, self._state, reward, terminated, truncated, info = self._step_fn(
            self._next_key(), self._state, jnp.asarray(actions), self.params
        )
        info = _to_numpy(info)
        info["final_obs"] = _obs_to_numpy(info["final_obs"])
        info["_final_obs"] = np.asarray(terminated | truncated)
        return (
            _obs_to_numpy(obs),
            np.asarray(reward, dtype=np.float64),
            np.asarray(terminated),
            np.asarray(truncated),
            info,
        )
