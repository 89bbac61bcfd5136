"""PPO's and XPPO's pieces in xrl_jax.losses against plain NumPy references: GAE, the clipped
surrogate and value loss, the mixtures' log-ratio, and the Gaussian mixture's entropy estimator
against quadrature (value and gradient)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from xrl_jax import losses
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture, safe_atanh
from xrl_jax.distributions.gaussian_density import TANH_JACOBIAN_EPS

# float32 against float64 references: each value below is a short sum of terms of size ~1-10, so
# agreement to ~1e-5 relative (a few dozen float32 roundings) is what the computation allows.
RTOL, ATOL = 2e-5, 2e-5


def gae_reference(rewards, values, next_values, terminated, truncated, gamma, lam):
    """The textbook backward loop, one environment column at a time, in float64."""
    steps, columns = rewards.shape
    advantages = np.zeros((steps, columns))
    for column in range(columns):
        later = 0.0
        for t in reversed(range(steps)):
            bootstrap = 0.0 if terminated[t, column] else gamma * next_values[t, column]
            delta = rewards[t, column] + bootstrap - values[t, column]
            if terminated[t, column] or truncated[t, column]:
                later = 0.0
            later = delta + gamma * lam * later
            advantages[t, column] = later
    return advantages, advantages + values


def test_gae_equals_the_backward_loop_with_terminations_and_truncations():
    rng = np.random.default_rng(0)
    shape = (9, 4)
    rewards, values, next_values = (rng.normal(size=shape) for _ in range(3))
    terminated = rng.random(shape) < 0.15
    truncated = ~terminated & (rng.random(shape) < 0.15)
    args = (rewards, values, next_values, terminated, truncated)
    got = jax.jit(losses.gae)(*(jnp.asarray(a) for a in args), 0.99, 0.95)
    want = gae_reference(*args, 0.99, 0.95)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), w, rtol=RTOL, atol=ATOL)


def test_gae_by_hand_a_truncated_step_bootstraps_and_stops_the_recursion():
    """Two steps, γ = 0.5, λ = 1: step 0 truncated (bootstraps V'_0 = 4, passes nothing back from step
    1), step 1 terminated (no bootstrap): A_1 = 2 - 1 = 1; A_0 = 1 + 0.5 * 4 - 3 = 0."""
    advantages, targets = losses.gae(
        jnp.array([1.0, 2.0]), jnp.array([3.0, 1.0]), jnp.array([4.0, 9.0]),
        jnp.array([False, True]), jnp.array([True, False]), 0.5, 1.0,
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(advantages), [0.0, 1.0])
    np.testing.assert_allclose(np.asarray(targets), [3.0, 2.0])


def test_gae_vmaps_over_seeds():
    rng = np.random.default_rng(1)
    rewards = jnp.asarray(rng.normal(size=(3, 6, 2)), jnp.float32)  # seeds, time, envs
    flags = jnp.zeros((3, 6, 2), bool)
    batched, _ = jax.vmap(losses.gae, in_axes=(0, 0, 0, 0, 0, None, None))(
        rewards, rewards * 0.5, rewards * 0.25, flags, flags, 0.9, 0.8
    )
    single, _ = losses.gae(rewards[1], rewards[1] * 0.5, rewards[1] * 0.25, flags[1], flags[1], 0.9, 0.8)
    np.testing.assert_allclose(np.asarray(batched[1]), np.asarray(single), rtol=RTOL, atol=ATOL)


def test_normalized_advantages_have_zero_mean_and_unit_spread_over_used_entries():
    advantages = jnp.array([1.0, 2.0, 3.0, 100.0])
    used = jnp.array([1.0, 1.0, 1.0, 0.0])
    out = np.asarray(losses.normalize_advantages(advantages, used))[:3]
    np.testing.assert_allclose([out.mean(), out.std()], [0.0, 1.0], atol=1e-5)
    assert np.all(np.asarray(losses.normalize_advantages(jnp.full(5, 7.0))) == 0.0)  # constant: no NaN


def test_clipped_surrogate_equals_the_formula_and_its_gradient_stops_where_clipped():
    rng = np.random.default_rng(2)
    log_ratio = rng.normal(scale=0.3, size=64)
    advantages = rng.normal(size=64)
    eps = 0.2
    ratio = np.exp(log_ratio)
    want = -np.mean(np.minimum(ratio * advantages, np.clip(ratio, 1 - eps, 1 + eps) * advantages))
    loss, metrics = losses.ppo_policy_loss(jnp.asarray(log_ratio), jnp.asarray(advantages), eps)
    np.testing.assert_allclose(float(loss), want, rtol=RTOL, atol=ATOL)
    np.testing.assert_allclose(float(metrics["clip_fraction"]), np.mean(np.abs(ratio - 1) > eps), atol=1e-7)
    np.testing.assert_allclose(float(metrics["approx_kl"]), np.mean(ratio - 1 - log_ratio), rtol=1e-4)
    grad = np.asarray(jax.grad(lambda lr: losses.ppo_policy_loss(lr, jnp.asarray(advantages), eps)[0])(
        jnp.asarray(log_ratio, jnp.float32)))  # fmt: skip
    # d/dlogρ of −min(ρA, clip(ρ)A)/n: −ρA/n where the unclipped term is the smaller, 0 where clipping
    # binds (ρ beyond 1 + ε with A > 0, or below 1 − ε with A < 0).
    binds = ((ratio > 1 + eps) & (advantages > 0)) | ((ratio < 1 - eps) & (advantages < 0))
    np.testing.assert_allclose(grad, np.where(binds, 0.0, -ratio * advantages / 64), rtol=1e-4, atol=1e-7)
    assert binds.any() and (~binds).any()


def test_value_loss_plain_and_clipped():
    values, old, targets = np.array([1.0, 2.0, 0.0]), np.array([0.0, 2.5, 0.1]), np.array([3.0, 2.0, -1.0])
    plain, _ = losses.ppo_value_loss(jnp.asarray(values), jnp.asarray(old), jnp.asarray(targets))
    np.testing.assert_allclose(float(plain), 0.5 * np.mean((values - targets) ** 2), rtol=RTOL)
    clipped, _ = losses.ppo_value_loss(jnp.asarray(values), jnp.asarray(old), jnp.asarray(targets), 0.2)
    moved = old + np.clip(values - old, -0.2, 0.2)
    want = 0.5 * np.mean(np.maximum((values - targets) ** 2, (moved - targets) ** 2))
    np.testing.assert_allclose(float(clipped), want, rtol=RTOL)


def _softmax(x):
    shifted = np.exp(x - x.max(-1, keepdims=True))
    return shifted / shifted.sum(-1, keepdims=True)


def _categorical_reference(action_logits, mixture_logits, present, action):
    """log Σ_o w_o q_o(a) with w the softmax over present objects, in float64."""
    weights = _softmax(np.where(present, mixture_logits, -np.inf))  # (B, O)
    at_action = _softmax(action_logits)[np.arange(len(action)), :, action]  # q_o(a_b): (B, O)
    return np.log(np.sum(weights * at_action, axis=-1))


def test_categorical_mixture_log_ratio_is_the_exact_mixture_log_ratio():
    rng = np.random.default_rng(3)
    batch, objects, actions = 5, 4, 3
    old_logits, new_logits = rng.normal(size=(2, batch, objects, actions))
    old_mix, new_mix = rng.normal(size=(2, batch, objects))
    present = rng.random((batch, objects)) < 0.7
    present[:, 0] = True
    action = rng.integers(0, actions, size=batch)
    old = CategoricalMixture.create(jnp.asarray(old_logits), jnp.asarray(old_mix), jnp.asarray(present))
    new = CategoricalMixture.create(jnp.asarray(new_logits), jnp.asarray(new_mix), jnp.asarray(present))
    got = losses.mixture_log_ratio(new, jnp.asarray(action), old.log_prob(jnp.asarray(action)))
    want = _categorical_reference(new_logits, new_mix, present, action) - _categorical_reference(
        old_logits, old_mix, present, action
    )
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-4, atol=1e-5)


def _gaussian_mixture_log_density(u, loc, log_scale, weights):
    """log Σ_k w_k N(u; μ_k, σ_k) over a diagonal Gaussian per component, float64; u (B, A)."""
    z = (u[:, None, :] - loc) / np.exp(log_scale)
    per = np.sum(-0.5 * z**2 - log_scale - 0.5 * np.log(2 * np.pi), axis=-1)
    top = per.max(-1, keepdims=True)
    return np.log(np.sum(weights * np.exp(per - top), axis=-1)) + top[:, 0]


def test_gaussian_mixture_log_ratio_is_exact_from_the_pre_squash_point_even_where_tanh_saturates():
    """The ratio of the stored pre-squash point: the tanh Jacobian cancels, and at u = 12 (float32's
    tanh(12) is within 2.4e-7 of 1, whose atanh is at most ~8: the action could not give u back) the
    ratio is still the mixture densities' ratio at u."""
    rng = np.random.default_rng(4)
    batch, components, dims = 6, 3, 2
    loc_old, loc_new = rng.normal(size=(2, batch, components, dims))
    scale_old, scale_new = rng.normal(scale=0.3, size=(2, batch, components, dims))
    logit_old, logit_new = rng.normal(size=(2, batch, components))
    old = SquashedGaussianMixture.create(jnp.asarray(loc_old), jnp.asarray(scale_old), jnp.asarray(logit_old))
    new = SquashedGaussianMixture.create(jnp.asarray(loc_new), jnp.asarray(scale_new), jnp.asarray(logit_new))
    u, old_log_prob = old.sample_pre_squash_and_log_prob(jax.random.PRNGKey(0))
    u = u.at[0, 0].set(12.0)
    old_log_prob = old.log_prob_pre_squash(u)
    assert float(safe_atanh(jnp.tanh(u[0, 0]))) < 10.0
    got = np.asarray(losses.mixture_log_ratio(new, u, old_log_prob))

    u64 = np.asarray(u, np.float64)
    want = _gaussian_mixture_log_density(u64, loc_new, np.asarray(new.log_scale), _softmax(logit_new)) - (
        _gaussian_mixture_log_density(u64, loc_old, np.asarray(old.log_scale), _softmax(logit_old))
    )
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    assert np.all(np.isfinite(got))
    with pytest.raises(TypeError, match="CategoricalMixture or SquashedGaussianMixture"):
        losses.mixture_log_ratio(object(), u, old_log_prob)


