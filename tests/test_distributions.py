"""Mixture distributions (docs/algorithms.md §3, §7.3, §8 items 1-8; paper eq. 3-10).

Closed forms, an independent probability-space implementation of the reference formula (§3.2),
grid quadrature, Monte-Carlo statistics and gradient checks. Jitted functions are module-level
and shapes are reused, so that each compiles once or twice for the whole file.
"""

from functools import partial

import distrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import ndtr

from xrl_jax.distributions import (
    ABSENT_LOG_WEIGHT,
    LOG_STD_MAX,
    MIXTURE_LOG_STD_MIN,
    CategoricalMixture,
    SquashedGaussianMixture,
    clip_log_std,
    clipped_entropy,
    masked_logits,
    masked_softmax,
    sample_slot,
    squashed_gaussian,
)

GM = SquashedGaussianMixture

# ---------------------------------------------------------------------------------------------
# Jitted entry points shared by the tests
# ---------------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames="floor")
def gm_log_prob(loc, log_scale, logits, mask, action, floor=False):
    return GM.create(loc, log_scale, logits, mask).log_prob(action, floor_density=floor)


@partial(jax.jit, static_argnames="num")
def gm_samples(loc, log_scale, logits, mask, key, num):
    """``num`` ancestral draws and ``num`` per-component draws, with their log densities."""
    pi = GM.create(loc, log_scale, logits, mask)
    keys = jax.random.split(key, 2 * num)
    actions, components = jax.vmap(pi.sample_with_component)(keys[:num])
    per_component, per_component_log_probs = jax.vmap(partial(pi.sample_per_component, floor_density=False))(
        keys[num:]
    )
    return {
        "actions": actions,
        "components": components,
        "log_probs": jax.vmap(pi.log_prob)(actions),
        "per_component": per_component,
        "per_component_log_probs": per_component_log_probs,
        "per_component_direct": jax.vmap(pi.log_prob)(per_component),
    }


@jax.jit
def gm_everything(loc, log_scale, logits, mask, action, key):
    """Every output of the Gaussian mixture (standard shapes (3, 5, 3), action (3, 3))."""
    pi = GM.create(loc, log_scale, logits, mask)
    return {
        "weights": pi.weights,
        "log_weights": pi.log_weights,
        "log_scale": pi.log_scale,
        "log_prob": pi.log_prob(action),
        "log_prob_floor": pi.log_prob(action, floor_density=True),
        "component_log_prob": pi.component_log_prob(action),
        "marginal": pi.component_marginal_log_prob(action),
        "distrax_components": pi.components_distrax().log_prob(action[..., None, :]),
        "sample": pi.sample_with_component(key),
        "sample_and_log_prob": pi.sample_and_log_prob(key),
        "per_component": pi.sample_per_component(key),
        "mode": pi.approximate_mode(),
        "entropy": pi.weights_entropy(),
    }


def actor_objective(loc, log_scale, logits, mask, key, kappa=1e-3, floor=True):
    """Shape of the XSAC actor loss (§3.4) with a made-up critic Q(a) = -|a - 0.3|²."""
    pi = GM.create(loc, log_scale, logits, mask)
    actions, log_probs = pi.sample_per_component(key, floor_density=floor)
    q = -jnp.sum(jnp.square(actions - 0.3), axis=-1)
    per_sample = jnp.sum(pi.weights * (0.2 * log_probs - q), axis=-1) - kappa * pi.weights_entropy()
    return jnp.mean(per_sample)


gm_objective_grad = jax.jit(jax.grad(actor_objective, argnums=(0, 1, 2)))


@jax.jit
def weights_and_grad(logits, mask, cotangent):
    def weighted(lg):
        return jnp.sum(masked_softmax(lg, mask) * cotangent)

    return masked_softmax(logits, mask), jax.grad(weighted)(logits)


@jax.jit
def cat_summary(component_logits, logits, mask, actions):
    pi = CategoricalMixture.create(component_logits, logits, mask)
    return {
        "weights": pi.weights,
        "probs": pi.probs(),
        "log_probs": pi.log_probs(),
        "log_prob": pi.log_prob(actions),
        "component_probs": pi.component_probs(),
        "distrax_probs": pi.to_distrax().probs,
        "distrax_components": pi.components_distrax().probs,
        "entropy": pi.entropy(),
        "weights_entropy": pi.weights_entropy(),
        "mode": pi.mode(),
    }


@partial(jax.jit, static_argnames="num")
def cat_samples(component_logits, logits, mask, key, num):
    pi = CategoricalMixture.create(component_logits, logits, mask)
    return jax.vmap(pi.sample_with_component)(jax.random.split(key, num))


def xdsac_like_objective(component_logits, logits, mask, q, kappa):
    """Closed-form discrete objective (eq. 4 + 10) to minimise, as in §2.4."""
    pi = CategoricalMixture.create(component_logits, logits, mask)
    return -jnp.sum(jnp.sum(pi.probs() * q, -1) + 0.1 * pi.entropy() + kappa * pi.weights_entropy())


cat_objective_grad = jax.jit(jax.grad(xdsac_like_objective, argnums=(0, 1)))


# ---------------------------------------------------------------------------------------------
# Independent references
# ---------------------------------------------------------------------------------------------


def np_masked_softmax(logits, mask):
    logits = np.where(mask, logits, -np.inf)
    shifted = np.exp(logits - logits.max(-1, keepdims=True))
    return shifted / shifted.sum(-1, keepdims=True)


