"""One on-policy iteration (xrl_jax.train.on_policy) on the fast env of tests/fast_env.py: the rollout's
time-major layout, the bootstrap value of a truncated step taken at its ending observation, the
advantages by GAE (and the truncation=terminal ablation's), the whole iteration under vmap over
members, and agent slots that sit steps out (the Intersection's): masked out of the losses, ending
their slot's GAE chain."""

import functools

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


def setup(algo="xdppo", truncation="drop"):
    config = AgentConfig(algo=algo, actor_width=32, critic_width=32, fe_width=32, fourier_scale=None,
                         gamma=0.9, clip_norm=0.5, ppo_epochs=2, ppo_minibatches=4,
                         truncation=truncation)  # fmt: skip
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


def test_an_idle_agent_slot_is_masked_out_and_ends_its_slots_advantage_chain():
    """Two agent slots of one env, 4 steps: slot 0 drives throughout; slot 1's vehicle drives steps
    0-1 and ends (terminated at 1), the slot is empty at step 2 and a new vehicle drives step 3. GAE
    by hand: nothing crosses the empty step, whose row the batch masks out."""
    from xrl_jax.train.kinds import KINDS

    gamma, lam = 0.9, 0.8
    acted = np.array([[[1, 1]], [[1, 1]], [[1, 0]], [[1, 1]]], bool)  # (T, E, slots)
    terminated = np.zeros((4, 1, 2), bool)
    terminated[1, 0, 1] = True
    reward = np.arange(8, dtype=np.float32).reshape(4, 1, 2) / 10
    value = np.linspace(0.5, 1.2, 8, dtype=np.float32).reshape(4, 1, 2)
    next_value = np.linspace(1.0, 0.3, 8, dtype=np.float32).reshape(4, 1, 2)
    info = {"acted": acted, "mean_velocity": np.zeros((4, 1), np.float32)}
    read = jax.vmap(KINDS["multi_agent"].read_step)
    record = read(jnp.asarray(reward), jnp.asarray(terminated), jnp.zeros((4, 1, 2), bool), info)
    obs = {"state": jnp.arange(8.0).reshape(4, 1, 2, 1)}
    rollout = on_policy.Rollout(obs, jnp.zeros((4, 1, 2), jnp.int32), jnp.zeros((4, 1, 2)),
                                jnp.asarray(value), jnp.asarray(next_value), record, info)  # fmt: skip
    batch = on_policy.rollout_batch(rollout, gamma, lam, masked=True)
    np.testing.assert_array_equal(np.asarray(batch["mask"]), acted.reshape(-1))
    assert batch["obs"]["state"].shape == (8, 1)
    advantage = np.asarray(batch["advantage"]).reshape(4, 2)
    r, v, nv = reward[:, 0], value[:, 0], next_value[:, 0]
    delta = r + gamma * nv - v
    expected_slot0 = np.zeros(4)
    later = 0.0
    for t in reversed(range(4)):
        later = delta[t, 0] + gamma * lam * later
        expected_slot0[t] = later
    ended = r[1, 1] - v[1, 1]  # terminated: nothing bootstrapped
    expected_slot1 = [delta[0, 1] + gamma * lam * ended, ended, delta[3, 1]]  # step 2 is masked out
    # float32 sums of a few terms of size ~1: a few ulps.
    np.testing.assert_allclose(advantage[:, 0], expected_slot0, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(advantage[[0, 1, 3], 1], expected_slot1, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("truncation", ["bootstrap", "terminal"])
def test_truncation_terminal_values_a_truncated_step_as_an_end(truncation):
    """One env, 3 steps, truncated at step 1. By hand: bootstrap (the family's own) values step 1 from
    its ending observation, terminal (the ablation, PureJaxRL's and rejax's reading) from nothing; in
    both, nothing flows from step 2 (the next episode) back into step 1."""
    gamma, lam = 0.9, 0.8
    reward = np.array([[0.3], [0.5], [0.7]], np.float32)
    value = np.array([[1.0], [1.2], [0.4]], np.float32)
    next_value = np.array([[1.1], [2.0], [0.6]], np.float32)
    truncated = np.array([[False], [True], [False]])
    record = jax.vmap(on_policy.ONE_AGENT_PER_ENV.read_step)(
        jnp.asarray(reward), jnp.zeros((3, 1), bool), jnp.asarray(truncated), {}
    )
    zeros = jnp.zeros((3, 1))
    rollout = on_policy.Rollout({"state": zeros}, zeros.astype(jnp.int32), zeros, jnp.asarray(value),
                                jnp.asarray(next_value), record, {})  # fmt: skip
    batch = on_policy.rollout_batch(rollout, gamma, lam, truncation_is_terminal=truncation == "terminal")
    r, v, nv = reward[:, 0], value[:, 0], next_value[:, 0]
    bootstrap = gamma * nv[1] if truncation == "bootstrap" else 0.0
    a1 = r[1] + bootstrap - v[1]
    expected = [r[0] + gamma * nv[0] - v[0] + gamma * lam * a1, a1, r[2] + gamma * nv[2] - v[2]]
    # float32 sums of a few terms of size ~1: a few ulps.
    np.testing.assert_allclose(np.asarray(batch["advantage"]), expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(batch["target"]), np.asarray(expected) + v, rtol=1e-6, atol=1e-6)


def test_the_iteration_takes_the_truncation_mode_from_the_agents_config(monkeypatch):
    seen = []
    real = on_policy.rollout_batch

    def spy(*args):
        seen.append(args[-1])
        return real(*args)

    monkeypatch.setattr(on_policy, "rollout_batch", spy)
    for truncation in ("drop", "terminal"):
        agent, venv = setup(truncation=truncation)
        state = agent.init(jax.random.PRNGKey(0), EXAMPLE)
        obs, venv_state = venv.reset(jax.random.PRNGKey(1), None)
        one = functools.partial(on_policy.iteration, agent, venv, None, steps=2)
        jax.eval_shape(one, state, venv_state, obs, jax.random.PRNGKey(2))  # traces it, computes nothing
    assert seen == [False, True]


def test_masked_rows_do_not_move_the_update():
    """The same batch with other contents in its masked-out rows: the same agent afterwards, bit for
    bit (their terms enter every sum as exact zeros)."""
    agent, _ = setup()
    state = agent.init(jax.random.PRNGKey(0), EXAMPLE)
    size = 32
    keys = jax.random.split(jax.random.PRNGKey(1), 6)
    batch = {
        "obs": {"state": jax.random.normal(keys[0], (size, 2)),
                "dots_set": jax.random.normal(keys[1], (size, 4, 3))},
        "sample": jax.random.randint(keys[2], (size,), 0, 3),
        "log_prob": jnp.full((size,), -1.1),
        "value": jnp.zeros(size),
        "advantage": jax.random.normal(keys[3], (size,)),
        "target": jax.random.normal(keys[4], (size,)),
        "mask": jnp.arange(size) % 3 != 0,
    }
    other = dict(batch)
    idle = ~batch["mask"]
    other["advantage"] = jnp.where(idle, 50.0, batch["advantage"])
    other["target"] = jnp.where(idle, -7.0, batch["target"])
    other["obs"] = {k: jnp.where(idle.reshape((-1,) + (1,) * (x.ndim - 1)), 3.0, x)
                    for k, x in batch["obs"].items()}
    update = jax.jit(agent.update)
    first, _ = update(keys[5], state, batch)
    second, _ = update(keys[5], state, other)
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), first, second))
    # Without the mask those rows do count: the test can tell.
    unmasked, _ = update(keys[5], state, {k: v for k, v in other.items() if k != "mask"})
    assert not jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), unmasked, first))