# A 1-D squashed mixture whose entropy quadrature can do: moderate means and scales keep the action
# away from ±1, where the density's 1e-6 Jacobian floor would matter.
LOC, LOG_SCALE, LOGITS = [[-0.8], [0.1], [0.9]], [[-0.7], [-1.2], [-0.4]], [0.3, -0.5, 0.1]


def _quadrature_entropy(loc, log_scale, logits):
    """H of a = tanh(u), u ~ Σ_k w_k N(μ_k, σ_k): −∫ p_u(u)·[log p_u(u) − log(1 − tanh²u + ε)] du on a
    fine grid (trapezoid; the density is smooth and negligible beyond ±8)."""
    grid = jnp.linspace(-8.0, 8.0, 16001)
    weights = jax.nn.softmax(logits)
    z = (grid[:, None] - loc[:, 0]) / jnp.exp(log_scale[:, 0])
    density = jnp.sum(weights * jnp.exp(-0.5 * z**2 - log_scale[:, 0]) / jnp.sqrt(2 * jnp.pi), axis=-1)
    log_jacobian = jnp.log(1.0 - jnp.tanh(grid) ** 2 + TANH_JACOBIAN_EPS)
    integrand = -density * (jnp.log(density + 1e-30) - log_jacobian)
    return jnp.trapezoid(integrand, grid)


