"""Environment protocol, spaces and wrappers shared by every scenario (gymnax-1.0 style).

An environment is a stateless object; everything that changes lives in an explicit ``state``
pytree and everything configurable in an explicit ``params`` pytree, so ``reset`` and ``step``
are pure functions that can be ``jit``-ed and ``vmap``-ed:

    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

``step`` does NOT reset by itself: wrap the env in :class:`AutoResetWrapper` for that (it keeps
the observation of the ending step in ``info["final_obs"]``). Batching is plain ``jax.vmap``
over the key / state / action with ``params`` broadcast; :class:`VmapWrapper` packages that.
"""

from __future__ import annotations

from typing import Any, Generic, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

TState = TypeVar("TState")
TParams = TypeVar("TParams")


def default_float():
    """The float dtype JAX uses right now (float32, or float64 inside ``jax.enable_x64(True)``)."""
    return jnp.result_type(float)


# --------------------------------------------------------------------------------------------
# Spaces
# --------------------------------------------------------------------------------------------


class Space:
    """Minimal space protocol: ``sample(key)``, ``contains(x)`` (a traced bool), shape, dtype."""

    shape: tuple[int, ...]
    dtype: Any

    def sample(self, key: jax.Array) -> Any:
        raise NotImplementedError

    def contains(self, x: Any) -> jax.Array:
        raise NotImplementedError


class Box(Space):
    """Continuous box ``low <= x <= high`` (bounds broadcast to ``shape``; may be infinite)."""

    def __init__(self, low, high, shape: tuple[int, ...], dtype=jnp.float32):
        self.shape = tuple(int(n) for n in shape)
        self.dtype = jnp.dtype(dtype)
        self.low = np.broadcast_to(np.asarray(low, dtype=np.float64), self.shape).astype(self.dtype)
        self.high = np.broadcast_to(np.asarray(high, dtype=np.float64), self.shape).astype(self.dtype)
        if np.any(self.low > self.high):
            raise ValueError(f"Box needs low <= high, got low={low}, high={high}")

    def sample(self, key: jax.Array) -> jax.Array:
        """Uniform on bounded coordinates; a standard normal (shifted/folded) on unbounded ones."""
        lo_inf, hi_inf = np.isinf(self.low), np.isinf(self.high)
        if not (lo_inf.any() or hi_inf.any()):
            return jax.random.uniform(key, self.shape, self.dtype, self.low, self.high)
        normal = jax.random.normal(key, self.shape, self.dtype)
        uniform = jax.random.uniform(
            key, self.shape, self.dtype, np.where(lo_inf, 0, self.low), np.where(hi_inf, 1, self.high)
        )
        low, high = np.where(lo_inf, 0, self.low), np.where(hi_inf, 0, self.high)
        value = np.where(lo_inf & hi_inf, 1, 0) * normal
        value = value + np.where(lo_inf & ~hi_inf, 1, 0) * (high - jnp.abs(normal))
        value = value + np.where(hi_inf & ~lo_inf, 1, 0) * (low + jnp.abs(normal))
        return (value + np.where(lo_inf | hi_inf, 0, 1) * uniform).astype(self.dtype)

    def contains(self, x) -> jax.Array:
        x = jnp.asarray(x)
        if x.shape != self.shape:
            return jnp.asarray(False)
        return jnp.all((x >= self.low) & (x <= self.high) & ~jnp.isnan(x))

    def __repr__(self) -> str:
        lo, hi = np.unique(self.low), np.unique(self.high)
        lo = lo[0] if lo.size == 1 else "array"
        hi = hi[0] if hi.size == 1 else "array"
        return f"Box({lo}, {hi}, {self.shape}, {self.dtype})"


class Discrete(Space):
    """Integers ``0 .. n-1``."""

    def __init__(self, n: int):
        if int(n) <= 0:
            raise ValueError(f"Discrete needs n > 0, got {n}")
        self.n = int(n)
        self.shape = ()
        self.dtype = jnp.dtype(jnp.int32)

    def sample(self, key: jax.Array) -> jax.Array:
        return jax.random.randint(key, (), 0, self.n, dtype=jnp.int32)

    def contains(self, x) -> jax.Array:
        x = jnp.asarray(x)
        if x.shape != () or not jnp.issubdtype(x.dtype, jnp.integer):
            return jnp.asarray(False)
        return (x >= 0) & (x < self.n)

    def __repr__(self) -> str:
        return f"Discrete({self.n})"


