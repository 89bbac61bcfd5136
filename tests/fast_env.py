"""A trivial env for the host-side tests (CLI, run folder, resume, trackers, report, explain), as Brax
tests its trainers on its "fast" env: its step is a few additions, so a smoke run of it compiles the
agent and little else, in about half the time of a scenario's (the car's 20 sub-steps dominate those).

A point moves along a line; four slots hold up to four dots ahead of it or behind it. Each step the
agent moves left, stays or moves right; the reward is how much closer it came to the nearest dot.
Episodes are truncated after ``MAX_STEPS`` steps. Observation ``{"state": (position, time),
"dots_set": (4, 3)}``, a dot's row ``(present, dx, 0)``, present rows first. Registered as ``fast`` by
:func:`register` (``run.py --import tests/fast_env.py`` registers it in a child process).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from envs.core import Box, Dict, Discrete, Environment

NAME, SLOTS, MAX_STEPS = "fast", 4, 8


@struct.dataclass
class FastState:
    position: jax.Array  # ()
    dots: jax.Array  # (SLOTS,) positions
    present: jax.Array  # (SLOTS,) bool, present slots first
    time: jax.Array  # steps taken


class FastEnv(Environment):
    """Three discrete moves: left, stay, right (0.25 each)."""

    @property
    def default_params(self):
        return None

    def reset_env(self, key, params):
        place, count_key = jax.random.split(key)
        dots = jax.random.uniform(place, (SLOTS,), minval=-1.0, maxval=1.0)
        present = jnp.arange(SLOTS) < jax.random.randint(count_key, (), 1, SLOTS + 1)
        state = FastState(jnp.zeros(()), dots, present, jnp.zeros((), jnp.int32))
        return self.observe(state), state

    def step_env(self, key, state, action, params):
        before = self.nearest(state)
        state = state.replace(position=state.position + 0.25 * (action - 1), time=state.time + 1)
        reward = before - self.nearest(state)
        truncated = state.time >= MAX_STEPS
        return self.observe(state), state, reward, jnp.zeros((), bool), truncated, {}

    def nearest(self, state):
        return jnp.min(jnp.where(state.present, jnp.abs(state.dots - state.position), 2.0))

    def observe(self, state):
        offsets = (state.dots - state.position) * state.present
        present = state.present.astype(offsets.dtype)
        rows = jnp.stack([present, offsets, jnp.zeros_like(offsets)], axis=-1)
        return {"state": jnp.stack([state.position, state.time / MAX_STEPS]), "dots_set": rows}

    def observation_space(self, params=None):
        return Dict({"state": Box(-jnp.inf, jnp.inf, (2,)), "dots_set": Box(-jnp.inf, jnp.inf, (SLOTS, 3))})

    def action_space(self, params=None):
        return Discrete(3)


def make_fast_env():
    env = FastEnv()
    return env, env.default_params


def register():
    """Register the env as ``fast`` (again: registering replaces) and return its scenario facts."""
    from xrl_jax import register_env

    return register_env(NAME, make_fast_env, max_episode_steps=MAX_STEPS, object_xy=(1, 2))


SCENARIO = register()
