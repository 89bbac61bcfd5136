"""What one iteration of the on-policy family does, for one member (docs/library.md, ``xrl_jax.ppo``):
a rollout of ``steps`` vector steps of its envs as one ``lax.scan``, the advantages of every step by
GAE, then the agent's epochs of minibatch updates on the flattened rollout. Pure and jittable: vmap
it over members, scan it over iterations (PureJaxRL's shape).

The value a step bootstraps from is that of its own next observation, the ending one where an
episode ended (``info["final_obs"]`` of an auto-resetting vector env), not the next episode's first:
so a truncated step is valued from where the car was, and GAE (``xrl_jax.losses.gae``) neither
bootstraps a terminated step nor carries advantages across an episode's end.
"""

from __future__ import annotations

from typing import Any

import jax
from flax import struct

from xrl_jax import losses


@struct.dataclass
class Rollout:
    """A rollout's steps, time-major: (T, E, ...) per leaf."""

    obs: Any
    sample: jax.Array  # what the ratio is taken at: action index, or pre-squash point
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    next_value: jax.Array  # V of the step's own next observation (the ending one where it ended)
    info: Any  # the env's per-step info (the trainer's bookkeeping reads it)


def collect_rollout(agent, venv, env_params, agent_state, venv_state, obs, key, steps: int):
    """``steps`` vector steps acting with ``agent``'s current policy: returns (venv_state, obs after
    the last step, :class:`Rollout`)."""

    def one_step(carry, step_key):
        venv_state, obs = carry
        act_key, env_key = jax.random.split(step_key)
        action, sample, log_prob, value = agent.rollout_act(act_key, agent_state, obs)
        next_obs, venv_state, reward, terminated, truncated, info = venv.step(
            env_key, venv_state, action, env_params
        )
        next_value = agent.value(agent_state.value_params, info["final_obs"])
        step = Rollout(obs, sample, log_prob, value, reward, terminated, truncated, next_value, info)
        return (venv_state, next_obs), step

    (venv_state, obs), rollout = jax.lax.scan(one_step, (venv_state, obs), jax.random.split(key, steps))
    return venv_state, obs, rollout


def rollout_batch(rollout: Rollout, gamma, gae_lambda) -> dict[str, Any]:
    """The agent's update batch: every step of ``rollout`` flattened over (T, E), with its GAE
    advantage and value target (``xrl_jax.ppo.ROLLOUT_KEYS``)."""
    advantage, target = losses.gae(
        rollout.reward, rollout.value, rollout.next_value, rollout.terminated, rollout.truncated,
        gamma, gae_lambda,
    )  # fmt: skip

    def flat(x):
        return x.reshape((-1, *x.shape[2:]))

    batch = {"obs": rollout.obs, "sample": rollout.sample, "log_prob": rollout.log_prob,
             "value": rollout.value, "advantage": advantage, "target": target}  # fmt: skip
    return jax.tree.map(flat, batch)


def iteration(agent, venv, env_params, agent_state, venv_state, obs, key, steps: int):
    """One rollout and the updates on it: returns (agent_state, venv_state, obs, rollout, metrics)."""
    rollout_key, update_key = jax.random.split(key)
    venv_state, obs, rollout = collect_rollout(
        agent, venv, env_params, agent_state, venv_state, obs, rollout_key, steps
    )
    hp = agent_state.hparams
    batch = rollout_batch(rollout, hp.gamma, hp.gae_lambda)
    agent_state, metrics = agent.update(update_key, agent_state, batch)
    return agent_state, venv_state, obs, rollout, metrics
