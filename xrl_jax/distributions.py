"""Mixture policies over objects: categorical mixture (paper eq. 3) and squashed diagonal
Gaussian mixture (paper eq. 6-7), docs/algorithms.md §3.

Both distributions are ``flax.struct`` dataclasses (pytrees), so they can be built inside a
jitted function, returned from it, vmapped and scanned. Every array has arbitrary leading batch
axes ``...``; the component axis (one component per object slot, or ``O·C`` flattened
object-major) is the last axis before the action axis.

Why the density is computed in log space: the reference evaluates Σ_k w_k Π_d N(u_d; μ, σ) in
probability space, which underflows to 0 (log = -inf) for points far from every component. Here
``log p_u = logsumexp_k(log w_k + Σ_d log N(u_d; μ_kd, σ_kd))``; it agrees with the reference
wherever that is finite and stays finite where it is not. The tanh change of variables uses the
reference's Jacobian ``Σ_d log(1 - a_d² + 1e-6)`` (SB3 epsilon), not the exact one, for parity.

Masking: absent slots get exactly zero weight and exactly zero gradient, whatever their logits
or parameters (absent parameters are replaced by harmless constants before use, so 0·value
never meets an inf/NaN). A sample without any present slot falls back to uniform weights over
all slots (§3.1.4).

Usage::

    from xrl_jax.distributions import SquashedGaussianMixture, CategoricalMixture

    # XSAC: means/log_stds (B, O, C, A), mixture logits (B, O), present mask (B, O)
    pi = SquashedGaussianMixture.from_objects(means, log_stds, mixture_logits, present)
    actions, log_probs = pi.sample_per_component(key)   # (B, O·C, A), (B, O·C): eq. 8-9
    loss = jnp.sum(pi.weights * (alpha * log_probs - q), -1) - kappa * pi.weights_entropy()
    next_action, next_log_prob = pi.sample_and_log_prob(key)   # targets, acting (§3.3)

    # XDSAC: per-object action logits (B, O, N), mixture logits (B, O), present (B, O)
    pi = CategoricalMixture.create(action_logits, mixture_logits, present)
    pi.probs(), pi.entropy(), pi.weights_entropy(), pi.sample(key), pi.mode()
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax import sets
from xrl_jax.config import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, SAC_LOG_STD_MIN  # the log-σ bounds' home

if TYPE_CHECKING:
    import distrax

Array = jax.Array


def _distrax():
    """distrax, an optional extra: only the adaptors below need it (and the TFP nightly it pulls)."""
    try:
        import distrax
    except ImportError:
        raise ImportError("the distrax adaptors need the extra: pip install 'xrl-jax[distrax]'") from None
    return distrax


TANH_JACOBIAN_EPS = 1e-6
"""ε in the reference's squash correction Σ_d log(1 - a_d² + ε) (§3.2, §7.3)."""
PROB_FLOOR = 1e-10
"""Floor of categorical probabilities inside logs, and of p_u in the actor-loss variant (§7.3)."""
ABSENT_LOG_WEIGHT = -1e30
"""Log weight of an absent slot: finite, so ``w·log w`` is 0 (not NaN) and logsumexp ignores it."""

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


# ---------------------------------------------------------------------------------------------
# Mixture weights (§3.1) and entropies
# ---------------------------------------------------------------------------------------------


def _as_float(x) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def _as_present(mask, shape: tuple[int, ...]) -> Array:
    """Boolean present flags; ``None`` means all present. Floats count as present above 0.5."""
    if mask is None:
        return jnp.ones(shape, dtype=bool)
    mask = jnp.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask must have shape {shape} (same as the mixture logits), got {mask.shape}")
    return mask if mask.dtype == jnp.bool_ else mask > 0.5


def _effective_present(present: Array) -> Array:
    """Slots that carry weight: the present ones, or all of them if none is present (§3.1.4)."""
    return present | ~jnp.any(present, axis=-1, keepdims=True)


