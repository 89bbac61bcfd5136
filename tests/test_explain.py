"""Explanations are faithful: per-object distributions weighted by the mixture weights are the policy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from network_support import action_size

from xrl_jax.agents import make_agent
from xrl_jax.config import preset
from xrl_jax.distributions import (
    LOG_STD_MAX,
    MIXTURE_LOG_STD_MIN,
    CategoricalMixture,
    SquashedGaussianMixture,
)
from xrl_jax.explain import explain, keep_components, prune
from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation

SHAPE = ENV_OBSERVATIONS["country_road"]
explain_jit = jax.jit(explain, static_argnums=0)


def observations(key, batch=(4,), present=37):
    """Random cone observations with the first `present` slots filled (rows beyond are zeros)."""
    key_state, key_set = jax.random.split(key)
    cones = jax.random.uniform(key_set, (*batch, SHAPE.num_objects, SHAPE.object_features), minval=-1)
    filled = jnp.arange(SHAPE.num_objects) < present
    cones = jnp.where(filled[:, None], cones.at[..., 0].set(1.0), 0.0)
    return {"state": jax.random.uniform(key_state, (*batch, SHAPE.state_dim), minval=-1), "cones_set": cones}


def reference_weights(out) -> np.ndarray:
    """Object weights w_o from the actor's raw output, independently of ``distributions``: the
    softmax of the mixture logits over the present objects (absent ones weigh 0)."""
    logits = np.where(np.asarray(out.present), np.asarray(out.mixture_logits, np.float64), -np.inf)
    weights = np.exp(logits - logits.max(-1, keepdims=True))
    return weights / weights.sum(-1, keepdims=True)


# The mixture agents in the default tier; the baselines' one-component explanations are marked slow.
@pytest.fixture(
    scope="module",
    params=[*(pytest.param(algo, marks=pytest.mark.slow) for algo in ("sac", "dsac")), "xsac", "xdsac"],
)
def agent_and_state(request):
    agent = make_agent(
        preset("smoke", "country_road", request.param), dummy_observation(SHAPE), action_size(request.param)
    )
    return agent, jax.jit(agent.init)(jax.random.PRNGKey(0))


def test_weights_are_a_distribution_over_present_objects(agent_and_state):
    agent, state = agent_and_state
    explanation = explain_jit(agent, state, observations(jax.random.PRNGKey(1), batch=(2, 3)))
    assert explanation.weights.shape[:2] == (2, 3)
    np.testing.assert_allclose(explanation.weights.sum(-1), 1.0, rtol=1e-5)
    if explanation.is_mixture:
        assert explanation.num_objects == SHAPE.num_objects
        assert np.all(np.asarray(explanation.weights)[..., 37:] == 0.0)
        assert np.all(np.asarray(explanation.present)[..., :37])
    else:
        assert explanation.num_objects == 1


def test_discrete_weighted_sum_of_objects_is_the_policy(agent_and_state):
    agent, state = agent_and_state
    if agent.config.algo not in ("dsac", "xdsac"):
        pytest.skip("discrete agents only")
    obs = observations(jax.random.PRNGKey(2))
    explanation = explain_jit(agent, state, obs)
    per_object = np.asarray(explanation.policy.component_probs())
    combined = np.einsum("bo,bon->bn", np.asarray(explanation.weights), per_object)
    np.testing.assert_allclose(combined, explanation.policy.probs(), atol=1e-6)
    if agent.config.algo == "xdsac":  # independently from the raw network outputs
        out = agent.actor_output(state.actor_params, obs)
        independent = np.einsum("bo,bon->bn", reference_weights(out), np.asarray(jax.nn.softmax(out.logits)))
        np.testing.assert_allclose(combined, independent, atol=1e-6)


def test_continuous_weighted_sum_of_object_densities_is_the_policy_density(agent_and_state):
    agent, state = agent_and_state
    if agent.config.algo != "xsac":
        pytest.skip("the continuous mixture agent")
    obs = observations(jax.random.PRNGKey(3))
    explanation = explain_jit(agent, state, obs)
    out = agent.actor_output(state.actor_params, obs)
    actions = jax.random.uniform(jax.random.PRNGKey(4), (4, 3), minval=-0.95, maxval=0.95)
    # Independent density: Σ_o w_o Π_d Normal(atanh a_d; μ, σ) / (1 − a_d²) from the raw outputs.
    pre = np.arctanh(np.asarray(actions, np.float64))[:, None, :]
    mean = np.asarray(out.means, np.float64)[:, :, 0, :]
    std = np.exp(np.clip(np.asarray(out.log_stds, np.float64), MIXTURE_LOG_STD_MIN, LOG_STD_MAX)[:, :, 0, :])
    normal = np.exp(-0.5 * ((pre - mean) / std) ** 2) / (np.sqrt(2 * np.pi) * std)
    per_object = np.prod(normal / (1 - np.asarray(actions, np.float64)[:, None, :] ** 2), axis=-1)
    density = np.sum(reference_weights(out) * per_object, axis=-1)
    ours = np.exp(np.asarray(explanation.policy.log_prob(actions), np.float64))
    np.testing.assert_allclose(ours, density, rtol=2e-3)  # the reference's Jacobian adds 1e-6 to 1 − a²


def total_variation_discrete(p, q):
    return 0.5 * np.abs(np.asarray(p) - np.asarray(q)).sum(-1)


def test_pruning_light_objects_changes_the_discrete_policy_by_at_most_epsilon():
    key_logits, key_mix = jax.random.split(jax.random.PRNGKey(5))
    policy = CategoricalMixture.create(
        jax.random.normal(key_logits, (64, 10, 12)) * 3, jax.random.normal(key_mix, (64, 10)) * 2
    )
    for epsilon in (0.01, 0.05, 0.2):
        pruned, removed = prune(policy, epsilon)
        assert np.all(np.asarray(removed) <= epsilon + 1e-6)
        tv = total_variation_discrete(policy.probs(), pruned.probs())
        assert np.all(tv <= np.asarray(removed) + 1e-6)
        assert np.any(np.asarray(removed) > 0)
        np.testing.assert_allclose(pruned.weights.sum(-1), 1.0, rtol=1e-5)


def test_pruning_light_objects_changes_the_continuous_policy_by_at_most_epsilon():
    key_loc, key_scale, key_mix = jax.random.split(jax.random.PRNGKey(6), 3)
    policy = SquashedGaussianMixture.create(
        jax.random.normal(key_loc, (8, 1)),
        jax.random.uniform(key_scale, (8, 1), minval=-1.5, maxval=0.0),
        jax.random.normal(key_mix, (8,)) * 2,
    )
    grid = jnp.linspace(-1 + 1e-4, 1 - 1e-4, 20001)[:, None]
    step = float(grid[1, 0] - grid[0, 0])
    for epsilon in (0.05, 0.3):
        pruned, removed = prune(policy, epsilon)
        p = np.exp(np.asarray(jax.vmap(policy.log_prob)(grid)))
        q = np.exp(np.asarray(jax.vmap(pruned.log_prob)(grid)))
        tv = 0.5 * np.sum(np.abs(p - q)) * step
        assert 0 < float(removed) <= epsilon
        assert tv <= float(removed) + 1e-3


def test_keeping_nothing_leaves_the_policy_unchanged():
    policy = CategoricalMixture.create(jnp.zeros((3, 4)), jnp.array([0.0, 1.0, 2.0]))
    same = keep_components(policy, jnp.zeros(3, bool))
    np.testing.assert_allclose(same.probs(), policy.probs())
