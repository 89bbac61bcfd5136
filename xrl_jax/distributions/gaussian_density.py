"""Squashed Gaussian pieces (docs/algorithms.md §3.2): log σ clipping, the tanh change of variables,
and the log densities of diagonal Gaussians and of their mixtures in log space.

Why the density is computed in log space: the reference evaluates Σ_k w_k Π_d N(u_d; μ, σ) in
probability space, which underflows to 0 (log = -inf) for points far from every component. Here
``log p_u = logsumexp_k(log w_k + Σ_d log N(u_d; μ_kd, σ_kd))``; it agrees with the reference
wherever that is finite and stays finite where it is not. The tanh change of variables uses the
reference's Jacobian ``Σ_d log(1 - a_d² + 1e-6)`` (SB3 epsilon), not the exact one, for parity.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from xrl_jax import sets
from xrl_jax.config import LOG_STD_MAX, MIXTURE_LOG_STD_MIN  # the log-σ bounds' home
from xrl_jax.distributions.weights import PROB_FLOOR, as_float

Array = jax.Array

TANH_JACOBIAN_EPS = 1e-6
"""ε in the reference's squash correction Σ_d log(1 - a_d² + ε) (§3.2, §7.3)."""

HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def clip_log_std(
    log_std: Array, log_std_min: float = MIXTURE_LOG_STD_MIN, log_std_max: float = LOG_STD_MAX
) -> Array:
    """log σ clipped to [log_std_min, log_std_max] (zero gradient outside, like jnp.clip)."""
    if not log_std_min <= log_std_max:
        raise ValueError(f"log_std_min ({log_std_min}) must not exceed log_std_max ({log_std_max})")
    return jnp.clip(log_std, log_std_min, log_std_max)


def tanh_log_det(action: Array) -> Array:
    """Reference squash correction Σ_d log(1 - a_d² + 1e-6): finite at a = ±1 (≈ -13.8 per dim)."""
    return jnp.sum(jnp.log(1.0 - jnp.square(action) + TANH_JACOBIAN_EPS), axis=-1)


def safe_atanh(action: Array) -> Array:
    """atanh of an action clipped to the largest float below 1 in magnitude (finite at ±1).

    The reference never inverts tanh (it keeps the pre-squash sample); this is only for evaluating
    the density of a given action. In float32 |atanh| ≤ 8.7, in float64 ≤ 18.7.
    """
    action = as_float(action)
    bound = 1.0 - jnp.finfo(action.dtype).epsneg
    return jnp.arctanh(jnp.clip(action, -bound, bound))


def gaussian_log_density(u: Array, loc: Array, log_scale: Array) -> Array:
    """Σ_d log N(u_d; μ_d, e^{log σ_d}) over the last axis (broadcasting).

    Written as a sum over the (few) action dimensions of arrays without the action axis, so that the
    mixture's pairwise density (K samples × K components, paper eq. 9) and its gradient never hold a
    4-D array whose short last axis XLA would have to reduce: half the time on CPU.
    """
    inv_scale = jnp.exp(-log_scale)
    squares = 0.0
    for d in range(log_scale.shape[-1]):
        z = (u[..., d] - loc[..., d]) * inv_scale[..., d]
        squares = squares + jnp.square(z)
    return -0.5 * squares - (jnp.sum(log_scale, axis=-1) + log_scale.shape[-1] * HALF_LOG_2PI)


def _pairwise_terms(u: Array, loc: Array, log_scale: Array, log_weights: Array) -> tuple[Array, list[Array]]:
    """log w_j + log N(u_k; μ_j, σ_j) for samples k × components j, (..., K, J), and the standardised
    differences z_kjd per action dimension (each (..., K, J))."""
    inv_scale = jnp.exp(-log_scale)
    z = [(u[..., :, None, d] - loc[..., None, :, d]) * inv_scale[..., None, :, d] for d in range(u.shape[-1])]
    per_component = log_weights - (jnp.sum(log_scale, axis=-1) + u.shape[-1] * HALF_LOG_2PI)
    return per_component[..., None, :] - 0.5 * sum(jnp.square(zd) for zd in z), z