def masked_log_softmax(logits: Array, mask: Array | None = None) -> Array:
    """Log mixture weights over the last axis: log w_o with absent slots at ``ABSENT_LOG_WEIGHT``.

    Written without ``jax.nn.softmax`` so that absent logits (even ±1e4 or 1e20) never enter an
    exp: their weight is exactly 0 and their gradient exactly 0. All-absent rows → uniform 1/O.
    """
    logits = _as_float(logits)
    present = _as_present(mask, logits.shape)
    any_present = jnp.any(present, axis=-1, keepdims=True)
    effective = present | ~any_present
    logits = jnp.where(any_present, logits, 0.0)  # the fallback ignores the logits: uniform
    shift = jax.lax.stop_gradient(jnp.max(jnp.where(effective, logits, -jnp.inf), axis=-1, keepdims=True))
    shifted = jnp.where(effective, logits - shift, ABSENT_LOG_WEIGHT)
    log_norm = jnp.log(jnp.sum(jnp.exp(shifted), axis=-1, keepdims=True))  # ≥ 0: the max term is 1
    return jnp.where(effective, shifted - log_norm, ABSENT_LOG_WEIGHT)


def masked_logits(logits: Array, mask: Array | None = None) -> Array:
    """Logits with absent slots at ``ABSENT_LOG_WEIGHT`` (finite, so 0·logit stays 0)."""
    logits = _as_float(logits)
    return jnp.where(_as_present(mask, logits.shape), logits, ABSENT_LOG_WEIGHT)


def sample_slot(key: Array, masked: Array, mask: Array | None = None) -> Array:
    """One slot per row drawn from :func:`masked_logits` output (..., K): absent slots are never
    drawn, and a row without any present slot draws uniformly over all slots (§3.1.4)."""
    present = _as_present(mask, masked.shape)
    any_present = jnp.any(present, axis=-1, keepdims=True)
    return jax.random.categorical(key, jnp.where(any_present, masked, 0.0), axis=-1)


def masked_softmax(logits: Array, mask: Array | None = None) -> Array:
    """Mixture weights w_o = m_o·exp(ℓ_o) / Σ_j m_j·exp(ℓ_j) (§3.1), exact zeros on absent slots."""
    return jnp.exp(masked_log_softmax(logits, mask))


def clipped_entropy(probs: Array, axis: int = -1) -> Array:
    """H(p) = -Σ p·log clip(p, 1e-10, 1), the reference's form for every categorical entropy (§7.3)."""
    return -jnp.sum(probs * jnp.log(jnp.clip(probs, PROB_FLOOR, 1.0)), axis=axis)


# ---------------------------------------------------------------------------------------------
# Squashed Gaussian pieces (§3.2)
# ---------------------------------------------------------------------------------------------


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
    action = _as_float(action)
    bound = 1.0 - jnp.finfo(action.dtype).epsneg
    return jnp.arctanh(jnp.clip(action, -bound, bound))


def _gaussian_log_density(u: Array, loc: Array, log_scale: Array) -> Array:
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
    return -0.5 * squares - (jnp.sum(log_scale, axis=-1) + log_scale.shape[-1] * _HALF_LOG_2PI)


def _pairwise_terms(u: Array, loc: Array, log_scale: Array, log_weights: Array) -> tuple[Array, list[Array]]:
    """log w_j + log N(u_k; μ_j, σ_j) for samples k × components j, (..., K, J), and the standardised
    differences z_kjd per action dimension (each (..., K, J))."""
    inv_scale = jnp.exp(-log_scale)
    z = [(u[..., :, None, d] - loc[..., None, :, d]) * inv_scale[..., None, :, d] for d in range(u.shape[-1])]
    per_component = log_weights - (jnp.sum(log_scale, axis=-1) + u.shape[-1] * _HALF_LOG_2PI)
    return per_component[..., None, :] - 0.5 * sum(jnp.square(zd) for zd in z), z


