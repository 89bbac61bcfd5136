"""Mixture policies over objects: categorical mixture (paper eq. 3) and squashed diagonal
Gaussian mixture (paper eq. 6-7), docs/algorithms.md §3.

Both distributions are ``flax.struct`` dataclasses (pytrees), so they can be built inside a
jitted function, returned from it, vmapped and scanned. Every array has arbitrary leading batch
axes ``...``; the component axis (one component per object slot, or ``O·C`` flattened
object-major) is the last axis before the action axis.

Masking: absent slots get exactly zero weight and exactly zero gradient, whatever their logits
or parameters (absent parameters are replaced by harmless constants before use, so 0·value
never meets an inf/NaN). A sample without any present slot falls back to uniform weights over
all slots (§3.1.4).

Modules, by what they hold:

* :mod:`~xrl_jax.distributions.weights`: the masked mixture weights, the categorical entropies and
  what both mixtures share;
* :mod:`~xrl_jax.distributions.gaussian_density`: the squashed Gaussian pieces and log densities,
  among them the pairwise mixture density of eq. 9 with its own gradient;
* :mod:`~xrl_jax.distributions.gaussian_mixture`: :class:`SquashedGaussianMixture` (XSAC, and SAC
  as one component);
* :mod:`~xrl_jax.distributions.categorical_mixture`: :class:`CategoricalMixture` (XDSAC, DSAC).

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

from xrl_jax.config import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, SAC_LOG_STD_MIN  # the log-σ bounds' home
from xrl_jax.distributions.categorical_mixture import CategoricalMixture
from xrl_jax.distributions.gaussian_density import TANH_JACOBIAN_EPS, clip_log_std, safe_atanh, tanh_log_det
from xrl_jax.distributions.gaussian_mixture import SquashedGaussianMixture, squashed_gaussian
from xrl_jax.distributions.weights import (
    ABSENT_LOG_WEIGHT,
    PROB_FLOOR,
    clipped_entropy,
    masked_log_softmax,
    masked_logits,
    masked_softmax,
    sample_slot,
)

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