def reference_log_prob(action, loc, log_scale, weights, floor=False):
    """The reference's probability-space formula (§3.2), in numpy in the inputs' dtype:
    products of univariate pdfs, weighted sum, then the log."""
    u = np.arctanh(action)[..., None, :]
    sigma = np.exp(np.clip(log_scale, MIXTURE_LOG_STD_MIN, LOG_STD_MAX))
    pdf = np.exp(-0.5 * ((u - loc) / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi).astype(sigma.dtype))
    p_u = np.sum(weights * np.prod(pdf, axis=-1), axis=-1)
    correction = np.prod(1 - action**2 + 1e-6, axis=-1)
    with np.errstate(divide="ignore"):
        if floor:
            return np.log(np.maximum(p_u, 1e-10)) - np.log(correction)
        return np.log(p_u / correction)


def random_mixture(seed, batch=(3,), k=5, a=3, present_prob=0.7):
    rng = np.random.default_rng(seed)
    loc = rng.normal(0, 1, (*batch, k, a)).astype(np.float32)
    log_scale = rng.uniform(-2.0, 0.3, (*batch, k, a)).astype(np.float32)
    logits = rng.normal(0, 1.5, (*batch, k)).astype(np.float32)
    mask = rng.random((*batch, k)) < present_prob
    mask[..., 0] = True
    return loc, log_scale, logits, mask


# ---------------------------------------------------------------------------------------------
# Mixture weights: §3.1, invariants §8 items 1-2
# ---------------------------------------------------------------------------------------------


