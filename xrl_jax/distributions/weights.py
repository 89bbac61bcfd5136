"""Mixture weights over object slots (docs/algorithms.md §3.1), the categorical entropies, and what
both mixtures share: the masking helpers, the :class:`Mixture` base and the optional distrax import.

An absent slot's log weight is the finite ``ABSENT_LOG_WEIGHT``: its weight and gradient are exactly
zero whatever its logit, and 0·value never meets an inf/NaN. A sample without any present slot falls
back to uniform weights over all slots (§3.1.4).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def require_distrax():
    """distrax, an optional extra: only the mixtures' adaptors need it (and the TFP nightly it pulls)."""
    try:
        import distrax
    except ImportError:
        raise ImportError("the distrax adaptors need the extra: pip install 'xrl-jax[distrax]'") from None
    return distrax


PROB_FLOOR = 1e-10
"""Floor of categorical probabilities inside logs, and of p_u in the actor-loss variant (§7.3)."""
ABSENT_LOG_WEIGHT = -1e30
"""Log weight of an absent slot: finite, so ``w·log w`` is 0 (not NaN) and logsumexp ignores it."""


def as_float(x) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def as_present(mask, shape: tuple[int, ...]) -> Array:
    """Boolean present flags; ``None`` means all present. Floats count as present above 0.5."""
    if mask is None:
        return jnp.ones(shape, dtype=bool)
    mask = jnp.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask must have shape {shape} (same as the mixture logits), got {mask.shape}")
    return mask if mask.dtype == jnp.bool_ else mask > 0.5


def effective_present(present: Array) -> Array:
    """Slots that carry weight: the present ones, or all of them if none is present (§3.1.4)."""
    return present | ~jnp.any(present, axis=-1, keepdims=True)


def masked_log_softmax(logits: Array, mask: Array | None = None) -> Array:
    """Log mixture weights over the last axis: log w_o with absent slots at ``ABSENT_LOG_WEIGHT``.

    Written without ``jax.nn.softmax`` so that absent logits (even ±1e4 or 1e20) never enter an
    exp: their weight is exactly 0 and their gradient exactly 0. All-absent rows → uniform 1/O.
    """
    logits = as_float(logits)
    present = as_present(mask, logits.shape)
    any_present = jnp.any(present, axis=-1, keepdims=True)
    effective = present | ~any_present
    logits = jnp.where(any_present, logits, 0.0)  # the fallback ignores the logits: uniform
    shift = jax.lax.stop_gradient(jnp.max(jnp.where(effective, logits, -jnp.inf), axis=-1, keepdims=True))
    shifted = jnp.where(effective, logits - shift, ABSENT_LOG_WEIGHT)
    log_norm = jnp.log(jnp.sum(jnp.exp(shifted), axis=-1, keepdims=True))  # ≥ 0: the max term is 1
    return jnp.where(effective, shifted - log_norm, ABSENT_LOG_WEIGHT)


def masked_logits(logits: Array, mask: Array | None = None) -> Array:
    """Logits with absent slots at ``ABSENT_LOG_WEIGHT`` (finite, so 0·logit stays 0)."""
    logits = as_float(logits)
    return jnp.where(as_present(mask, logits.shape), logits, ABSENT_LOG_WEIGHT)


def sample_slot(key: Array, masked: Array, mask: Array | None = None) -> Array:
    """One slot per row drawn from :func:`masked_logits` output (..., K): absent slots are never
    drawn, and a row without any present slot draws uniformly over all slots (§3.1.4)."""
    present = as_present(mask, masked.shape)
    any_present = jnp.any(present, axis=-1, keepdims=True)
    return jax.random.categorical(key, jnp.where(any_present, masked, 0.0), axis=-1)


def masked_softmax(logits: Array, mask: Array | None = None) -> Array:
    """Mixture weights w_o = m_o·exp(ℓ_o) / Σ_j m_j·exp(ℓ_j) (§3.1), exact zeros on absent slots."""
    return jnp.exp(masked_log_softmax(logits, mask))


def clipped_entropy(probs: Array, axis: int = -1) -> Array:
    """H(p) = -Σ p·log clip(p, 1e-10, 1), the reference's form for every categorical entropy (§7.3)."""
    return -jnp.sum(probs * jnp.log(jnp.clip(probs, PROB_FLOOR, 1.0)), axis=axis)


class Mixture:
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
        return effective_present(self.present)

    def weights_entropy(self) -> Array:
        """H(w) = -Σ_k w_k log clip(w_k, 1e-10, 1): the κ regulariser's entropy (eq. 10, §3.6)."""
        return clipped_entropy(self.weights)