class Dict(Space):
    """A dictionary of sub-spaces (key order as given; observations use the same keys)."""

    def __init__(self, spaces: dict[str, Space]):
        self.spaces = dict(spaces)
        self.shape = None
        self.dtype = None

    def sample(self, key: jax.Array) -> dict[str, Any]:
        keys = jax.random.split(key, len(self.spaces))
        return {name: space.sample(k) for (name, space), k in zip(self.spaces.items(), keys, strict=True)}

    def contains(self, x) -> jax.Array:
        if not isinstance(x, dict) or set(x) != set(self.spaces):
            return jnp.asarray(False)
        result = jnp.asarray(True)
        for name, space in self.spaces.items():
            result = result & space.contains(x[name])
        return result

    def __getitem__(self, name: str) -> Space:
        return self.spaces[name]

    def __repr__(self) -> str:
        inner = ", ".join(f"{k!r}: {v}" for k, v in self.spaces.items())
        return f"Dict({{{inner}}})"


def action_size(space: Space) -> int:
    """What an agent's action head has for ``space``: the choices of a Discrete space, the length of
    a one-dimensional Box."""
    return int(space.n) if isinstance(space, Discrete) else int(space.shape[0])


# --------------------------------------------------------------------------------------------
# Environment protocol
# --------------------------------------------------------------------------------------------


class Environment(Generic[TState, TParams]):
    """Base class: subclasses implement ``reset_env``, ``step_env``, the spaces and ``default_params``.

    ``reset``/``step`` accept ``params=None`` (meaning ``default_params``) for convenience; pass
    params explicitly inside jitted code to avoid rebuilding them at trace time.

    Two questions every env answers, so that adaptors and trainers ask it rather than its type:
    :attr:`num_agents` (how many agents act; :attr:`multi_agent`) and :meth:`max_episode_steps`
    (its time limit).
    """

    num_agents: int = 1
    """How many agents act in one env. 1: observation, action and reward have no agent axis. More
    (the Intersection's 8 vehicle slots): each carries a leading axis of that size, the spaces
    describe one agent, and the episode's flags stay scalars."""

    @property
    def multi_agent(self) -> bool:
        """Whether observations, actions and rewards carry a leading agent axis (``num_agents > 1``)."""
        return self.num_agents > 1

    def max_episode_steps(self, params: TParams | None = None) -> int | None:
        """The step count at which the env truncates an episode, or None when it has none it can
        say. The default reads ``params.max_steps`` (the racing envs' field) if the params have one;
        an env that keeps its limit elsewhere overrides this."""
        params = self.default_params if params is None else params
        limit = getattr(params, "max_steps", None)
        return None if limit is None else int(limit)

    @property
    def default_params(self) -> TParams:
        raise NotImplementedError

    @property
    def name(self) -> str:
        return type(self).__name__

    @property
    def unwrapped(self) -> Environment:
        return self

    def reset(self, key: jax.Array, params: TParams | None = None) -> tuple[Any, TState]:
        params = self.default_params if params is None else params
        return self.reset_env(key, params)

    def step(
        self, key: jax.Array, state: TState, action: Any, params: TParams | None = None
    ) -> tuple[Any, TState, jax.Array, jax.Array, jax.Array, dict[str, Any]]:
        params = self.default_params if params is None else params
        return self.step_env(key, state, action, params)

    def reset_env(self, key: jax.Array, params: TParams) -> tuple[Any, TState]:
        raise NotImplementedError

    def step_env(self, key, state, action, params):
        raise NotImplementedError

    def observation_space(self, params: TParams | None = None) -> Space:
        raise NotImplementedError

    def action_space(self, params: TParams | None = None) -> Space:
        raise NotImplementedError


class Wrapper(Environment):
    """Forwards everything to the wrapped env; subclasses override what they change."""

    def __init__(self, env: Environment):
        self._env = env

    @property
    def unwrapped(self) -> Environment:
        return self._env.unwrapped if isinstance(self._env, Wrapper) else self._env

    @property
    def default_params(self):
        return self._env.default_params

    @property
    def name(self) -> str:
        return self._env.name

    @property
    def num_agents(self) -> int:
        return self._env.num_agents

    def max_episode_steps(self, params=None):
        return self._env.max_episode_steps(params)

    def reset_env(self, key, params):
        return self._env.reset_env(key, params)

    def step_env(self, key, state, action, params):
        return self._env.step_env(key, state, action, params)

    def observation_space(self, params=None):
        return self._env.observation_space(params)

    def action_space(self, params=None):
        return self._env.action_space(params)

    def __getattr__(self, name):
        # Only reached for attributes the wrapper itself lacks (e.g. scenario helpers).
        if name == "_env":
            raise AttributeError(name)
        return getattr(self._env, name)