@jax.custom_vjp
def _pairwise_log_density(u: Array, loc: Array, log_scale: Array, log_weights: Array) -> Array:
    """log p_u(u_k) = logsumexp_j(log w_j + Σ_d log N(u_kd; μ_jd, σ_jd)) of K samples under a mixture of
    J components: u (..., K, A); loc, log_scale (..., J, A); log_weights (..., J) → (..., K).

    Its own gradient because autodiff's sums over the samples k (per component j, for the gradients of
    μ_j, log σ_j and w_j) are reductions over a middle axis that XLA's CPU backend runs several times
    slower than a matrix product; here they are products with a vector of ones (same terms, same
    order of magnitude, no cancellation): the XSAC actor loss's K × K block costs a third.
    """
    return jax.nn.logsumexp(_pairwise_terms(u, loc, log_scale, log_weights)[0], axis=-1)


def _pairwise_forward(u, loc, log_scale, log_weights):
    log_density = _pairwise_log_density(u, loc, log_scale, log_weights)
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


_pairwise_log_density.defvjp(_pairwise_forward, _pairwise_backward)


def _pairwise_among_weighted(
    plan: sets.FirstPresent, u: Array, loc: Array, log_scale: Array, log_weights: Array
) -> Array:
    """:func:`_pairwise_log_density` on each sample's first weighted components (``plan``), in the K
    slots again. The slots kept past a sample's count carry no weight (log weight ``ABSENT_LOG_WEIGHT``),
    so they add exactly nothing, as in the full sum."""

    def take(x):
        return jnp.take_along_axis(x, plan.order[..., None], axis=-2)

    kept_log_weights = jnp.take_along_axis(log_weights, plan.order, axis=-1)
    compact = _pairwise_log_density(take(u), take(loc), take(log_scale), kept_log_weights)
    return jnp.take_along_axis(compact, plan.place, axis=-1)


def _mixture_log_prob(
    u: Array, action: Array, loc: Array, log_scale: Array, log_weights: Array, floor_density: bool
) -> Array:
    """log π(a) = [floored] logsumexp_k(log w_k + log N(u; μ_k, σ_k)) - Σ_d log(1 - a_d² + ε).

    u, action: (..., A); loc, log_scale: (..., K, A); log_weights: (..., K); all broadcasting.
    """
    per_component = _gaussian_log_density(u[..., None, :], loc, log_scale) + log_weights
    log_density = jax.nn.logsumexp(per_component, axis=-1)
    if floor_density:
        log_density = jnp.maximum(log_density, math.log(PROB_FLOOR))
    return log_density - tanh_log_det(action)


class _Mixture:
    """What both mixtures share: ``log_weights`` (..., K) and a per-component array (..., K, X)."""

    log_weights: Array
    _per_component_field = ""  # the subclass's field with the per-component array

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return getattr(self, self._per_component_field).shape[:-2]

    @property
    def num_components(self) -> int:
        return getattr(self, self._per_component_field).shape[-2]

    @property
    def weights(self) -> Array:
        """w_k: (..., K), exactly 0 on absent slots, summing to 1."""
        return jnp.exp(self.log_weights)

    @property
    def weighted(self) -> Array:
        """(..., K) bool: the components that carry weight (the present ones, or all of them in a
        sample without any, §3.1.4); the others' parameters and values never matter."""
        return _effective_present(self.present)

    def weights_entropy(self) -> Array:
        """H(w) = -Σ_k w_k log clip(w_k, 1e-10, 1): the κ regulariser's entropy (eq. 10, §3.6)."""
        return clipped_entropy(self.weights)


# ---------------------------------------------------------------------------------------------
# Squashed diagonal Gaussian mixture (paper eq. 6-9, §3.2-§3.4, §3.7, §3.9)
# ---------------------------------------------------------------------------------------------