def test_the_gaussian_mixture_entropy_estimate_is_unbiased_in_value_and_gradient():
    """Mean of 4,000 estimates against quadrature, and the mean of their gradients with respect to the
    mixture logits and the means against the quadrature entropy's own gradient: each within four
    standard errors of its Monte Carlo mean (the spread measured from the same draws)."""
    params = (jnp.array(LOC), jnp.array(LOG_SCALE), jnp.array(LOGITS))

    def estimate(params, key):
        loc, log_scale, logits = params
        pi = SquashedGaussianMixture.create(loc, log_scale, logits, log_std_min=-5.0)
        return pi.entropy_estimate(key)

    keys = jax.random.split(jax.random.PRNGKey(7), 4000)
    values, grads = jax.vmap(jax.value_and_grad(estimate), in_axes=(None, 0))(params, keys)
    exact, exact_grad = jax.value_and_grad(lambda p: _quadrature_entropy(*p))(params)
    values = np.asarray(values)
    spread = values.std() / np.sqrt(len(values))
    assert abs(values.mean() - float(exact)) <= 4 * spread, (values.mean(), exact)
    for name, got, want in zip(("loc", "log_scale", "logits"), grads, exact_grad, strict=True):
        got = np.asarray(got)
        spread = got.std(axis=0) / np.sqrt(len(got)) + 1e-4  # + quadrature's own error
        assert np.all(np.abs(got.mean(axis=0) - np.asarray(want)) <= 4 * spread), (name, got.mean(0), want)


def test_xppo_actor_loss_adds_the_entropy_bonus_and_the_kappa_term_and_ppo_is_one_object():
    log_ratio, advantages = jnp.array([0.1, -0.2]), jnp.array([1.0, -1.0])
    entropy, weights = jnp.array([0.5, 0.7]), jnp.array([[0.5, 0.5], [1.0, 0.0]])
    surrogate, _ = losses.ppo_policy_loss(log_ratio, advantages, 0.2)
    loss, metrics = losses.xppo_actor_loss(log_ratio, advantages, entropy, weights, 0.2, 0.01, 0.1)
    weights_entropy = np.array([np.log(2.0), 0.0])
    want = float(surrogate) - 0.01 * 0.6 - 0.1 * weights_entropy.mean()
    np.testing.assert_allclose(float(loss), want, rtol=RTOL)
    np.testing.assert_allclose(float(metrics["mixture_entropy"]), weights_entropy.mean(), rtol=RTOL)
    one, _ = losses.xppo_actor_loss(log_ratio, advantages, entropy, jnp.ones((2, 1)), 0.2, 0.01, 0.1)
    np.testing.assert_allclose(float(one), float(surrogate) - 0.01 * 0.6, rtol=RTOL)
