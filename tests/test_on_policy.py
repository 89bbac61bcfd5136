"""One on-policy iteration (xrl_jax.train.on_policy) on the fast env of tests/fast_env.py: the rollout's
time-major layout, the bootstrap value of a truncated step taken at its ending observation, the
advantages by GAE, and the whole iteration under vmap over members."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fast_env import MAX_STEPS, FastEnv

from envs.core import vmap_env
from xrl_jax import losses
from xrl_jax.config import AgentConfig
from xrl_jax.ppo import make_ppo_agent
from xrl_jax.train import on_policy

EXAMPLE = {"state": jnp.zeros(2), "dots_set": jnp.zeros((4, 3))}
ENVS, STEPS = 4, 2 * MAX_STEPS  # every env truncates at steps 7 and 15


def setup(algo="xdppo"):
    config = AgentConfig(algo=algo, actor_width=32, critic_width=32, fe_width=32, fourier_scale=None,
                         gamma=0.9, clip_norm=0.5, ppo_epochs=2, ppo_minibatches=4)  # fmt: skip
    return make_ppo_agent(config, EXAMPLE, 3), vmap_env(FastEnv(), ENVS)


def test_a_truncated_step_bootstraps_from_its_ending_observation_not_the_next_episodes_first():
    agent, venv = setup()
    state = agent.init(jax.random.PRNGKey(0), EXAMPLE)
    obs, venv_state = venv.reset(jax.random.PRNGKey(1), None)
    _, _, rollout = jax.jit(on_policy.collect_rollout, static_argnums=(0, 1, 7))(
        agent, venv, None, state, venv_state, obs, jax.random.PRNGKey(2), STEPS
    )
    assert rollout.reward.shape == (STEPS, ENVS) and rollout.obs["dots_set"].shape == (STEPS, ENVS, 4, 3)
    truncated = np.asarray(rollout.truncated)
    assert truncated[[MAX_STEPS - 1, STEPS - 1]].all() and truncated.sum() == 2 * ENVS
    value, next_value = np.asarray(rollout.value), np.asarray(rollout.next_value)
    # Within an episode the next observation is the next step's own: the same value (same network,
    # same input; 1e-6 allows another batching of the same product).
    inside = [t for t in range(STEPS - 1) if t != MAX_STEPS - 1]
    np.testing.assert_allclose(next_value[inside], value[[t + 1 for t in inside]], atol=1e-6)
    # At the truncation the ending observation (time feature 1) is valued, not the reset one (time 0).
    assert np.all(np.abs(next_value[MAX_STEPS - 1] - value[MAX_STEPS]) > 1e-6)
    ending_time = np.asarray(rollout.obs["state"][MAX_STEPS - 1, :, 1]) + 1 / MAX_STEPS
    np.testing.assert_allclose(ending_time, 1.0, atol=1e-6)


@pytest.mark.slow  # the GAE itself is tested against NumPy in the default tier (tests/test_losses_ppo.py)
def test_the_update_batch_is_the_flattened_rollout_with_its_gae():
    agent, venv = setup()
    state = agent.init(jax.random.PRNGKey(0), EXAMPLE)
    obs, venv_state = venv.reset(jax.random.PRNGKey(1), None)
    key = jax.random.PRNGKey(3)
    _, _, rollout = on_policy.collect_rollout(agent, venv, None, state, venv_state, obs, key, STEPS)
    batch = on_policy.rollout_batch(rollout, 0.9, 0.95)
    advantage, target = losses.gae(rollout.reward, rollout.value, rollout.next_value, rollout.terminated,
                                   rollout.truncated, 0.9, 0.95)  # fmt: skip
    np.testing.assert_array_equal(np.asarray(batch["advantage"]), np.asarray(advantage).reshape(-1))
    np.testing.assert_array_equal(np.asarray(batch["target"]), np.asarray(target).reshape(-1))
    assert batch["obs"]["dots_set"].shape == (STEPS * ENVS, 4, 3) and batch["sample"].shape == (STEPS * ENVS,)
    # Row t * E + e is env e at step t.
    np.testing.assert_array_equal(np.asarray(batch["log_prob"][ENVS + 2]), np.asarray(rollout.log_prob[1, 2]))


def test_iterations_run_under_vmap_over_members_and_scan_over_iterations():
    agent, venv = setup("xdppo")

    def run(key):
        init_key, reset_key, key = jax.random.split(key, 3)
        state = agent.init(init_key, EXAMPLE)
        obs, venv_state = venv.reset(reset_key, None)

        def body(carry, key):
            state, venv_state, obs = carry
            state, venv_state, obs, rollout, metrics = on_policy.iteration(
                agent, venv, None, state, venv_state, obs, key, STEPS
            )
            return (state, venv_state, obs), (jnp.mean(rollout.reward), metrics)

        keys = jax.random.split(key, 3)
        (state, _, _), (rewards, metrics) = jax.lax.scan(body, (state, venv_state, obs), keys)
        return state, rewards, metrics

    states, rewards, metrics = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 2))
    assert rewards.shape == (2, 3) and np.all(np.isfinite(np.asarray(rewards)))
    assert all(np.all(np.isfinite(np.asarray(m))) for m in metrics.values())
    np.testing.assert_array_equal(np.asarray(states.step), [3 * 2 * 4] * 2)  # iterations x epochs x batches
    assert not np.array_equal(np.asarray(rewards[0]), np.asarray(rewards[1]))  # members differ