@struct.dataclass
class SquashedGaussianMixture(_Mixture):
    """π(a|s) = Σ_k w_k Π_d h(a_d; μ_kd, σ_kd), a ∈ (-1, 1)^A, h = tanh-squashed Normal (eq. 7).

    Build with :meth:`create` (flat components) or :meth:`from_objects` (O objects × C
    components, w_{o,c} = w_o / C). Fields (all already masked and clipped):

    * ``loc``, ``log_scale``: (..., K, A) pre-squash mean and clipped log σ; absent slots hold 0.
    * ``log_weights``: (..., K) log w_k, ``ABSENT_LOG_WEIGHT`` on absent slots.
    * ``present``: (..., K) bool, the mask as given (explanations draw only present slots).
    """

    loc: Array
    log_scale: Array
    log_weights: Array
    present: Array

    @classmethod
    def create(
        cls,
        loc: Array,
        log_scale: Array,
        logits: Array | None = None,
        mask: Array | None = None,
        log_std_min: float = MIXTURE_LOG_STD_MIN,
        log_std_max: float = LOG_STD_MAX,
    ) -> SquashedGaussianMixture:
        """Mixture of K components: loc, log_scale (..., K, A); logits, mask (..., K).

        ``logits=None`` gives uniform weights over present slots (the ``uniform_mixture``
        ablation); log σ is clipped to [log_std_min, log_std_max] (:func:`clip_log_std`).
        """
        loc, log_scale = _as_float(loc), _as_float(log_scale)
        if loc.ndim < 2 or loc.shape != log_scale.shape:
            raise ValueError(
                f"loc and log_scale must share a shape (..., K, A); got {loc.shape} and {log_scale.shape}"
            )
        logits = jnp.zeros(loc.shape[:-1], loc.dtype) if logits is None else _as_float(logits)
        if logits.shape != loc.shape[:-1]:
            raise ValueError(
                f"logits must have shape {loc.shape[:-1]} (loc minus its last axis), got {logits.shape}"
            )
        present = _as_present(mask, logits.shape)
        effective = _effective_present(present)[..., None]
        return cls(
            loc=jnp.where(effective, loc, 0.0),
            log_scale=jnp.where(effective, clip_log_std(log_scale, log_std_min, log_std_max), 0.0),
            log_weights=masked_log_softmax(logits, present),
            present=present,
        )

    @classmethod
    def from_objects(
        cls, loc: Array, log_scale: Array, logits: Array | None = None, mask: Array | None = None, **log_std
    ) -> SquashedGaussianMixture:
        """Per-object mixture: loc, log_scale (..., O, C, A); logits, mask (..., O).

        Components are flattened object-major to K = O·C, k = o·C + c; each object's weight is
        split uniformly over its C components (§3.1.5), by repeating its logit C times.
        ``log_std_min`` / ``log_std_max`` (keywords) as for :meth:`create`.
        """
        loc, log_scale = jnp.asarray(loc), jnp.asarray(log_scale)
        if loc.ndim < 3 or loc.shape != log_scale.shape:
            raise ValueError(
                f"loc and log_scale must share a shape (..., O, C, A); got {loc.shape} and {log_scale.shape}"
            )
        *batch, num_objects, per_object, action_dim = loc.shape
        object_shape = (*batch, num_objects)
        if logits is not None and jnp.shape(logits) != tuple(object_shape):
            raise ValueError(f"logits must have shape {tuple(object_shape)}, got {jnp.shape(logits)}")
        if mask is not None and jnp.shape(mask) != tuple(object_shape):
            raise ValueError(f"mask must have shape {tuple(object_shape)}, got {jnp.shape(mask)}")

        def per_component(x):
            return None if x is None else jnp.repeat(jnp.asarray(x), per_object, axis=-1)

        flat = (*batch, num_objects * per_object, action_dim)
        return cls.create(
            loc.reshape(flat),
            log_scale.reshape(flat),
            per_component(logits),
            per_component(mask),
            **log_std,
        )

    # -- shapes and weights -------------------------------------------------------------------

    _per_component_field = "loc"

    @property
    def action_dim(self) -> int:
        return self.loc.shape[-1]

    @property
    def scale(self) -> Array:
        """σ = exp(clipped log σ): (..., K, A)."""
        return jnp.exp(self.log_scale)

    # -- densities ----------------------------------------------------------------------------

    def _check_action(self, action: Array) -> Array:
        action = _as_float(action)
        if action.ndim < 1 or action.shape[-1] != self.action_dim:
            raise ValueError(f"action must have shape (..., {self.action_dim}), got {action.shape}")
        return action

    def log_prob(self, action: Array, floor_density: bool = False) -> Array:
        """log π(a|s) of actions (..., A) in [-1, 1]^A; ``...`` broadcasts against the batch shape.

        ``floor_density=True`` is the reference's actor-loss variant, log max(p_u, 1e-10);
        the default is its sampler/target variant (no floor). Finite at a = ±1 (see safe_atanh).
        """
        action = self._check_action(action)
        return _mixture_log_prob(
            safe_atanh(action), action, self.loc, self.log_scale, self.log_weights, floor_density
        )

    def component_log_prob(self, action: Array) -> Array:
        """log h_k(a) of every component alone (no weight): (..., K). For explanations."""
        action = self._check_action(action)
        u = safe_atanh(action)[..., None, :]
        return _gaussian_log_density(u, self.loc, self.log_scale) - tanh_log_det(action)[..., None]

    def component_marginal_log_prob(self, action: Array) -> Array:
        """Per-dimension marginal log h(a_d; μ_kd, σ_kd) of every component: (..., K, A).

        The explanation glyphs (§6.3) draw these 1-D marginals per object.
        """
        action = self._check_action(action)[..., None, :]
        z = (safe_atanh(action) - self.loc) * jnp.exp(-self.log_scale)
        return (
            -0.5 * jnp.square(z)
            - self.log_scale
            - _HALF_LOG_2PI
            - jnp.log(1.0 - jnp.square(action) + TANH_JACOBIAN_EPS)
        )

    # -- sampling -----------------------------------------------------------------------------

    def _sample_pre_squash(self, key: Array) -> tuple[Array, Array]:
        """Ancestral draw of the pre-squash point: k ~ Cat(w), u = μ_k + σ_k ε. Returns (u, k)."""
        component_key, noise_key = jax.random.split(key)
        component = jax.random.categorical(component_key, self.log_weights, axis=-1)
        index = component[..., None, None]
        loc = jnp.take_along_axis(self.loc, index, axis=-2)[..., 0, :]
        log_scale = jnp.take_along_axis(self.log_scale, index, axis=-2)[..., 0, :]
        noise = jax.random.normal(noise_key, loc.shape, loc.dtype)
        return loc + jnp.exp(log_scale) * noise, component

    def sample_with_component(self, key: Array) -> tuple[Array, Array]:
        """Ancestral sample (§3.3): k ~ Cat(w), a = tanh(μ_k + σ_k ε). Returns (a, k).

        Absent slots are never chosen. Not differentiable w.r.t. the weights.
        """
        u, component = self._sample_pre_squash(key)
        return jnp.tanh(u), component

    def sample(self, key: Array) -> Array:
        """One action (..., A) from the full mixture (acting, evaluation of XSAC, §3.7-3.8)."""
        return self.sample_with_component(key)[0]

    def sample_and_log_prob(self, key: Array, floor_density: bool = False) -> tuple[Array, Array]:
        """Ancestral sample and its log density under the **full** mixture (targets, §3.3).

        Same draw as :meth:`sample` for the same key. The density uses the pre-squash point, so
        it stays exact where tanh saturates to ±1.
        """
        u, _ = self._sample_pre_squash(key)
        action = jnp.tanh(u)
        log_prob = _mixture_log_prob(u, action, self.loc, self.log_scale, self.log_weights, floor_density)
        return action, log_prob

    def sample_per_component(
        self, key: Array, floor_density: bool = True, packing: sets.Packing | None = None
    ) -> tuple[Array, Array]:
        """One reparameterised sample per component and its full-mixture log density (eq. 8-9, §3.4).

        Returns actions (..., K, A) with a_k = tanh(μ_k + σ_k ⊙ ε_k), and log π(a_k|s) (..., K)
        under the **full** mixture (K × K pairs), differentiable w.r.t. μ, log σ and the mixture
        logits. ``floor_density=True`` (default) is the actor-loss variant.
        Combine as Σ_k w_k·(α·log π(a_k|s) - Q(s, a_k)): the exact expectation over k.

        With ``packing`` (:mod:`xrl_jax.sets`) the pairs are formed among the components that carry
        weight only, up to ``packing.set_width(K)`` of them per sample (all K where some sample has
        more): the others add exactly nothing to a density, and their own samples' log densities,
        which no loss weighs, come out as 0.
        """
        noise = jax.random.normal(key, self.loc.shape, self.loc.dtype)
        u = self.loc + jnp.exp(self.log_scale) * noise
        actions = jnp.tanh(u)
        plan = sets.per_set_plan(self.weighted, packing)
        mixture = (u, self.loc, self.log_scale, self.log_weights)
        log_density = sets.compact_or_dense(plan, _pairwise_among_weighted, _pairwise_log_density, *mixture)
        if plan is not None:
            log_density = jnp.where(self.weighted, log_density, 0.0)
        if floor_density:
            log_density = jnp.maximum(log_density, math.log(PROB_FLOOR))
        log_probs = log_density - tanh_log_det(actions)
        return actions, log_probs

    # -- deterministic summaries --------------------------------------------------------------

    def approximate_mode(self) -> Array:
        """The present component's squashed mean tanh(μ_k) of highest mixture density (§3.9).

        The reference's unused "approximate max": the true mode may lie between components and
        is shifted by the tanh Jacobian. Absent components' means are not candidates (the
        reference also scores them; they carry no weight, so this only drops meaningless points).
        """
        squashed = jnp.tanh(self.loc)
        log_density = _pairwise_log_density(self.loc, self.loc, self.log_scale, self.log_weights)
        log_density = log_density - tanh_log_det(squashed)
        log_density = jnp.where(self.log_weights > 0.5 * ABSENT_LOG_WEIGHT, log_density, -jnp.inf)
        best = jnp.argmax(log_density, axis=-1)
        return jnp.take_along_axis(squashed, best[..., None, None], axis=-2)[..., 0, :]

    def components_distrax(self) -> distrax.Distribution:
        """Per-component squashed Gaussians as one distrax distribution, batch (..., K), event (A,).

        For explanations and plots. Note distrax's Tanh uses the exact Jacobian, not the
        reference's 1e-6 epsilon, and its log_prob is infinite at a = ±1.
        """
        distrax = _distrax()
        base = distrax.MultivariateNormalDiag(self.loc, self.scale)
        return distrax.Transformed(base, distrax.Block(distrax.Tanh(), ndims=1))


