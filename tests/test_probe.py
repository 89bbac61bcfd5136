"""Probe task: XSAC and XDSAC must learn a contextual bandit AND explain it with the right object.

The observation is a set of objects ``[present, is_informative, signal]`` (plus a noise state
vector). Exactly one object, at a random slot, is flagged informative; its signal alone decides
the best action, every other object's signal is noise. γ = 0 and every episode lasts one step,
so Q(s, a) is the immediate reward. A mixture policy solves the task only by putting its weight
on the informative object, which is what the explanation should then show.
"""

import time

import jax
import jax.numpy as jnp
import pytest

from xrl_jax.agents import make_agent
from xrl_jax.config import AgentConfig

NUM_OBJECTS = 4
STATE_DIM = 2
NUM_ACTIONS = 3  # discrete probe
BATCH = 64
PROBE_STEPS = 800  # gradient steps (each on 64 fresh contexts); compilation dominates the run time


def probe_contexts(key, batch: int, discrete: bool):
    """Observations and the informative slot / its signal (jittable)."""
    slot_key, signal_key, noise_key, state_key = jax.random.split(key, 4)
    slot = jax.random.randint(slot_key, (batch,), 0, NUM_OBJECTS)
    informative = jax.nn.one_hot(slot, NUM_OBJECTS)
    if discrete:
        signal = jax.random.randint(signal_key, (batch, NUM_OBJECTS), 0, NUM_ACTIONS) - 1.0
    else:
        signal = jax.random.uniform(signal_key, (batch, NUM_OBJECTS), minval=-1.0, maxval=1.0)
    del noise_key
    objects = jnp.stack([jnp.ones((batch, NUM_OBJECTS)), informative, signal], axis=-1)
    obs = {"state": jax.random.normal(state_key, (batch, STATE_DIM)), "objects_set": objects}
    key_signal = jnp.sum(informative * signal, axis=-1)
    return obs, slot, key_signal


def probe_reward(action, key_signal, discrete: bool):
    if discrete:
        return (action == (key_signal + 1).astype(jnp.int32)).astype(jnp.float32)
    return -jnp.square(action[..., 0] - 0.8 * key_signal)


def probe_config(algo: str) -> AgentConfig:
    return AgentConfig(
        algo=algo,
        actor_width=32,
        actor_depth=2,
        critic_width=32,
        critic_depth=2,
        feature_extractor="deepset",
        fe_width=32,
        fourier_scale=None,
        actor_lr=1e-3,
        critic_lr=1e-3,
        gamma=0.0,
        tau=0.05,
    )


def train_probe(algo: str, steps: int, seed: int = 0):
    """Train on fresh contexts every step (no buffer needed for a bandit); return eval statistics."""
    discrete = algo == "xdsac"
    example = {"state": jnp.zeros(STATE_DIM), "objects_set": jnp.zeros((NUM_OBJECTS, 3))}
    agent = make_agent(probe_config(algo), example, NUM_ACTIONS if discrete else 1)

    def train_step(state, key):
        context_key, act_key, update_key = jax.random.split(key, 3)
        obs, _, key_signal = probe_contexts(context_key, BATCH, discrete)
        action = agent.act(act_key, state, obs, "train")
        reward = probe_reward(action, key_signal, discrete)
        batch = {
            "obs": obs,
            "action": action,
            "reward": reward,
            "next_obs": obs,
            "terminated": jnp.ones(BATCH, bool),
            "truncated": jnp.zeros(BATCH, bool),
        }
        state, metrics = agent.update(update_key, state, batch)
        return state, metrics["loss_critic"]

    @jax.jit
    def run(key):
        init_key, train_key, eval_key = jax.random.split(key, 3)
        state = agent.init(init_key, example)
        state, _ = jax.lax.scan(train_step, state, jax.random.split(train_key, steps))
        context_key, act_key = jax.random.split(eval_key)
        obs, slot, key_signal = probe_contexts(context_key, 1024, discrete)
        action = agent.act(act_key, state, obs, "eval")
        weights = agent.policy(state.actor_params, obs).weights  # (B, O·C) = (B, O) for C = 1
        weight_on_informative = jnp.take_along_axis(weights, slot[:, None], axis=-1)[:, 0]
        return jnp.mean(probe_reward(action, key_signal, discrete)), jnp.mean(weight_on_informative)

    start = time.perf_counter()
    reward, weight = run(jax.random.PRNGKey(seed))
    reward, weight = float(reward), float(weight)
    return {"reward": reward, "weight": weight, "seconds": time.perf_counter() - start}


def test_probe_contexts_have_one_informative_object():
    obs, slot, key_signal = probe_contexts(jax.random.PRNGKey(0), 16, discrete=True)
    flags = obs["objects_set"][..., 1]
    assert jnp.all(jnp.sum(flags, axis=-1) == 1)
    assert jnp.all(flags[jnp.arange(16), slot] == 1)
    assert jnp.all(probe_reward((key_signal + 1).astype(jnp.int32), key_signal, True) == 1)


def test_xsac_learns_probe_and_explains_with_the_informative_object():
    result = train_probe("xsac", steps=PROBE_STEPS)
    print("xsac probe", result)
    # ignoring the informative object scores at best −E[(0.8 s)²] ≈ −0.21; uniform random ≈ −0.55
    assert result["reward"] > -0.08, result
    assert result["weight"] > 0.6, result


def test_xdsac_learns_probe_and_explains_with_the_informative_object():
    result = train_probe("xdsac", steps=PROBE_STEPS)
    print("xdsac probe", result)
    # chance level is 1/3
    assert result["reward"] > 0.9, result
    assert result["weight"] > 0.6, result


@pytest.mark.slow
@pytest.mark.optimised
@pytest.mark.parametrize("algo", ["xsac", "xdsac"])
def test_probe_other_seeds(algo):
    for seed in (1, 2):
        result = train_probe(algo, steps=3000, seed=seed)
        print(algo, seed, result)
        assert result["weight"] > 0.6, result
