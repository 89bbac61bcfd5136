"""The on-policy agents (xrl_jax.ppo): shapes and finiteness under vmap over members, the rollout's
stored log-probability, and the probe task of tests/test_probe.py learned and explained by XPPO and
XDPPO (PPO and DPPO learn it too, in the slow tier)."""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_probe import NUM_ACTIONS, NUM_OBJECTS, STATE_DIM, probe_contexts, probe_reward

from xrl_jax import losses
from xrl_jax.config import ON_POLICY_ALGOS, AgentConfig
from xrl_jax.ppo import ROLLOUT_KEYS, make_ppo_agent

EXAMPLE = {"state": jnp.zeros(STATE_DIM), "objects_set": jnp.zeros((NUM_OBJECTS, 3))}


def in_default_tier(*algos):
    """``ON_POLICY_ALGOS`` as parameters, those not named in the slow tier (each test keeps one or two
    agents in the default tier: the mixtures' code path includes the one-object case)."""
    return [a if a in algos else pytest.param(a, marks=pytest.mark.slow) for a in ON_POLICY_ALGOS]


def ppo_config(algo: str, **changes) -> AgentConfig:
    base = dict(algo=algo, actor_width=32, actor_depth=2, critic_width=32, critic_depth=2,
                feature_extractor="deepset", fe_width=32, fourier_scale=None, actor_lr=1e-3,
                critic_lr=1e-3, gamma=0.0, clip_norm=0.5, ppo_epochs=4, ppo_minibatches=4)  # fmt: skip
    return AgentConfig(**{**base, **changes})


def make(algo: str, **changes):
    discrete = algo in ("dppo", "xdppo")
    return make_ppo_agent(ppo_config(algo, **changes), EXAMPLE, NUM_ACTIONS if discrete else 1), discrete


def bandit_batch(agent, state, key, size, discrete):
    """One rollout of one-step episodes (γ = 0, terminated): the advantage is r − V(s), by GAE."""
    context_key, act_key = jax.random.split(key)
    obs, _, key_signal = probe_contexts(context_key, size, discrete)
    action, sample, log_prob, value = agent.rollout_act(act_key, state, obs)
    reward = probe_reward(action, key_signal, discrete)
    done = jnp.ones((1, size), bool)
    advantage, target = losses.gae(
        reward[None], value[None], jnp.zeros((1, size)), done, ~done, state.hparams.gamma,
        state.hparams.gae_lambda,
    )  # fmt: skip
    batch = {"obs": obs, "sample": sample, "log_prob": log_prob, "value": value,
             "advantage": advantage[0], "target": target[0]}  # fmt: skip
    return batch, reward


@pytest.mark.parametrize("algo", in_default_tier("xdppo"))
def test_rollout_and_update_have_the_right_shapes_and_stay_finite_under_vmap(algo):
    agent, discrete = make(algo)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states = jax.vmap(agent.init)(keys)

    def one_round(state, key):
        batch, _ = bandit_batch(agent, state, key, 32, discrete)
        assert set(batch) == set(ROLLOUT_KEYS)
        return (*agent.update(key, state, batch), batch)

    states, metrics, batch = jax.jit(jax.vmap(one_round))(states, keys)
    sample = np.asarray(batch["sample"])
    if discrete:
        assert sample.shape == (2, 32) and sample.dtype == np.int32 and sample.min() >= 0
    else:
        assert sample.shape == (2, 32, 1)  # the pre-squash point; the env gets tanh of it
    assert np.asarray(batch["value"]).shape == (2, 32)
    assert all(np.all(np.isfinite(np.asarray(v))) for v in metrics.values())
    assert int(states.step[0]) == 4 * 4  # epochs x minibatches
    expected = {"loss_policy", "loss_actor", "loss_value", "clip_fraction", "approx_kl", "entropy_mean",
                "mixture_entropy"}  # fmt: skip
    assert expected <= set(metrics)
    if algo in ("ppo", "dppo"):  # one object: the κ term is zero
        np.testing.assert_array_equal(np.asarray(metrics["mixture_entropy"]), 0.0)
    else:  # four objects: a spread-out start
        assert np.all(np.asarray(metrics["mixture_entropy"]) > 0.5)