def test_masked_softmax_is_a_softmax_over_present_slots():
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 3, (4, 6)).astype(np.float32)
    logits[0, 3], logits[1, 1], logits[2, 0] = 1e4, -1e4, 1e4
    mask = rng.random((4, 6)) < 0.5
    mask[:, 2] = True
    mask[3] = False  # no present slot: uniform fallback
    weights, _ = weights_and_grad(logits, mask, np.ones((4, 6), np.float32))
    weights = np.asarray(weights)
    assert np.all(weights >= 0)
    np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-6)
    assert np.all(weights[:3][~mask[:3]] == 0.0)
    np.testing.assert_allclose(weights[:3], np_masked_softmax(logits[:3], mask[:3]), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(weights[3], np.full(6, 1 / 6), rtol=1e-6)


def test_masked_softmax_gradient_finite_and_zero_on_absent():
    logits = np.array([1e4, 0.5, -1e4, 1e4, -1e4, 1e20], np.float32)[None].repeat(4, 0)
    logits[1, 0] = -1e4  # absent logits of either sign or absurdly large
    mask = np.array([False, True, True, True, False, False])[None].repeat(4, 0)
    mask[2:, 0] = True  # rows 2-3: a present slot at +1e4 competing with another at +1e4
    cotangent = np.random.default_rng(1).normal(size=(4, 6)).astype(np.float32)
    weights, grad = weights_and_grad(logits, mask, cotangent)
    weights, grad = np.asarray(weights), np.asarray(grad)
    assert np.all(np.isfinite(grad))
    assert np.all(grad[~mask] == 0.0) and np.all(weights[~mask] == 0.0)
    # Softmax Jacobian y ⊙ (c - Σ y c) on the present slots.
    expected = weights * (cotangent - np.sum(weights * cotangent, -1, keepdims=True))
    np.testing.assert_allclose(grad, expected, atol=1e-6)


def test_logit_centring_changes_neither_weights_nor_gradients():
    rng = np.random.default_rng(1)
    logits = rng.normal(0, 2, (4, 6)).astype(np.float32)
    mask = rng.random((4, 6)) < 0.6
    mask[:, 0] = True
    cotangent = rng.normal(size=(4, 6)).astype(np.float32)
    centred = logits - logits.mean(-1, keepdims=True)  # mean over all slots, as the reference
    w1, g1 = weights_and_grad(logits, mask, cotangent)
    w2, g2 = weights_and_grad(centred, mask, cotangent)
    np.testing.assert_allclose(w1, w2, atol=1e-6)
    np.testing.assert_allclose(g1, g2, atol=1e-6)


@jax.jit
def _object_and_split_weights(loc, log_scale, logits, mask):
    whole = GM.create(loc, log_scale, logits, mask)
    split = GM.from_objects(jnp.stack([loc, loc + 1], -2), jnp.stack([log_scale] * 2, -2), logits, mask)
    return whole.weights, whole.weights_entropy(), split.weights, split.weights_entropy(), split.loc


def test_components_per_object_split_the_object_weight():
    assert float(clipped_entropy(np.array([0.5, 0.5, 0.0, 0.0]))) == pytest.approx(np.log(2), abs=1e-6)
    # C = 2 components per object: w_{o,c} = w_o / 2 and H(flat) = H(objects) + ln 2 (§3.6).
    w, h, w_split, h_split, loc_split = _object_and_split_weights(*random_mixture(2))
    assert loc_split.shape == (3, 10, 3)
    expected = np.repeat(np.asarray(w) / 2, 2, axis=-1)  # object-major flattening k = 2·o + c
    np.testing.assert_allclose(w_split, expected, rtol=1e-6)
    np.testing.assert_allclose(h_split, np.asarray(h) + np.log(2), atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Squashed Gaussian mixture density: §3.2, invariants §8 items 3-4
# ---------------------------------------------------------------------------------------------


@jax.jit
def _single_component_views(loc, log_scale, action):
    baseline = squashed_gaussian(loc, log_scale)
    exact = distrax.Transformed(
        distrax.MultivariateNormalDiag(loc, jnp.exp(log_scale)), distrax.Block(distrax.Tanh(), 1)
    )
    clipped = squashed_gaussian(loc, jnp.full_like(log_scale, -30.0)).log_scale
    return baseline.log_prob(action), exact.log_prob(action), clipped


def test_one_object_one_component_is_the_plain_squashed_gaussian():
    rng = np.random.default_rng(3)
    loc = rng.normal(0, 1, (5, 1, 3)).astype(np.float32)
    log_scale = rng.uniform(-4.5, 1.5, (5, 1, 3)).astype(np.float32)
    action = rng.uniform(-0.95, 0.95, (5, 3)).astype(np.float32)
    ours = gm_log_prob(loc, log_scale, np.zeros((5, 1), np.float32), np.ones((5, 1), bool), action)
    # Closed form: Σ_d log N(atanh a_d; μ_d, σ_d) - Σ_d log(1 - a_d² + 1e-6), in float64 numpy.
    u, mu, log_sigma = np.arctanh(action.astype(np.float64)), loc[:, 0], log_scale[:, 0]
    normal = -0.5 * ((u - mu) / np.exp(log_sigma)) ** 2 - log_sigma - 0.5 * np.log(2 * np.pi)
    expected = np.sum(normal, -1) - np.sum(np.log(1 - action.astype(np.float64) ** 2 + 1e-6), -1)
    np.testing.assert_allclose(ours, expected, rtol=1e-5, atol=1e-5)
    baseline, exact, clipped = _single_component_views(loc[:, 0], log_scale[:, 0], action)
    # The SAC baseline constructor (log σ bounds [-20, 2]) gives the same policy ...
    np.testing.assert_allclose(baseline, ours, atol=1e-5)
    assert float(np.min(clipped)) == -20.0
    # ... and distrax's Tanh (exact Jacobian, no 1e-6) differs only by the epsilon here.
    np.testing.assert_allclose(exact, ours, atol=1e-4)


def test_log_space_equals_reference_product_formula_where_finite():
    loc, log_scale, logits, mask = random_mixture(4, (6,))
    action = np.random.default_rng(5).uniform(-0.97, 0.97, (6, 3)).astype(np.float32)
    weights = np_masked_softmax(logits, mask)
    for floor in (False, True):
        ours = gm_log_prob(loc, log_scale, logits, mask, action, floor=floor)
        ref32 = reference_log_prob(action, loc, log_scale, weights, floor)
        assert ref32.dtype == np.float32 and np.all(np.isfinite(ref32))
        np.testing.assert_allclose(ours, ref32, atol=1e-5, rtol=1e-5)
    with jax.enable_x64(True):
        loc64, log_scale64, logits64, action64 = (
            x.astype(np.float64) for x in (loc, log_scale, logits, action)
        )
        ours64 = gm_log_prob(loc64, log_scale64, logits64, mask, action64)
        ref64 = reference_log_prob(action64, loc64, log_scale64, np_masked_softmax(logits64, mask))
        assert ours64.dtype == jnp.float64
        np.testing.assert_allclose(ours64, ref64, rtol=1e-12, atol=1e-12)


def test_log_space_stays_finite_where_the_product_underflows():
    # Narrow components (log σ = -5) far from the action: Π_d pdf ≈ exp(-1e5) underflows in float32.
    loc = np.array([[[2.0, -2.0, 1.5], [-1.8, 2.2, -1.0]]], np.float32)
    log_scale = np.full_like(loc, -5.0)
    logits = np.array([[0.3, -0.2]], np.float32)
    mask = np.ones((1, 2), bool)
    action = np.array([[0.2, 0.1, -0.3]], np.float32)
    assert np.all(np.isinf(reference_log_prob(action, loc, log_scale, np_masked_softmax(logits, mask))))
    ours = gm_log_prob(loc, log_scale, logits, mask, action)
    assert np.all(np.isfinite(ours)) and float(ours[0]) < -1e4
    # Exact value: float64 logsumexp of the per-component log densities.
    a64 = action.astype(np.float64)
    u = np.arctanh(a64)[:, None]
    per_comp = np.sum(-0.5 * ((u - loc) / np.exp(-5.0)) ** 2 + 5.0 - 0.5 * np.log(2 * np.pi), -1)
    per_comp += np.log(np_masked_softmax(logits.astype(np.float64), mask))
    top = per_comp.max(-1)
    correction = np.sum(np.log(1 - a64**2 + 1e-6), -1)
    expected = top + np.log(np.exp(per_comp - top[:, None]).sum(-1)) - correction
    np.testing.assert_allclose(ours, expected, rtol=1e-6)
    # The actor-loss variant floors p_u at 1e-10, as the reference does.
    floored = gm_log_prob(loc, log_scale, logits, mask, action, floor=True)
    np.testing.assert_allclose(floored, np.log(1e-10) - correction, rtol=1e-6)


def _tanh_grid(num, u_max):
    """Quadrature on (-1, 1) through a = tanh(u): nodes a_i and weights of the trapezoid rule in u.

    ∫ f(a) da = ∫ f(tanh u)(1 - tanh² u) du; the uniform-u trapezoid converges spectrally for
    these smooth, fast-decaying integrands and puts nodes where a squashed density can pile up.
    """
    u = np.linspace(-u_max, u_max, num)
    weights = np.full(num, u[1] - u[0]) * (1 - np.tanh(u) ** 2)
    weights[[0, -1]] *= 0.5
    return np.tanh(u), weights


def _density(loc, log_scale, logits, mask, points):
    return np.exp(
        np.asarray(gm_log_prob(loc, log_scale, logits, mask, points.astype(np.float32)), np.float64)
    )


# A 1-D mixture (quadrature) and a 2-D one (quadrature and sampling); slot 3 is absent and would
# dominate if it were not masked.
LOC_1D = np.array([[-1.5], [0.2], [1.2], [7.0]], np.float32)
LOG_SCALE_1D = np.log(np.array([[0.3], [1.0], [0.6], [0.1]], np.float32))
LOC_2D = np.array([[-1.2, -1.0], [0.3, 0.8], [1.5, 1.0], [9.0, 0.0]], np.float32)
LOG_SCALE_2D = np.log(np.array([[0.4, 0.8], [0.8, 0.3], [0.3, 0.5], [0.1, 0.5]], np.float32))
LOGITS = np.array([0.0, 0.7, -0.4, 3.0], np.float32)
MASK = np.array([True, True, True, False])
WEIGHTS = np_masked_softmax(LOGITS, MASK)
BIN_EDGES = np.linspace(-1, 1, 41)


def _bin_probs(loc, log_scale, edges=BIN_EDGES):
    """Exact P(a ∈ bin) of a 1-D mixture from the Normal CDF in u = atanh(a) (no density code)."""
    u = np.arctanh(np.clip(edges, -1 + 1e-15, 1 - 1e-15))
    return np.diff(ndtr((u[:, None] - loc[None]) / np.exp(log_scale[None])) @ WEIGHTS)


def test_density_integrates_to_one_in_1d():
    grid, quad_weights = _tanh_grid(8001, 9.0)
    density = _density(LOC_1D, LOG_SCALE_1D, LOGITS, MASK, grid[:, None])
    assert np.sum(density * quad_weights) == pytest.approx(1.0, abs=1e-5)
    # A plain uniform grid on [-1, 1]: integrated per bin, the density gives the exact bin masses.
    uniform = np.linspace(-1, 1, 8001)
    density = _density(LOC_1D, LOG_SCALE_1D, LOGITS, MASK, uniform[:, None])
    per_bin = [np.trapezoid(density[i : i + 201], uniform[i : i + 201]) for i in range(0, 8000, 200)]
    np.testing.assert_allclose(per_bin, _bin_probs(LOC_1D[:, 0], LOG_SCALE_1D[:, 0]), atol=2e-4)
    assert np.sum(per_bin) == pytest.approx(1.0, abs=1e-4)


GRID_2D, QUAD_WEIGHTS_2D = _tanh_grid(601, 8.0)


@pytest.fixture(scope="module")
def density_2d():
    points = np.stack(np.meshgrid(GRID_2D, GRID_2D, indexing="ij"), -1)
    return points, _density(LOC_2D, LOG_SCALE_2D, LOGITS, MASK, points)


def _integrate_2d(values):
    return QUAD_WEIGHTS_2D @ values @ QUAD_WEIGHTS_2D


def test_density_integrates_to_one_in_2d(density_2d):
    _, density = density_2d
    assert _integrate_2d(density) == pytest.approx(1.0, abs=1e-5)


# ---------------------------------------------------------------------------------------------
# Sampling: §3.3, §3.4 (eq. 9), invariants §8 items 5-6
# ---------------------------------------------------------------------------------------------

NUM_DRAWS = 40_000


@pytest.fixture(scope="module")
def draws_2d():
    draws = gm_samples(LOC_2D, LOG_SCALE_2D, LOGITS, MASK, jax.random.key(7), NUM_DRAWS)
    return {name: np.asarray(x) for name, x in draws.items()}


def test_ancestral_samples_match_the_density(draws_2d, density_2d):
    components = draws_2d["components"]
    assert np.all(MASK[components])  # the absent slot is never drawn
    np.testing.assert_allclose(np.bincount(components, minlength=4) / NUM_DRAWS, WEIGHTS, atol=0.01)
    # Histogram of the first action dimension against its exact marginal bin masses.
    expected = _bin_probs(LOC_2D[:, 0], LOG_SCALE_2D[:, 0])
    observed = np.histogram(draws_2d["actions"][:, 0], BIN_EDGES)[0] / NUM_DRAWS
    stderr = np.sqrt(expected * (1 - expected) / NUM_DRAWS) + 1e-4
    assert np.max(np.abs(observed - expected) / stderr) < 5
    # Moments of the samples against quadrature of the 2-D density.
    (points, density), actions = density_2d, draws_2d["actions"].astype(np.float64)
    a0, a1 = points[..., 0], points[..., 1]
    for f_grid, f_samples in [
        (a0, actions[:, 0]),
        (a1, actions[:, 1]),
        (a0 * a1, actions[:, 0] * actions[:, 1]),
        (a1**2, actions[:, 1] ** 2),
    ]:
        tolerance = 5 * f_samples.std() / np.sqrt(NUM_DRAWS)
        assert f_samples.mean() == pytest.approx(_integrate_2d(density * f_grid), abs=tolerance)


def test_per_component_samples_weighted_by_w_match_the_mixture(draws_2d):
    per_comp, per_comp_log_probs = draws_2d["per_component"], draws_2d["per_component_log_probs"]
    expected = _bin_probs(LOC_2D[:, 0], LOG_SCALE_2D[:, 0])
    observed = sum(WEIGHTS[k] * np.histogram(per_comp[:, k, 0], BIN_EDGES)[0] for k in range(4)) / NUM_DRAWS
    assert np.max(np.abs(observed - expected) / (np.sqrt(expected / NUM_DRAWS) + 1e-4)) < 5
    # Each component's sample is scored under the full mixture (§3.4), as log_prob at that action
    # (away from ±1, where atanh of a float32 action loses the pre-squash value).
    inside = np.all(np.abs(per_comp) < 0.999, axis=-1)
    np.testing.assert_allclose(
        per_comp_log_probs[inside], draws_2d["per_component_direct"][inside], atol=2e-3
    )
    # The exact expectation over k (eq. 8) and ancestral Monte Carlo estimate the same E_π[log π].
    analytic = np.sum(WEIGHTS * per_comp_log_probs.mean(0))
    log_probs = draws_2d["log_probs"]
    tolerance = 5 * log_probs.std() / np.sqrt(NUM_DRAWS) + 1e-3
    assert analytic == pytest.approx(log_probs.mean(), abs=tolerance)


STANDARD_ACTION = np.array([[0.1, -0.2, 0.3], [0.5, 0.0, -0.9], [-0.6, 0.7, 0.2]], np.float32)


def test_sampling_is_deterministic_and_consistent():
    loc, log_scale, logits, mask = random_mixture(9)
    key = jax.random.key(5)
    first = gm_everything(loc, log_scale, logits, mask, STANDARD_ACTION, key)
    second = gm_everything(loc, log_scale, logits, mask, STANDARD_ACTION, key)
    jax.tree.map(np.testing.assert_array_equal, first, second)
    other = gm_everything(loc, log_scale, logits, mask, STANDARD_ACTION, jax.random.key(6))
    assert not np.array_equal(first["per_component"][0], other["per_component"][0])
    # sample and sample_and_log_prob make the same draw; its density is the full mixture's.
    action, log_prob = first["sample_and_log_prob"]
    np.testing.assert_array_equal(action, first["sample"][0])
    assert action.shape == (3, 3) and log_prob.shape == (3,)
    np.testing.assert_allclose(log_prob, gm_log_prob(loc, log_scale, logits, mask, action), atol=1e-3)
    assert np.all(mask[np.arange(3), first["sample"][1]])


# ---------------------------------------------------------------------------------------------
# Gradients and masking: §3.4, §7.2.1, §7.3
# ---------------------------------------------------------------------------------------------


def test_gradients_reach_weights_and_parameters_and_match_finite_differences():
    loc, log_scale, logits, mask = random_mixture(10, present_prob=1.0)
    grad_loc, grad_log_scale, grad_logits = gm_objective_grad(loc, log_scale, logits, mask, jax.random.key(0))
    assert np.all(np.abs(grad_logits) > 1e-7), "weights must not be stop-gradiented (§7.2.1)"
    assert np.all(np.abs(grad_loc) > 0) and np.all(np.abs(grad_log_scale) > 0)
    # Directional derivatives against central differences, in float64 (smooth variant: no floor).
    with jax.enable_x64(True):
        params = tuple(x.astype(np.float64) for x in (loc, log_scale, logits))
        value_and_grad = jax.jit(
            jax.value_and_grad(
                lambda *p: actor_objective(*p, mask, jax.random.key(0), floor=False), (0, 1, 2)
            )
        )
        _, grads = value_and_grad(*params)
        rng = np.random.default_rng(0)
        for _ in range(3):
            direction = tuple(rng.normal(size=p.shape) for p in params)
            step = 1e-6
            plus, _ = value_and_grad(*(p + step * d for p, d in zip(params, direction, strict=True)))
            minus, _ = value_and_grad(*(p - step * d for p, d in zip(params, direction, strict=True)))
            numeric = (float(plus) - float(minus)) / (2 * step)
            analytic = sum(float(np.sum(g * d)) for g, d in zip(grads, direction, strict=True))
            assert analytic == pytest.approx(numeric, rel=1e-6, abs=1e-8)


def test_absent_objects_get_zero_weight_and_zero_gradient():
    loc, log_scale, logits, mask = random_mixture(12)
    mask[:, 3:] = False
    mask[:, :3] = True
    # Garbage on the absent slots: huge logits and parameters must not leak anywhere.
    logits[:, 3], logits[:, 4] = 1e4, 1e20
    loc[:, 3:], log_scale[:, 3:] = 1e6, 50.0
    grads = gm_objective_grad(loc, log_scale, logits, mask, jax.random.key(1))
    for grad in grads:
        grad = np.asarray(grad)
        assert np.all(np.isfinite(grad))
        assert np.all(grad[:, 3:] == 0.0) and np.any(grad[:, :3] != 0.0)
    out = gm_everything(loc, log_scale, logits, mask, STANDARD_ACTION, jax.random.key(1))
    assert np.all(np.asarray(out["weights"])[:, 3:] == 0.0)
    for name, value in jax.tree_util.tree_leaves_with_path(out):
        assert np.all(np.isfinite(value)), name
    # The result equals the mixture without those slots (padding invariance, §8 item 8).
    trimmed = gm_log_prob(loc[:, :3], log_scale[:, :3], logits[:, :3], mask[:, :3], STANDARD_ACTION)
    np.testing.assert_allclose(out["log_prob"], trimmed, rtol=1e-6)


def test_permuting_and_padding_slots_leaves_the_distribution_unchanged():
    loc, log_scale, logits, mask = random_mixture(13, (2, 2), 4)  # two leading batch axes
    action = np.random.default_rng(0).uniform(-0.9, 0.9, (2, 2, 3)).astype(np.float32)
    base = gm_log_prob(loc, log_scale, logits, mask, action)
    assert base.shape == (2, 2)
    perm = np.array([2, 0, 3, 1])
    permuted = gm_log_prob(
        loc[..., perm, :], log_scale[..., perm, :], logits[..., perm], mask[..., perm], action
    )
    np.testing.assert_allclose(permuted, base, rtol=1e-6, atol=1e-6)

    def pad(x, value, axis):
        shape = list(x.shape)
        shape[axis] = 2
        return np.concatenate([x, np.full(shape, value, x.dtype)], axis=axis)

    padded = gm_log_prob(
        pad(loc, 3.0, -2), pad(log_scale, 1.0, -2), pad(logits, 9.0, -1), pad(mask, False, -1), action
    )
    np.testing.assert_allclose(padded, base, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("log_std", [MIXTURE_LOG_STD_MIN, LOG_STD_MAX, -100.0, 100.0])
def test_everything_finite_at_extreme_logits_clip_bounds_and_saturated_actions(log_std):
    loc = np.array([[0.0, 3.0, -3.0], [12.0, -12.0, 0.5], [1.0, 1.0, 1.0], [-9.0, 0.0, 9.0], [0.2, 0.0, 0.0]])
    loc = np.repeat(loc[None], 3, 0).astype(np.float32)
    log_scale = np.full_like(loc, log_std)
    logits = np.array(
        [[1e4, -1e4, 0.0, 1e4, -1e4], [-1e4, -1e4, 1e4, 1e4, 0.0], [0.0, 1e4, 1e4, -1e4, 1e20]], np.float32
    )
    mask = np.array([[1, 1, 0, 0, 1], [1, 1, 1, 1, 1], [0, 0, 0, 0, 0]], bool)
    action = np.array([[1.0, -1.0, 0.999999], [-1.0, 1.0, 1.0], [0.0, 1.0, -1.0]], np.float32)
    out = gm_everything(loc, log_scale, logits, mask, action, jax.random.key(2))
    out.pop("distrax_components")  # distrax's exact tanh Jacobian is not finite at ±1 (documented)
    for name, value in jax.tree_util.tree_leaves_with_path(out):
        assert np.all(np.isfinite(value)), name
    grads = gm_objective_grad(loc, log_scale, logits, mask, jax.random.key(2))
    assert all(np.all(np.isfinite(g)) for g in grads)
    np.testing.assert_allclose(np.asarray(out["weights"])[2], 1 / 5, rtol=1e-6)  # all absent: uniform
    stored = np.asarray(out["log_scale"])
    assert stored.min() >= MIXTURE_LOG_STD_MIN and stored.max() <= LOG_STD_MAX


@jax.jit
@jax.vmap
def _log_prob_grad_wrt_log_std(log_std):
    def log_prob(log_scale):
        return GM.create(jnp.zeros((1, 1)), log_scale, None, None).log_prob(jnp.array([0.3]))

    return jax.grad(log_prob)(jnp.reshape(log_std, (1, 1)))[0, 0]


def test_log_std_clip_stops_the_gradient_outside_the_bounds():
    grads = np.asarray(_log_prob_grad_wrt_log_std(np.array([-7.0, 3.0, 0.0], np.float32)))
    assert grads[0] == 0.0 and grads[1] == 0.0 and grads[2] != 0.0


def test_approximate_mode_picks_the_densest_present_squashed_mean():
    loc = np.zeros((3, 5, 3), np.float32)
    loc[:, :3] = [[-1.0, 0.5, 0.0], [1.0, -0.5, 0.3], [0.2, 0.2, 0.2]]
    log_scale = np.zeros_like(loc)
    log_scale[:, :3] = np.log([[0.1] * 3, [0.3] * 3, [0.01] * 3])
    logits = np.array([[0.0, 1.0, 10.0, 0, 0], [-10.0, 1.0, 10.0, 0, 0], [0.0, 1.0, 10.0, 0, 0]], np.float32)
    mask = np.array([[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [1, 1, 1, 0, 0]], bool)
    mode = np.asarray(gm_everything(loc, log_scale, logits, mask, STANDARD_ACTION, jax.random.key(0))["mode"])
    # Row 0: component 0 is 27x denser at its mean than 1 and outweighs its smaller weight.
    # Row 1: component 0 has weight e^-11 relative to 1. Row 2: the narrow slot is present now.
    np.testing.assert_allclose(mode, np.tanh(loc[:, [0, 1, 2]][np.arange(3), np.arange(3)]), rtol=1e-6)


def test_component_views():
    out = gm_everything(*random_mixture(14), STANDARD_ACTION, jax.random.key(0))
    joint, marginal = np.asarray(out["component_log_prob"]), np.asarray(out["marginal"])
    assert joint.shape == (3, 5) and marginal.shape == (3, 5, 3)
    # The same ~3·A float32 terms summed in another order: a few ulps of the largest (|log h| up to ~130).
    np.testing.assert_allclose(joint, marginal.sum(-1), rtol=8 * np.finfo(np.float32).eps, atol=1e-5)
    np.testing.assert_allclose(joint, out["distrax_components"], atol=1e-4)  # exact vs SB3 Jacobian
    # Mixture = logsumexp(log w + component log densities).
    mixture = jax.nn.logsumexp(np.asarray(out["log_weights"]) + joint, axis=-1)
    np.testing.assert_allclose(mixture, out["log_prob"], atol=1e-5)


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match="loc and log_scale"):
        GM.create(np.zeros((3, 2)), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="logits must have shape"):
        GM.create(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(4))
    with pytest.raises(ValueError, match="mask must have shape"):
        GM.create(np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), np.ones(2))
    with pytest.raises(ValueError, match="action must have shape"):
        GM.create(np.zeros((3, 2)), np.zeros((3, 2))).log_prob(np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., O, C, A\)"):
        GM.from_objects(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="component_logits"):
        CategoricalMixture.create(np.zeros(12))
    with pytest.raises(ValueError, match="integers"):
        CategoricalMixture.create(np.zeros((2, 12))).log_prob(np.float32(1.0))


# ---------------------------------------------------------------------------------------------
# Categorical mixture: eq. 3-4, §2.4, §3.5, invariant §8 item 7
# ---------------------------------------------------------------------------------------------


def test_categorical_mixture_probs_are_the_weighted_component_sum():
    rng = np.random.default_rng(15)
    comp = rng.normal(0, 2, (2, 3, 5, 12)).astype(np.float32)  # two leading batch axes
    logits = rng.normal(0, 1, (2, 3, 5)).astype(np.float32)
    mask = rng.random((2, 3, 5)) < 0.6
    mask[..., 1] = True
    actions = rng.integers(0, 12, (2, 3))
    out = cat_summary(comp, logits, mask, actions)
    w = np_masked_softmax(logits, mask)
    q = np.exp(comp - comp.max(-1, keepdims=True))
    q /= q.sum(-1, keepdims=True)
    q = np.where(mask[..., None], q, 1 / 12)  # absent rows: zero logits, uniform
    np.testing.assert_allclose(out["component_probs"], q, atol=1e-6)
    np.testing.assert_allclose(out["distrax_components"], q, atol=1e-6)
    p = np.einsum("...o,...on->...n", w, q)
    np.testing.assert_allclose(out["probs"], p, atol=1e-6)
    np.testing.assert_allclose(np.asarray(out["probs"]).sum(-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(out["distrax_probs"], p, atol=1e-6)
    np.testing.assert_allclose(out["log_probs"], np.log(p), atol=1e-5)
    np.testing.assert_allclose(
        out["log_prob"], np.log(np.take_along_axis(p, actions[..., None], -1)[..., 0]), atol=1e-5
    )
    np.testing.assert_allclose(out["entropy"], -np.sum(p * np.log(p), -1), atol=1e-5)
    np.testing.assert_array_equal(out["mode"], p.argmax(-1))


SINGLE_ACTION = np.array(0)


def test_categorical_single_present_object_is_its_component():
    comp = np.random.default_rng(16).normal(size=(4, 12)).astype(np.float32)
    mask = np.array([False, False, True, False])
    out = cat_summary(comp, np.array([9.0, -3.0, 0.0, 1e4], np.float32), mask, SINGLE_ACTION)
    np.testing.assert_allclose(out["probs"], jax.nn.softmax(comp[2]), atol=1e-6)
    assert float(out["weights_entropy"]) == 0.0


def test_categorical_finite_at_extreme_logits():
    comp = np.zeros((4, 12), np.float32)
    comp[0, :3], comp[1, :3], comp[2, :3] = [1e4, -1e4, 0.0], [-1e4, 1e4, 1e4], [-1e4, 0.0, 1e20]
    mask = np.array([True, True, True, False])
    for logits in ([1e4, -1e4, 0.0, 1e20], [-1e4, -1e4, -1e4, 1e4], [1e4, 1e4, -1e4, -1e20]):
        logits = np.array(logits, np.float32)
        out = cat_summary(comp, logits, mask, SINGLE_ACTION)
        for name, value in out.items():
            assert np.all(np.isfinite(value)), name
        grads = cat_objective_grad(comp, logits, mask, np.linspace(-1, 1, 12, dtype=np.float32), 1e-3)
        assert all(np.all(np.isfinite(g)) for g in grads)
        np.testing.assert_allclose(np.asarray(out["probs"]).sum(), 1.0, atol=1e-6)


def test_categorical_ancestral_sampling_frequencies_and_determinism():
    rng = np.random.default_rng(17)
    comp = rng.normal(0, 1, (4, 12)).astype(np.float32)
    logits = np.array([0.5, -0.5, 2.0, 1.0], np.float32)
    mask = np.array([True, True, False, True])
    actions, objects = (np.asarray(x) for x in cat_samples(comp, logits, mask, jax.random.key(4), NUM_DRAWS))
    out = cat_summary(comp, logits, mask, SINGLE_ACTION)
    p = np.asarray(out["probs"], np.float64)
    freq = np.bincount(actions, minlength=12) / NUM_DRAWS
    assert np.max(np.abs(freq - p) / np.sqrt(p * (1 - p) / NUM_DRAWS)) < 5
    w = np.asarray(out["weights"])
    np.testing.assert_allclose(np.bincount(objects, minlength=4) / NUM_DRAWS, w, atol=0.01)
    assert not np.any(objects == 2)
    again = cat_samples(comp, logits, mask, jax.random.key(4), NUM_DRAWS)
    np.testing.assert_array_equal(again[0], actions)
    np.testing.assert_array_equal(again[1], objects)


def test_categorical_gradients_reach_mixture_logits_and_kappa_pushes_towards_uniform():
    rng = np.random.default_rng(18)
    comp = rng.normal(size=(4, 12)).astype(np.float32)
    logits = np.array([2.0, 0.0, -1.0, 7.0], np.float32)
    mask = np.array([True, True, True, False])
    q = rng.normal(size=12).astype(np.float32)
    grad_comp, grad_logits = (np.asarray(g) for g in cat_objective_grad(comp, logits, mask, q, 1e-3))
    assert np.all(grad_logits[:3] != 0.0) and grad_logits[3] == 0.0
    assert np.all(grad_comp[3] == 0.0) and np.any(grad_comp[:3] != 0.0)
    # Constant Q and identical components: only H(w) acts; a gradient step raises it.
    same_comp = np.zeros_like(comp)
    _, g = cat_objective_grad(same_comp, logits, mask, np.zeros(12, np.float32), 1.0)
    g = np.asarray(g)
    before = float(cat_summary(same_comp, logits, mask, SINGLE_ACTION)["weights_entropy"])
    after = float(cat_summary(same_comp, logits - 0.1 * g, mask, SINGLE_ACTION)["weights_entropy"])
    assert after > before
    assert g[0] > 0 and g[2] < 0  # largest weight pushed down, smallest up


def test_absent_log_weight_is_finite_and_harmless():
    assert np.isfinite(ABSENT_LOG_WEIGHT)
    weights, _ = weights_and_grad(
        np.zeros((4, 6), np.float32), np.eye(4, 6, dtype=bool), np.ones((4, 6), np.float32)
    )
    np.testing.assert_array_equal(weights, np.eye(4, 6))
    assert np.all(np.asarray(clipped_entropy(weights)) == 0.0)


def test_log_std_clip_bounds_are_checked_and_honoured():
    np.testing.assert_array_equal(clip_log_std(np.array([-30.0, 0.0, 5.0]), -20.0, 2.0), [-20.0, 0.0, 2.0])
    with pytest.raises(ValueError, match="must not exceed"):
        clip_log_std(np.zeros(2), 3.0, 2.0)
    sac = squashed_gaussian(np.zeros(2), np.array([-30.0, 5.0]))  # SB3 bounds by default
    np.testing.assert_array_equal(sac.log_scale[0], [-20.0, 2.0])


def test_sample_slot_never_draws_absent_slots_and_falls_back_to_uniform():
    logits = np.array([[0.0, 50.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0]], np.float32)
    present = np.array([[True, False, True, True], [False] * 4])
    masked = masked_logits(logits, present)
    np.testing.assert_array_equal(masked[0, 1], np.float32(ABSENT_LOG_WEIGHT))
    draws = jax.vmap(lambda k: sample_slot(k, masked, present))(jax.random.split(jax.random.key(0), 2000))
    assert not np.any(np.asarray(draws[:, 0]) == 1)
    counts = np.bincount(np.asarray(draws[:, 1]), minlength=4) / 2000  # no slot present: uniform
    np.testing.assert_allclose(counts, 0.25, atol=0.05)


def test_pairwise_density_gradient_equals_autodiff_of_its_formula():
    """The K samples × K components density has its own gradient (sums over samples as products with
    ones, xrl_jax.distributions.gaussian_density.pairwise_log_density); it must be the gradient of the
    plain formula, absent components (log weight -1e30) included. float64: the two sum the same terms in
    another order, so they agree to ~K·u relative (u = 1.1e-16); 1e-10 leaves a wide margin."""
    from jax.test_util import check_grads

    from xrl_jax.distributions.gaussian_density import mixture_log_prob, pairwise_log_density, tanh_log_det

    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        u, loc = (jnp.asarray(rng.normal(size=(2, 6, 3))) for _ in range(2))
        log_scale = jnp.asarray(rng.uniform(-3, 1, (2, 6, 3)))
        log_weights = jax.nn.log_softmax(jnp.asarray(rng.normal(size=(2, 6))))
        log_weights = log_weights.at[:, 4:].set(ABSENT_LOG_WEIGHT)
        cotangent = jnp.asarray(rng.normal(size=(2, 6)))

        def plain(*args):
            u, loc, log_scale, log_weights = args
            action = jnp.tanh(u)
            return mixture_log_prob(u, action, loc[..., None, :, :], log_scale[..., None, :, :],
                                    log_weights[..., None, :], False) + tanh_log_det(action)  # fmt: skip

        args = (u, loc, log_scale, log_weights)
        np.testing.assert_allclose(pairwise_log_density(*args), plain(*args), rtol=1e-12)
        own = jax.vjp(pairwise_log_density, *args)[1](cotangent)
        reference = jax.vjp(plain, *args)[1](cotangent)
        for got, want in zip(own, reference, strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(want))))
        finite_weights = log_weights.at[:, 4:].set(-3.0)  # finite differences need finite weights
        check_grads(pairwise_log_density, (*args[:3], finite_weights), order=1, modes=["rev"])
