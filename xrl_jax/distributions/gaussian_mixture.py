"""The squashed diagonal Gaussian mixture of XSAC (paper eq. 6-9, docs/algorithms.md §3.2-§3.4,
§3.7, §3.9) and the baseline SAC policy as its one-component case.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax import sets
from xrl_jax.config import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, SAC_LOG_STD_MIN  # the log-σ bounds' home
from xrl_jax.distributions.gaussian_density import (
    HALF_LOG_2PI,
    TANH_JACOBIAN_EPS,
    clip_log_std,
    gaussian_log_density,
    mixture_log_prob,
    pairwise_among_weighted,
    pairwise_log_density,
    safe_atanh,
    tanh_log_det,
)
from xrl_jax.distributions.weights import (
    ABSENT_LOG_WEIGHT,
    PROB_FLOOR,
    Mixture,
    as_float,
    as_present,
    effective_present,
    masked_log_softmax,
    require_distrax,
)

if TYPE_CHECKING:
    import distrax

Array = jax.Array


@struct.dataclass
class SquashedGaussianMixture(Mixture):
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
        loc, log_scale = as_float(loc), as_float(log_scale)
        if loc.ndim < 2 or loc.shape != log_scale.shape:
            raise ValueError(
                f"loc and log_scale must share a shape (..., K, A); got {loc.shape} and {log_scale.shape}"
            )
        logits = jnp.zeros(loc.shape[:-1], loc.dtype) if logits is None else as_float(logits)
        if logits.shape != loc.shape[:-1]:
            raise ValueError(
                f"logits must have shape {loc.shape[:-1]} (loc minus its last axis), got {logits.shape}"
            )
        present = as_present(mask, logits.shape)
        effective = effective_present(present)[..., None]
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
        action = as_float(action)
        if action.ndim < 1 or action.shape[-1] != self.action_dim:
            raise ValueError(f"action must have shape (..., {self.action_dim}), got {action.shape}")
        return action

    def log_prob(self, action: Array, floor_density: bool = False) -> Array:
        """log π(a|s) of actions (..., A) in [-1, 1]^A; ``...`` broadcasts against the batch shape.

        ``floor_density=True`` is the reference's actor-loss variant, log max(p_u, 1e-10);
        the default is its sampler/target variant (no floor). Finite at a = ±1 (see safe_atanh).
        """
        action = self._check_action(action)
        return mixture_log_prob(
            safe_atanh(action), action, self.loc, self.log_scale, self.log_weights, floor_density
        )

    def log_prob_pre_squash(self, u: Array) -> Array:
        """log π(tanh(u)|s) from the pre-squash point u (..., A): exact where tanh saturates, where
        atanh of the stored action could not give u back. An on-policy ratio π_new/π_old at one stored
        u is exact this way: the tanh Jacobian is the same float in both and cancels."""
        u = self._check_action(u)
        return mixture_log_prob(u, jnp.tanh(u), self.loc, self.log_scale, self.log_weights, False)

    def sample_pre_squash_and_log_prob(self, key: Array) -> tuple[Array, Array]:
        """:meth:`sample_and_log_prob` returning the pre-squash point u (..., A) instead of the action
        tanh(u): what an on-policy rollout stores for :meth:`log_prob_pre_squash` later."""
        u, _ = self._sample_pre_squash(key)
        return u, mixture_log_prob(u, jnp.tanh(u), self.loc, self.log_scale, self.log_weights, False)

    def entropy_estimate(self, key: Array) -> Array:
        """An unbiased, differentiable estimate of the mixture's entropy H(π(·|s)) (...), which has no
        closed form: one reparameterised draw per component, a_k = tanh(μ_k + σ_k ε_k), and
        -Σ_k w_k log π(a_k|s) under the full mixture, the exact expectation over the component k (the
        estimator of XSAC's actor loss, eq. 8-9, without its density floor). Gradients reach the weights
        through the sum and the components through the draws."""
        _, log_probs = self.sample_per_component(key, floor_density=False)
        return -jnp.sum(self.weights * log_probs, axis=-1)

    def component_log_prob(self, action: Array) -> Array:
        """log h_k(a) of every component alone (no weight): (..., K). For explanations."""
        action = self._check_action(action)
        u = safe_atanh(action)[..., None, :]
        return gaussian_log_density(u, self.loc, self.log_scale) - tanh_log_det(action)[..., None]

    def component_marginal_log_prob(self, action: Array) -> Array:
        """Per-dimension marginal log h(a_d; μ_kd, σ_kd) of every component: (..., K, A).

        The explanation glyphs (§6.3) draw these 1-D marginals per object.
        """
        action = self._check_action(action)[..., None, :]
        z = (safe_atanh(action) - self.loc) * jnp.exp(-self.log_scale)
        return (
            -0.5 * jnp.square(z)
            - self.log_scale
            - HALF_LOG_2PI
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
        log_prob = mixture_log_prob(u, action, self.loc, self.log_scale, self.log_weights, floor_density)
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
        log_density = sets.compact_or_dense(plan, pairwise_among_weighted, pairwise_log_density, *mixture)
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
        log_density = pairwise_log_density(self.loc, self.loc, self.log_scale, self.log_weights)
        log_density = log_density - tanh_log_det(squashed)
        log_density = jnp.where(self.log_weights > 0.5 * ABSENT_LOG_WEIGHT, log_density, -jnp.inf)
        best = jnp.argmax(log_density, axis=-1)
        return jnp.take_along_axis(squashed, best[..., None, None], axis=-2)[..., 0, :]

    def components_distrax(self) -> distrax.Distribution:
        """Per-component squashed Gaussians as one distrax distribution, batch (..., K), event (A,).

        For explanations and plots. Note distrax's Tanh uses the exact Jacobian, not the
        reference's 1e-6 epsilon, and its log_prob is infinite at a = ±1.
        """
        distrax = require_distrax()
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