def _select(done: jax.Array, if_done, if_not):
    """Pytree-wise ``where(done, a, b)`` for a scalar ``done`` (per env, i.e. before vmap)."""
    return jax.tree.map(lambda a, b: jnp.where(done, a, b), if_done, if_not)


class AutoResetWrapper(Wrapper):
    """Resets an env inside ``step`` when an episode ends (terminated or truncated).

    On an ending step the returned ``obs``/``state`` are those of the NEW episode (as in gymnax
    and gymnasium's same-step autoreset), and the observation produced by the ending step is kept
    in ``info["final_obs"]`` (on every other step ``info["final_obs"]`` equals ``obs``), so a
    learner can store ``(obs, action, reward, final_obs, terminated)`` and bootstrap truncations.
    ``reward``/``terminated``/``truncated`` and the other info entries belong to the ending step.
    The step's ``key`` seeds the reset (split so the inner step gets an independent key).

    Cost: under ``vmap`` the reset is computed on every step for every env (``where`` selects),
    so it pays to keep ``reset_env`` cheap (e.g. a track bank rather than track generation).
    """

    def step_env(self, key, state, action, params):
        key_step, key_reset = jax.random.split(key)
        obs_st, state_st, reward, terminated, truncated, info = self._env.step_env(
            key_step, state, action, params
        )
        obs_re, state_re = self._env.reset_env(key_reset, params)
        done = terminated | truncated
        state = _select(done, state_re, state_st)
        obs = _select(done, obs_re, obs_st)
        info = dict(info)
        info["final_obs"] = obs_st
        return obs, state, reward, terminated, truncated, info


class VmapWrapper(Wrapper):
    """Runs ``num_envs`` copies in lock-step via ``jax.vmap`` (params shared, keys split).

    ``reset(key, params)`` and ``step(key, state, action, params)`` take ONE key and batched
    state/actions (leading axis ``num_envs``); outputs all get that leading axis. Equivalent to
    ``jax.vmap(env.step, in_axes=(0, 0, 0, None))`` with ``jax.random.split(key, num_envs)``.
    """

    def __init__(self, env: Environment, num_envs: int):
        super().__init__(env)
        if int(num_envs) <= 0:
            raise ValueError(f"num_envs must be positive, got {num_envs}")
        self.num_envs = int(num_envs)

    def reset_env(self, key, params):
        keys = jax.random.split(key, self.num_envs)
        return jax.vmap(self._env.reset_env, in_axes=(0, None))(keys, params)

    def step_env(self, key, state, action, params):
        keys = jax.random.split(key, self.num_envs)
        return jax.vmap(self._env.step_env, in_axes=(0, 0, 0, None))(keys, state, action, params)

    def sample_actions(self, key, params=None):
        """One random action per env from the single-env action space."""
        space = self._env.action_space(params)
        return jax.vmap(space.sample)(jax.random.split(key, self.num_envs))

    # What a trainer asks of any vector env besides reset and step; a vector env that brings its own
    # tracks (envs.track_feed.FreshTrackEnvs) answers differently, these envs have nothing to add.

    def reset_key(self, env_key: jax.Array, tracks_key: jax.Array) -> jax.Array:
        """Which of a training member's keys seeds :meth:`reset`: here the envs' own key; a vector
        env that feeds its envs tracks takes the member's track stream ``tracks_key`` instead."""
        del tracks_key
        return env_key

    def refill(self, state, agree=lambda flag: flag):
        """Upkeep between scans of steps, away from the per-step hot path, on states with leading
        batch axes; ``agree`` turns a local decision into one shared by every device. None here."""
        del agree
        return state

    def refill_bytes(self, state) -> int:
        """Bytes that :meth:`refill` holds on top of ``state`` while it works (for memory plans)."""
        del state
        return 0

    def counters(self, state) -> dict[str, jax.Array]:
        """Counters worth reporting, from a state (e.g. how many tracks the envs drove so far)."""
        del state
        return {}


def vmap_env(env: Environment, num_envs: int, auto_reset: bool = True) -> VmapWrapper:
    """Convenience: ``VmapWrapper(AutoResetWrapper(env), num_envs)`` (the usual training setup)."""
    return VmapWrapper(AutoResetWrapper(env) if auto_reset else env, num_envs)
