"""Closed-form checks of every loss in xrl_jax.losses on tiny hand-made inputs
(docs/algorithms.md §1–§3, §8)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from xrl_jax import losses


def test_huber_quadratic_inside_linear_outside():
    errors = jnp.array([0.0, 0.5, -0.5, 0.999, 1.0, 2.0, -3.0])
    expected = np.array([0.0, 0.125, 0.125, 0.5 * 0.999**2, 0.5, 1.5, 2.5])
    np.testing.assert_allclose(losses.huber(errors), expected, rtol=1e-6)
    np.testing.assert_allclose(losses.squared(errors), 0.5 * np.asarray(errors) ** 2, rtol=1e-6)


def test_critic_loss_huber_vs_l2_mean_over_critics_and_batch():
    q = jnp.array([[1.0, 2.0, 0.0], [0.5, -1.0, 4.0]])
    target = jnp.array([0.5, 0.0, 0.0])
    errors = np.asarray(q - target)  # [[0.5, 2, 0], [0, -1, 4]]
    huber = np.where(np.abs(errors) < 1, 0.5 * errors**2, np.abs(errors) - 0.5)
    loss, metrics = losses.critic_loss(q, target, "huber")
    np.testing.assert_allclose(loss, huber.mean(), rtol=1e-6)
    # the reference's continuous form ½·Σ_j mean_b equals the mean over the (2, B) stack
    np.testing.assert_allclose(loss, 0.5 * huber.mean(axis=1).sum(), rtol=1e-6)
    assert metrics["loss_critic"] == loss
    loss_l2, _ = losses.critic_loss(q, target, "l2")
    np.testing.assert_allclose(loss_l2, (0.5 * errors**2).mean(), rtol=1e-6)
    assert float(loss_l2) > float(loss)  # large errors: L2 grows quadratically
    with pytest.raises(ValueError, match="huber"):
        losses.critic_loss(q, target, "l1")


def test_critic_loss_weight_drops_transitions_and_target_is_constant():
    q = jnp.array([[1.0, 100.0], [1.0, -100.0]])
    target = jnp.array([0.0, 0.0])
    loss, _ = losses.critic_loss(q, target, weight=jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(loss, 0.5, rtol=1e-6)  # only the first transition counts
    loss_none, _ = losses.critic_loss(q, target, weight=jnp.zeros(2))
    assert float(loss_none) == 0.0
    grad_target = jax.grad(lambda y: losses.critic_loss(q, y)[0])(target)
    np.testing.assert_array_equal(grad_target, 0.0)


def test_continuous_target_min_entropy_and_done_masking():
    reward = jnp.array([1.0, 1.0, -1.0])
    terminated = jnp.array([0.0, 1.0, 0.0])
    gamma, alpha = 0.95, 0.2
    next_q = jnp.array([[3.0, 5.0, -2.0], [2.0, 7.0, -4.0]])
    next_log_prob = jnp.array([-1.0, 0.5, 2.0])
    y = losses.continuous_td_target(reward, gamma * (1 - terminated), next_q, next_log_prob, alpha)
    expected = [1 + 0.95 * (2.0 + 0.2), 1.0, -1 + 0.95 * (-4.0 - 0.4)]
    np.testing.assert_allclose(y, expected, rtol=1e-6)
    # the target is a constant
    g = jax.grad(lambda nq: losses.continuous_td_target(reward, 0.9, nq, next_log_prob, alpha).sum())(next_q)
    np.testing.assert_array_equal(g, 0.0)


def test_discrete_target_min_per_action_before_expectation():
    probs = jnp.array([[0.5, 0.5]])
    # per-action min = [0, 0] -> expectation 0; min of expectations would be min(5, 5) = 5
    next_q = jnp.array([[[0.0, 10.0]], [[10.0, 0.0]]])
    y = losses.discrete_td_target(jnp.array([0.0]), jnp.array([1.0]), next_q, probs, 0.0)
    np.testing.assert_allclose(y, [0.0], atol=1e-7)
    y_alpha = losses.discrete_td_target(jnp.array([0.0]), jnp.array([1.0]), next_q, probs, 2.0)
    np.testing.assert_allclose(y_alpha, [2.0 * np.log(2.0)], rtol=1e-6)
    y_done = losses.discrete_td_target(jnp.array([3.0]), jnp.array([0.0]), next_q, probs, 2.0)
    np.testing.assert_allclose(y_done, [3.0])


def test_clipped_entropy_clip_keeps_zero_probabilities_finite():
    probs = jnp.array([[1.0, 0.0, 0.0], [0.25, 0.25, 0.5]])
    np.testing.assert_allclose(losses.clipped_entropy(probs), [0.0, 1.5 * np.log(2.0)], atol=1e-6)
    grad = jax.grad(lambda p: losses.clipped_entropy(p).sum())(probs)
    assert np.all(np.isfinite(grad))


def test_sac_actor_loss_closed_form_uses_min_critic():
    log_prob = jnp.array([-1.0, 0.5])
    q = jnp.array([[2.0, 3.0], [1.0, 4.0]])
    loss, metrics = losses.sac_actor_loss(log_prob, q, 0.5)
    np.testing.assert_allclose(loss, np.mean([0.5 * -1.0 - 1.0, 0.5 * 0.5 - 3.0]), rtol=1e-6)
    np.testing.assert_allclose(metrics["entropy_mean"], 0.25, rtol=1e-6)
    # α is a constant in the actor loss
    g_alpha = jax.grad(lambda a: losses.sac_actor_loss(log_prob, q, a)[0])(0.5)
    assert float(g_alpha) == 0.0


def test_dsac_actor_loss_uses_mean_critic_and_entropy():
    probs = jnp.array([[0.2, 0.8]])
    q = jnp.array([[[1.0, 3.0]], [[3.0, -1.0]]])  # mean = [2, 1], min = [1, -1]
    alpha = 0.1
    loss, metrics = losses.dsac_actor_loss(probs, q, alpha)
    entropy = -(0.2 * np.log(0.2) + 0.8 * np.log(0.8))
    np.testing.assert_allclose(loss, -(0.2 * 2 + 0.8 * 1 + alpha * entropy), rtol=1e-6)
    np.testing.assert_allclose(metrics["entropy_mean"], entropy, rtol=1e-6)


def test_xsac_actor_loss_equals_explicit_sum():
    rng = np.random.default_rng(0)
    weights = np.array([[0.2, 0.5, 0.3, 0.0], [1.0, 0.0, 0.0, 0.0]], dtype=np.float32)
    log_prob = rng.normal(size=(2, 4)).astype(np.float32)
    q = rng.normal(size=(2, 2, 4)).astype(np.float32)
    alpha, kappa = 0.3, 0.01
    loss, metrics = losses.xsac_actor_loss(
        jnp.array(weights), jnp.array(log_prob), jnp.array(q), alpha, kappa
    )
    expected = []
    for b in range(2):
        total = 0.0
        entropy = 0.0
        for k in range(4):
            total += weights[b, k] * (alpha * log_prob[b, k] - min(q[0, b, k], q[1, b, k]))
            if weights[b, k] > 0:
                entropy -= weights[b, k] * np.log(weights[b, k])
        expected.append(total - kappa * entropy)
    np.testing.assert_allclose(loss, np.mean(expected), rtol=1e-5)
    mean_lp = (weights * log_prob).sum(-1)
    np.testing.assert_allclose(metrics["entropy_mean"], -mean_lp.mean(), rtol=1e-5)
    np.testing.assert_allclose(metrics["entropy"], -mean_lp, rtol=1e-5)


def test_xdsac_actor_loss_closed_form_vs_explicit_sum():
    rng = np.random.default_rng(1)
    object_logits = rng.normal(size=(3, 4, 5)).astype(np.float32)  # (B, O, N)
    object_probs = np.exp(object_logits) / np.exp(object_logits).sum(-1, keepdims=True)
    weights = np.array([[0.5, 0.5, 0, 0], [0.1, 0.2, 0.3, 0.4], [1, 0, 0, 0]], dtype=np.float32)
    probs = np.einsum("bo,bon->bn", weights, object_probs)
    q = rng.normal(size=(2, 3, 5)).astype(np.float32)
    alpha, kappa = 0.2, 0.05
    loss, _ = losses.xdsac_actor_loss(jnp.array(probs), jnp.array(weights), jnp.array(q), alpha, kappa)
    expected = 0.0
    for b in range(3):
        value = 0.0
        for a in range(5):
            value += probs[b, a] * (0.5 * (q[0, b, a] + q[1, b, a]) - alpha * np.log(probs[b, a]))
        h_w = -sum(w * np.log(w) for w in weights[b] if w > 0)
        expected += -(value + kappa * h_w)
    np.testing.assert_allclose(loss, expected / 3, rtol=1e-5)


def _xsac_loss_of_logits(logits, kappa):
    weights = jax.nn.softmax(logits, axis=-1)
    log_prob = jnp.zeros_like(weights)
    q = jnp.ones((2, *weights.shape))  # constant critic: only the κ term depends on the weights
    return losses.xsac_actor_loss(weights, log_prob, q, 0.1, kappa)[0]


def _xdsac_loss_of_logits(logits, kappa):
    weights = jax.nn.softmax(logits, axis=-1)
    object_probs = jnp.full((1, 3, 4), 0.25)
    probs = jnp.einsum("bo,bon->bn", weights, object_probs)
    return losses.xdsac_actor_loss(probs, weights, jnp.ones((2, 1, 4)), 0.1, kappa)[0]


@pytest.mark.parametrize("loss_of_logits", [_xsac_loss_of_logits, _xdsac_loss_of_logits])
def test_kappa_term_pushes_weights_towards_uniform(loss_of_logits):
    logits = jnp.array([[2.0, 0.0, -1.0]])
    grad = jax.grad(loss_of_logits)(logits, 0.01)
    step = logits - grad  # one gradient-descent step
    h_before = losses.clipped_entropy(jax.nn.softmax(logits))
    h_after = losses.clipped_entropy(jax.nn.softmax(step))
    assert float(h_after[0]) > float(h_before[0])
    assert float(grad[0, 0]) > 0 > float(grad[0, 2])  # the dominant logit is pushed down
    # κ < 0 (Fig. 8) does the opposite; κ = 0 leaves the weights alone
    grad_neg = jax.grad(loss_of_logits)(logits, -0.01)
    np.testing.assert_allclose(grad_neg, -grad, atol=1e-6)
    np.testing.assert_allclose(jax.grad(loss_of_logits)(logits, 0.0), 0.0, atol=1e-7)


def test_xsac_weights_get_gradient_through_expectation():
    logits = jnp.array([[0.3, -0.2]])
    log_prob = jnp.array([[-1.0, -2.0]])
    q = jnp.array([[[1.0, 3.0]], [[1.0, 3.0]]])

    def loss(lg):
        return losses.xsac_actor_loss(jax.nn.softmax(lg), log_prob, q, 0.1, 0.0)[0]

    grad = jax.grad(loss)(logits)
    # the component with the larger Q must gain weight
    assert float(grad[0, 1]) < 0 < float(grad[0, 0])


@pytest.mark.parametrize("entropy, direction", [(5.0, -1.0), (-5.0, 1.0)])
def test_entropy_coefficient_gradient_sign(entropy, direction):
    """§8 item 10: entropy above target → log α decreases (gradient descent), below → increases."""
    target = 0.0
    ent = jnp.full((4,), entropy)
    loss_fn = lambda la: losses.entropy_coef_loss(la, ent, target)[0]
    grad = jax.grad(loss_fn)(jnp.log(0.1))
    assert np.sign(-float(grad)) == direction
    np.testing.assert_allclose(grad, entropy - target, rtol=1e-6)
    # the reference's continuous form −ℓ·mean(log π + H_target) has the same gradient
    ref = jax.grad(lambda la: -la * jnp.mean(-ent + target))(jnp.log(0.1))
    np.testing.assert_allclose(grad, ref, rtol=1e-6)


def test_polyak_update():
    target = {"a": jnp.array([0.0, 1.0]), "b": {"c": jnp.array(2.0)}}
    online = {"a": jnp.array([1.0, 3.0]), "b": {"c": jnp.array(-2.0)}}
    out = losses.polyak_update(target, online, 0.25)
    np.testing.assert_allclose(out["a"], [0.25, 1.5])
    np.testing.assert_allclose(out["b"]["c"], 1.0)
    same = losses.polyak_update(target, online, 1.0)
    np.testing.assert_allclose(same["a"], online["a"])


def test_losses_jit_and_run_in_float64():
    with jax.enable_x64(True):
        q = jnp.ones((2, 3), dtype=jnp.float64)
        loss, _ = jax.jit(losses.critic_loss, static_argnums=2)(q, jnp.zeros(3, jnp.float64), "huber")
        assert loss.dtype == jnp.float64
        w = jnp.full((3, 2), 0.5, dtype=jnp.float64)
        loss, _ = jax.jit(losses.xsac_actor_loss)(w, jnp.zeros((3, 2)), jnp.zeros((2, 3, 2)), 0.1, 0.1)
        assert loss.dtype == jnp.float64