@pytest.mark.parametrize("algo", in_default_tier("xppo"))  # the Gaussian ratio is the subtle one
def test_the_stored_log_probability_is_the_policys_at_the_stored_sample(algo):
    """Before any update the ratio is 1: the rollout's log π(sample) equals the policy's own, so the
    first minibatch's clipped surrogate starts from ρ = 1 (same computation: equal to rounding)."""
    agent, discrete = make(algo)
    state = agent.init(jax.random.PRNGKey(1))
    batch, _ = bandit_batch(agent, state, jax.random.PRNGKey(2), 64, discrete)
    pi = agent.policy(state.actor_params, batch["obs"])
    log_ratio = losses.mixture_log_ratio(pi, batch["sample"], batch["log_prob"])
    np.testing.assert_allclose(np.asarray(log_ratio), 0.0, atol=1e-5)


def test_make_ppo_agent_refuses_an_off_policy_algo_and_a_batch_it_cannot_split():
    with pytest.raises(ValueError, match="off-policy"):
        make_ppo_agent(ppo_config("sac"), EXAMPLE, 1)
    agent, _ = make("xppo")
    state = agent.init(jax.random.PRNGKey(0))
    batch, _ = bandit_batch(agent, state, jax.random.PRNGKey(1), 30, False)
    with pytest.raises(ValueError, match="30 transitions cannot be split into 4"):
        agent.update(jax.random.PRNGKey(2), state, batch)
    with pytest.raises(ValueError, match="lacks advantage"):
        agent.update(jax.random.PRNGKey(2), state, {k: v for k, v in batch.items() if k != "advantage"})


def train_bandit(algo: str, rounds: int, seed: int = 0):
    """PPO on fresh probe contexts: every round a rollout of 256 one-step episodes and its epochs."""
    agent, discrete = make(algo)

    def one_round(state, key):
        rollout_key, update_key = jax.random.split(key)
        batch, reward = bandit_batch(agent, state, rollout_key, 256, discrete)
        state, _ = agent.update(update_key, state, batch)
        return state, jnp.mean(reward)

    @jax.jit
    def run(key):
        init_key, train_key, eval_key = jax.random.split(key, 3)
        state = agent.init(init_key)
        state, _ = jax.lax.scan(one_round, state, jax.random.split(train_key, rounds))
        context_key, act_key = jax.random.split(eval_key)
        obs, slot, key_signal = probe_contexts(context_key, 1024, discrete)
        action = agent.act(act_key, state, obs, "eval")
        weights = agent.policy(state.actor_params, obs).weights
        one_object = weights.shape[-1] == 1  # PPO, DPPO: all weight on their one component
        on_informative = 1.0 if one_object else jnp.take_along_axis(weights, slot[:, None], axis=-1)
        return jnp.mean(probe_reward(action, key_signal, discrete)), jnp.mean(on_informative)

    start = time.perf_counter()
    reward, weight = run(jax.random.PRNGKey(seed))
    return {"reward": float(reward), "weight": float(weight), "seconds": time.perf_counter() - start}


# A uniformly random discrete action earns 1/3 on average, a random continuous one about -0.55 (the
# squared error against 0.8·signal, signal uniform in [-1, 1]); the mixture weight on the informative
# one of 4 objects starts at 1/4.
@pytest.mark.parametrize(
    "algo, reward_above", [("xdppo", 0.9), pytest.param("xppo", -0.08, marks=pytest.mark.slow)]
)
def test_xppo_learns_the_probe_and_explains_it_with_the_informative_object(algo, reward_above):
    result = train_bandit(algo, rounds=150)
    assert result["reward"] > reward_above, result
    assert result["weight"] > 0.6, result


@pytest.mark.slow
@pytest.mark.parametrize("algo, reward_above", [("dppo", 0.9), ("ppo", -0.08)])
def test_plain_ppo_learns_the_probe(algo, reward_above):
    result = train_bandit(algo, rounds=150)
    assert result["reward"] > reward_above, result