@jax.custom_vjp
def pairwise_log_density(u: Array, loc: Array, log_scale: Array, log_weights: Array) -> Array:
    """log p_u(u_k) = logsumexp_j(log w_j + Σ_d log N(u_kd; μ_jd, σ_jd)) of K samples under a mixture of
    J components: u (..., K, A); loc, log_scale (..., J, A); log_weights (..., J) → (..., K).

    Its own gradient because autodiff's sums over the samples k (per component j, for the gradients of
    μ_j, log σ_j and w_j) are reductions over a middle axis that XLA's CPU backend runs several times
    slower than a matrix product; here they are products with a vector of ones (same terms, same
    order of magnitude, no cancellation): the XSAC actor loss's K × K block costs a third.
    """
    return jax.nn.logsumexp(_pairwise_terms(u, loc, log_scale, log_weights)[0], axis=-1)


def _pairwise_forward(u, loc, log_scale, log_weights):
    log_density = pairwise_log_density(u, loc, log_scale, log_weights)
    return log_density, (u, loc, log_scale, log_weights, log_density)


def _pairwise_backward(residuals, cotangent):
    u, loc, log_scale, log_weights, log_density = residuals
    terms, z = _pairwise_terms(u, loc, log_scale, log_weights)
    # r_kj = ḡ_k · posterior of component j given sample k
    r = jnp.exp(terms - log_density[..., :, None]) * cotangent[..., :, None]
    ones = jnp.ones(r.shape[-2], r.dtype)

    def over_samples(x):  # Σ_k x_kj as a matrix-vector product
        return jnp.einsum("...kj,k->...j", x, ones)

    inv_scale = jnp.exp(-log_scale)
    d_weights = over_samples(r)
    d_u, d_loc, d_log_scale = [], [], []
    for d, zd in enumerate(z):
        rz = r * zd  # ∂/∂z_kjd of the terms is −z_kjd
        d_loc.append(over_samples(rz) * inv_scale[..., d])
        d_log_scale.append(over_samples(rz * zd) - d_weights)
        d_u.append(-jnp.einsum("...kj,...j->...k", rz, inv_scale[..., d]))
    stack = lambda parts: jnp.stack(parts, axis=-1)
    return stack(d_u), stack(d_loc), stack(d_log_scale), d_weights


pairwise_log_density.defvjp(_pairwise_forward, _pairwise_backward)


def pairwise_among_weighted(
    plan: sets.FirstPresent, u: Array, loc: Array, log_scale: Array, log_weights: Array
) -> Array:
    """:func:`pairwise_log_density` on each sample's first weighted components (``plan``), in the K
    slots again. The slots kept past a sample's count carry no weight (log weight ``ABSENT_LOG_WEIGHT``),
    so they add exactly nothing, as in the full sum."""

    def take(x):
        return jnp.take_along_axis(x, plan.order[..., None], axis=-2)

    kept_log_weights = jnp.take_along_axis(log_weights, plan.order, axis=-1)
    compact = pairwise_log_density(take(u), take(loc), take(log_scale), kept_log_weights)
    return jnp.take_along_axis(compact, plan.place, axis=-1)


def mixture_log_prob(
    u: Array, action: Array, loc: Array, log_scale: Array, log_weights: Array, floor_density: bool
) -> Array:
    """log π(a) = [floored] logsumexp_k(log w_k + log N(u; μ_k, σ_k)) - Σ_d log(1 - a_d² + ε).

    u, action: (..., A); loc, log_scale: (..., K, A); log_weights: (..., K); all broadcasting.
    """
    per_component = gaussian_log_density(u[..., None, :], loc, log_scale) + log_weights
    log_density = jax.nn.logsumexp(per_component, axis=-1)
    if floor_density:
        log_density = jnp.maximum(log_density, math.log(PROB_FLOOR))
    return log_density - tanh_log_det(action)
