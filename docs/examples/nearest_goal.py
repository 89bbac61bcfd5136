"""A toy set-observation env for the mixture agents: reach the nearest of up to 8 goals.

The agent is a point on the plane; 2 to 8 goals lie around it in random slots of an 8-row set. Each
step it moves 0.15 in one of 4 directions (or stays); the reward is how much closer it came to the
nearest goal, plus 1 when it reaches one (within 0.15), which ends the episode; 40 steps truncate
it. Observation: ``{"state": (x, y), "goals_set": (8, 3)}``, a goal's row (present, dx, dy) relative
to the agent, an empty slot all zeros. A well-trained XDSAC agent should put its weight on the
nearest goal: the explanation says which goal it walks to.

Importing this module registers the env as ``nearest_goal`` (``xrl_jax.register_env``), so
``experiments/run.py --import docs/examples/nearest_goal.py --env nearest_goal ...`` trains on it.
Run it to train XDSAC and draw the explanation figure::

    python docs/examples/nearest_goal.py --out /tmp/nearest_goal
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from flax import struct

from envs.core import Box, Dict, Discrete, Environment
from xrl_jax import register_env

SLOTS = 8
MOVES = jnp.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


@struct.dataclass
class NearestGoalParams:
    step_size: float = 0.15
    reach_radius: float = 0.15
    max_steps: int = struct.field(pytree_node=False, default=40)
    min_goals: int = struct.field(pytree_node=False, default=2)


@struct.dataclass
class NearestGoalState:
    position: jax.Array  # (2,)
    goals: jax.Array  # (SLOTS, 2)
    present: jax.Array  # (SLOTS,) bool
    time: jax.Array  # steps taken


class NearestGoal(Environment):
    """Five discrete moves: stay, +x, -x, +y, -y."""

    @property
    def default_params(self) -> NearestGoalParams:
        return NearestGoalParams()

    def reset_env(self, key, params):
        place, count_key, slot_key = jax.random.split(key, 3)
        points = jax.random.uniform(place, (SLOTS + 1, 2), minval=-1.0, maxval=1.0)
        count = jax.random.randint(count_key, (), params.min_goals, SLOTS + 1)
        present = jax.random.permutation(slot_key, jnp.arange(SLOTS) < count)
        state = NearestGoalState(points[0], points[1:], present, jnp.zeros((), jnp.int32))
        return self.observe(state), state

    def step_env(self, key, state, action, params):
        before = self.nearest_distance(state)
        position = state.position + params.step_size * MOVES[action]
        state = state.replace(position=position, time=state.time + 1)
        after = self.nearest_distance(state)
        reached = after < params.reach_radius
        reward = before - after + reached.astype(after.dtype)
        truncated = (state.time >= params.max_steps) & ~reached
        return self.observe(state), state, reward, reached, truncated, {}

    def nearest_distance(self, state) -> jax.Array:
        distances = jnp.linalg.norm(state.goals - state.position, axis=-1)
        return jnp.min(jnp.where(state.present, distances, jnp.inf))

    def observe(self, state):
        relative = (state.goals - state.position) * state.present[:, None]
        rows = jnp.concatenate([state.present[:, None].astype(relative.dtype), relative], axis=-1)
        return {"state": state.position, "goals_set": rows}

    def observation_space(self, params=None):
        return Dict({"state": Box(-jnp.inf, jnp.inf, (2,)), "goals_set": Box(-jnp.inf, jnp.inf, (SLOTS, 3))})

    def action_space(self, params=None):
        return Discrete(len(MOVES))


def make_nearest_goal():
    env = NearestGoal()
    return env, env.default_params


SCENARIO = register_env("nearest_goal", make_nearest_goal, max_episode_steps=40, object_xy=(1, 2))


def main() -> None:
    from pathlib import Path

    from xrl_jax.config import resolve_config
    from xrl_jax.explain.run_figures import FigureRequest, explain_run
    from xrl_jax.train import train

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="the run folder (new)")
    parser.add_argument("--steps", type=int, default=12_000, help="env steps per seed (default 12000)")
    parser.add_argument("--seeds", type=int, default=2)
    args = parser.parse_args()
    settings = {"eval_interval": "2000", "eval_episodes": "32"}
    cfg = resolve_config("nearest_goal", "xdsac", "quick", args.seeds, args.steps, settings)
    summary = train(cfg, args.out)
    print(f"final return IQM {summary['aggregate']['avg_return']['estimate']:.3f}")
    out = Path(args.out)
    request = FigureRequest(
        run=out, out=out / "explanation.png", attributions=out / "explanation.jsonl", episode=2
    )
    print(explain_run(request))


if __name__ == "__main__":
    main()
