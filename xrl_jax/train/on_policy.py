"""What one iteration of the on-policy family does, for one member (docs/library.md, ``xrl_jax.ppo``):
a rollout of ``steps`` vector steps of its envs as one ``lax.scan``, the advantages of every step by
GAE, then the agent's epochs of minibatch updates on the flattened rollout. Pure and jittable: vmap
it over members, scan it over iterations (PureJaxRL's shape).

The value a step bootstraps from is that of its own next observation, the ending one where an
episode ended (``info["final_obs"]`` of an auto-resetting vector env), not the next episode's first:
so a truncated step is valued from where the car was, and GAE (``xrl_jax.losses.gae``) neither
bootstraps a terminated step nor carries advantages across an episode's end. ``truncation=terminal``
(an ablation) values a truncated step as a terminated one, as PureJaxRL and rejax do.

On the Intersection every agent slot of every env is an actor of the one agent (parameter sharing);
the scenario kind reads which slots acted (:meth:`~xrl_jax.train.kinds.base.ScenarioKind.read_step`),
and an empty slot's steps are masked out of the losses and end the slot's GAE chain.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax import losses
from xrl_jax.train.kinds.base import ScenarioKind, StepRecord
from xrl_jax.train.step import episode_bookkeeping, tree_all_finite

ONE_AGENT_PER_ENV = ScenarioKind()  # the base kind's reading of a step: every env's one agent acting


@struct.dataclass
class Rollout:
    """A rollout's steps, time-major: (T, actors..., ...) per leaf (actors: envs, or envs x agent
    slots)."""

    obs: Any
    sample: jax.Array  # what the ratio is taken at: action index, or pre-squash point
    log_prob: jax.Array
    value: jax.Array
    next_value: jax.Array  # V of the step's own next observation (the ending one where it ended)
    record: StepRecord  # reward, who acted, terminated, truncated, as the scenario kind reads them
    info: Any  # the env's per-step info (the trainer's bookkeeping reads it)

    @property
    def reward(self) -> jax.Array:
        return self.record.reward

    @property
    def terminated(self) -> jax.Array:
        return self.record.terminated

    @property
    def truncated(self) -> jax.Array:
        return self.record.truncated


def collect_rollout(agent, venv, env_params, agent_state, venv_state, obs, key, steps: int,
                    read_step=ONE_AGENT_PER_ENV.read_step):  # fmt: skip
    """``steps`` vector steps acting with ``agent``'s current policy: returns (venv_state, obs after
    the last step, :class:`Rollout`). ``read_step`` is the scenario kind's
    (:meth:`~xrl_jax.train.kinds.base.ScenarioKind.read_step`): on the Intersection every agent slot
    is an actor, and the slots that did not act are marked."""

    def one_step(carry, step_key):
        venv_state, obs = carry
        act_key, env_key = jax.random.split(step_key)
        action, sample, log_prob, value = agent.rollout_act(act_key, agent_state, obs)
        next_obs, venv_state, reward, terminated, truncated, info = venv.step(
            env_key, venv_state, action, env_params
        )
        next_value = agent.value(agent_state.value_params, info["final_obs"])
        record = read_step(reward, terminated, truncated, info)
        step = Rollout(obs, sample, log_prob, value, next_value, record, info)
        return (venv_state, next_obs), step

    (venv_state, obs), rollout = jax.lax.scan(one_step, (venv_state, obs), jax.random.split(key, steps))
    return venv_state, obs, rollout


def rollout_batch(rollout: Rollout, gamma, gae_lambda, masked: bool = False,
                  truncation_is_terminal: bool = False) -> dict[str, Any]:  # fmt: skip
    """The agent's update batch: every step of ``rollout`` flattened over (T, actors...), with its GAE
    advantage and value target (``xrl_jax.ppo.ROLLOUT_KEYS``). With ``masked``, the batch's ``mask``
    says which steps an actor took (an empty agent slot's are weighed out of the losses); such a step
    also ends the slot's GAE chain, so nothing flows across the gap to the next vehicle in the slot.
    With ``truncation_is_terminal`` a truncated step bootstraps nothing, as a terminated one."""
    record = rollout.record
    terminated = record.terminated | record.truncated if truncation_is_terminal else record.terminated
    advantage, target = losses.gae(
        record.reward, rollout.value, rollout.next_value, terminated, record.truncated | ~record.acted,
        gamma, gae_lambda,
    )  # fmt: skip
    step_axes = record.reward.ndim  # T and the actor axes

    def flat(x):
        return x.reshape((-1, *x.shape[step_axes:]))

    batch = {"obs": rollout.obs, "sample": rollout.sample, "log_prob": rollout.log_prob,
             "value": rollout.value, "advantage": advantage, "target": target}  # fmt: skip
    if masked:
        batch["mask"] = record.acted
    return jax.tree.map(flat, batch)


def iteration(agent, venv, env_params, agent_state, venv_state, obs, key, steps: int,
              kind: ScenarioKind = ONE_AGENT_PER_ENV):  # fmt: skip
    """One rollout and the updates on it: returns (agent_state, venv_state, obs, rollout, metrics).
    ``kind``: the scenario kind whose steps these are (default: one agent per env)."""
    rollout_key, update_key = jax.random.split(key)
    venv_state, obs, rollout = collect_rollout(
        agent, venv, env_params, agent_state, venv_state, obs, rollout_key, steps, kind.read_step
    )
    hp = agent_state.hparams
    terminal = agent.config.truncation == "terminal"
    batch = rollout_batch(rollout, hp.gamma, hp.gae_lambda, kind.idle_actors, terminal)
    agent_state, metrics = agent.update(update_key, agent_state, batch)
    return agent_state, venv_state, obs, rollout, metrics


# ---- the trainer's chunk of the on-policy family ------------------------------------------------------


def iteration_metric_shapes(parts):
    """Shapes of the update metrics of one iteration (the chunk report's names and dtypes)."""
    agent, venv, env_params = parts.agent, parts.venv, parts.params

    def metrics(key):
        state = agent.init(key, parts.obs_example)
        obs, venv_state = venv.reset(key, env_params)
        return iteration(agent, venv, env_params, state, venv_state, obs, key, 1, parts.kind)[4]

    return jax.eval_shape(metrics, jax.random.PRNGKey(0))


def member_iteration(parts, state, t):
    """One iteration of a member starting at vector step ``t``, as the chunk scans it: the run state
    after the rollout and its updates (every step's episodes into the bookkeeping, in order), and
    per vector step the outputs the chunk report reads (the update's metrics at the iteration's last
    step, weighted by its minibatch updates, so that the report's average over updates is the mean
    over iterations)."""
    steps, agent = parts.cfg.agent.rollout_steps, parts.agent
    key, iteration_key = jax.random.split(state.key)
    agent_state, venv_state, obs, rollout, metrics = iteration(
        agent, parts.venv, parts.params, state.agent, state.venv_state, state.obs, iteration_key, steps,
        parts.kind,
    )  # fmt: skip

    def bookkeeping(state, record):
        return state.replace(**episode_bookkeeping(parts, state, record)), None

    state = jax.lax.scan(bookkeeping, state, rollout.record)[0]
    state = state.with_venv_state(venv_state, agent=agent_state, obs=obs, key=key)
    updates = parts.cfg.agent.ppo_epochs * parts.cfg.agent.ppo_minibatches
    last = jnp.arange(steps) == steps - 1
    rewards_finite = jnp.all(jnp.isfinite(rollout.reward.reshape(steps, -1)), axis=1)
    observations_finite = jax.vmap(tree_all_finite)(rollout.info["final_obs"])  # per vector step
    outs = {
        **jax.vmap(parts.kind.step_outputs)(rollout.record, rollout.info),
        "metrics": jax.tree.map(lambda m: jnp.where(last, m * updates, 0).astype(m.dtype), metrics),
        "updates": jnp.where(last, updates, 0).astype(jnp.int32),
        "env_nonfinite": (~rewards_finite).astype(jnp.int32) + 2 * (~observations_finite).astype(jnp.int32),
    }
    return state, outs