def squashed_gaussian(
    loc: Array, log_scale: Array, log_std_min: float = SAC_LOG_STD_MIN, log_std_max: float = LOG_STD_MAX
) -> SquashedGaussianMixture:
    """The baseline SAC policy tanh(N(μ, σ)) (§2.1) as a one-component mixture.

    loc, log_scale: (..., A); log σ clipped to the SB3 bounds [-20, 2] by default.
    """
    loc, log_scale = jnp.asarray(loc), jnp.asarray(log_scale)
    return SquashedGaussianMixture.create(
        loc[..., None, :], log_scale[..., None, :], log_std_min=log_std_min, log_std_max=log_std_max
    )


# ---------------------------------------------------------------------------------------------
# Categorical mixture (paper eq. 3-4, §2.4, §3.5)
# ---------------------------------------------------------------------------------------------


@struct.dataclass
class CategoricalMixture(_Mixture):
    """π(a|s) = Σ_o w_o q_o(a) with q_o = softmax(action logits of object o) (paper eq. 3).

    Fields: ``component_logits`` (..., O, N) with absent rows replaced by zeros (uniform, as
    the reference does; they carry no weight), ``log_weights`` (..., O) and ``present`` (..., O)
    as in :class:`SquashedGaussianMixture`.
    """

    component_logits: Array
    log_weights: Array
    present: Array

    @classmethod
    def create(
        cls, component_logits: Array, logits: Array | None = None, mask: Array | None = None
    ) -> CategoricalMixture:
        """component_logits (..., O, N); mixture logits, mask (..., O) (``None``: uniform / all present)."""
        component_logits = _as_float(component_logits)
        if component_logits.ndim < 2:
            raise ValueError(f"component_logits must have shape (..., O, N), got {component_logits.shape}")
        object_shape = component_logits.shape[:-1]
        logits = jnp.zeros(object_shape, component_logits.dtype) if logits is None else _as_float(logits)
        if logits.shape != object_shape:
            raise ValueError(f"logits must have shape {object_shape}, got {logits.shape}")
        present = _as_present(mask, object_shape)
        return cls(
            component_logits=jnp.where(present[..., None], component_logits, 0.0),
            log_weights=masked_log_softmax(logits, present),
            present=present,
        )

    _per_component_field = "component_logits"

    @property
    def num_actions(self) -> int:
        return self.component_logits.shape[-1]

    def component_log_probs(self) -> Array:
        """log q_o(a): (..., O, N)."""
        return jax.nn.log_softmax(self.component_logits, axis=-1)

    def component_probs(self) -> Array:
        """q_o(a): (..., O, N), the per-object explanation distributions."""
        return jax.nn.softmax(self.component_logits, axis=-1)

    def probs(self) -> Array:
        """π(a|s) = Σ_o w_o q_o(a): (..., N), sums to 1."""
        return jnp.sum(self.weights[..., None] * self.component_probs(), axis=-2)

    def log_probs(self) -> Array:
        """log π(a|s) in log space (logsumexp over objects): (..., N), finite at extreme logits."""
        return jax.nn.logsumexp(self.log_weights[..., None] + self.component_log_probs(), axis=-2)

    def log_prob(self, action: Array) -> Array:
        """log π(a|s) of integer actions (...) broadcasting against the batch shape."""
        action = jnp.asarray(action)
        if not jnp.issubdtype(action.dtype, jnp.integer):
            raise ValueError(f"discrete actions must be integers, got dtype {action.dtype}")
        log_probs = self.log_probs()
        shape = jnp.broadcast_shapes(log_probs.shape[:-1], action.shape)
        log_probs = jnp.broadcast_to(log_probs, (*shape, self.num_actions))
        index = jnp.broadcast_to(action, shape)[..., None]
        return jnp.take_along_axis(log_probs, index, axis=-1)[..., 0]

    def entropy(self) -> Array:
        """Entropy of the **mixture** π (not of its components), with the reference's 1e-10 clip."""
        return clipped_entropy(self.probs())

    def sample_with_component(self, key: Array) -> tuple[Array, Array]:
        """Ancestral sample (paper §III-C): o ~ Cat(w), a ~ Cat(q_o). Returns (a, o), int32."""
        object_key, action_key = jax.random.split(key)
        component = jax.random.categorical(object_key, self.log_weights, axis=-1)
        logits = jnp.take_along_axis(self.component_logits, component[..., None, None], axis=-2)[..., 0, :]
        return jax.random.categorical(action_key, logits, axis=-1), component

    def sample(self, key: Array) -> Array:
        """One action (...) from π (training-time acting, §3.7)."""
        return self.sample_with_component(key)[0]

    def mode(self) -> Array:
        """argmax_a π(a|s): the XDSAC evaluation action (§3.8)."""
        return jnp.argmax(self.probs(), axis=-1)

    def components_distrax(self) -> distrax.Categorical:
        """Per-object categoricals q_o as one distrax distribution, batch (..., O)."""
        return _distrax().Categorical(logits=self.component_logits)

    def to_distrax(self) -> distrax.Categorical:
        """The mixture π as a plain distrax categorical, batch (...)."""
        return _distrax().Categorical(logits=self.log_probs())


__all__ = [
    "ABSENT_LOG_WEIGHT",
    "LOG_STD_MAX",
    "MIXTURE_LOG_STD_MIN",
    "PROB_FLOOR",
    "SAC_LOG_STD_MIN",
    "TANH_JACOBIAN_EPS",
    "CategoricalMixture",
    "SquashedGaussianMixture",
    "clip_log_std",
    "clipped_entropy",
    "masked_log_softmax",
    "masked_logits",
    "masked_softmax",
    "safe_atanh",
    "sample_slot",
    "squashed_gaussian",
    "tanh_log_det",
]
