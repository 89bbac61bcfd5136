"""Actors of SAC, discrete SAC, XSAC and XDSAC (docs/algorithms.md §2, §3.7, §4.3).

The actors return **raw** head outputs: mixture logits for every slot (centred, not masked), log σ
as the head produced it (not clipped) and the present mask. Turning them into a policy — masking
absent objects, clipping log σ, the mixture weights — is the job of :mod:`xrl_jax.distributions`
(``agents.Agent.policy_from_output``). The fast acting paths sample on their own and use the same
distribution-owned masking and clipping. Conventions as in :mod:`xrl_jax.extractors`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax.distributions import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, clip_log_std, masked_logits, sample_slot
from xrl_jax.extractors import MLP, Observation, object_inputs

Array = jax.Array


def centre(logits: Array) -> Array:
    """Logits minus their mean over the last axis: the mixture logits over **all** slots (§3.1 step 2)
    and the action logits of the categorical heads; a no-op for the softmax."""
    return logits - jnp.mean(logits, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Per-object ("myopic") mixture actors
# ---------------------------------------------------------------------------------------------


def _resolve_weight_depth(weight_depth: int | None, depth: int) -> int:
    resolved = depth if weight_depth is None else weight_depth
    if not 1 <= resolved <= depth:
        raise ValueError(f"weight_depth (φ_d) must be in 1..{depth} (hidden depth), got {weight_depth}")
    return resolved


def _select_object(values: Array, index: Array) -> Array:
    """Pick ``values[..., index, :]`` per batch element; values (..., O, D), index (...,) int."""
    return jnp.take_along_axis(values, index[..., None, None], axis=-2)[..., 0, :]


@struct.dataclass
class GaussianMixtureOutput:
    """Full XSAC actor output for every object slot (§4.3 explanation outputs), raw.

    means, log_stds: (..., O, C, A), log_stds not clipped; mixture_logits: (..., O), centred over all
    slots, absent slots not masked; present: (..., O) bool.
    """

    means: Array
    log_stds: Array
    mixture_logits: Array
    present: Array


@struct.dataclass
class CategoricalMixtureOutput:
    """Full XDSAC actor output (§2.4, §4.3), raw.

    logits: (..., O, N) per-object action logits, centred over actions, absent slots not masked;
    mixture_logits: (..., O) as in GaussianMixtureOutput; present: (..., O) bool.
    """

    logits: Array
    mixture_logits: Array
    present: Array


@struct.dataclass
class FastSample:
    """Result of an actor's fast acting path (§3.7).

    action: (..., A) float (continuous) or (...,) int32 (discrete); object_index: (...,) sampled object;
    component_index: (...,) sampled component (always 0 for discrete); mixture_logits: (..., O) the
    full output's logits masked by ``distributions.masked_logits``, which the object was drawn from;
    head: the chosen object's head outputs as the sample used them, for checks and explanations —
    continuous ``(means (..., C, A), log_stds (..., C, A))`` with log σ clipped, discrete ``logits (..., N)``.
    """

    action: Array
    object_index: Array
    component_index: Array
    mixture_logits: Array
    head: Any


class _MyopicTrunk(nn.Module):
    """Shared per-object trunk with the φ branch after hidden layer ``weight_depth`` (1-based φ_d).

    ``branch(x)`` runs layers 1..φ_d (the part needed for the mixture logits, all objects);
    ``rest(h)`` runs layers φ_d+1..depth (only needed for the action head, so the fast path runs it
    for the sampled object only). ``uniform_mixture`` drops φ (all logits 0).
    """

    width: int
    depth: int
    weight_depth: int
    uniform_mixture: bool = False

    def setup(self):
        self.layers = [nn.Dense(self.width, name=f"hidden_{i}") for i in range(self.depth)]
        if not self.uniform_mixture:
            self.mixture_logit = nn.Dense(1, name="mixture_logit")

    def branch(self, x: Array) -> Array:
        for layer in self.layers[: self.weight_depth]:
            x = nn.relu(layer(x))
        return x

    def rest(self, h: Array) -> Array:
        for layer in self.layers[self.weight_depth :]:
            h = nn.relu(layer(h))
        return h

    def mixture_logits(self, h: Array) -> Array:
        """Centred mixture logits (..., O) from the branch output."""
        if self.uniform_mixture:  # ablation of §3.1.6: no φ, uniform weights over present objects
            return jnp.zeros(h.shape[:-1], h.dtype)
        return centre(self.mixture_logit(h)[..., 0])

    def __call__(self, x: Array) -> tuple[Array, Array]:
        h = self.branch(x)
        return self.rest(h), self.mixture_logits(h)

    def sample_object(self, x: Array, present: Array, key: Array) -> tuple[Array, Array, Array]:
        """Fast path, first half: the branch for all objects, then an object drawn from the masked
        mixture logits. Returns (the chosen object's last hidden layer, those masked logits, the index)."""
        h = self.branch(x)
        logits = masked_logits(self.mixture_logits(h), present)
        object_index = sample_slot(key, logits, present)
        return self.rest(_select_object(h, object_index)), logits, object_index


class MixtureGaussianActor(nn.Module):
    """XSAC per-object actor (§2.3, §4.3): one squashed-Gaussian mixture component per object.

    For every slot o: μ, log σ ∈ R^{C×A} and a mixture logit from a linear φ on hidden layer
    ``weight_depth`` (φ_d ∈ 1..depth, default the last, as in every config). No feature extractor: the
    input is the fixed reshaper ``object_inputs``. ``log_std_min`` / ``log_std_max`` clip the fast
    path's log σ (the full path's outputs are raw).
    """

    action_dim: int = 3
    width: int = 256
    depth: int = 3
    weight_depth: int | None = None
    components_per_object: int = 1
    log_std_min: float = MIXTURE_LOG_STD_MIN
    log_std_max: float = LOG_STD_MAX
    set_key: str | None = None
    neutral_object: bool = False
    neutral_flag: bool = False
    uniform_mixture: bool = False

    def setup(self):
        if self.depth < 1 or self.components_per_object < 1 or self.action_dim < 1:
            raise ValueError("depth, components_per_object and action_dim must be >= 1")
        weight_depth = _resolve_weight_depth(self.weight_depth, self.depth)
        self.trunk = _MyopicTrunk(self.width, self.depth, weight_depth, self.uniform_mixture)
        self.mean_head = nn.Dense(self.action_dim * self.components_per_object, name="mean")
        self.log_std_head = nn.Dense(self.action_dim * self.components_per_object, name="log_std")

    def _heads(self, h: Array) -> tuple[Array, Array]:
        shape = (*h.shape[:-1], self.components_per_object, self.action_dim)
        return self.mean_head(h).reshape(shape), self.log_std_head(h).reshape(shape)

    def __call__(self, obs: Observation) -> GaussianMixtureOutput:
        """Full path: every object's component parameters and mixture logit."""
        inputs, present = object_inputs(obs, self.set_key, self.neutral_object, self.neutral_flag)
        h, mixture_logits = self.trunk(inputs)
        means, log_stds = self._heads(h)
        return GaussianMixtureOutput(means, log_stds, mixture_logits, present)

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Fast acting path (§3.7): sample the object first, then run the rest for it alone.

        Layers 1..φ_d and φ run for all O objects (the logits need them); layers φ_d+1..depth and the
        μ / log σ heads run once per sample. Distributionally identical to full-mixture sampling.
        """
        inputs, present = object_inputs(obs, self.set_key, self.neutral_object, self.neutral_flag)
        key_object, key_component, key_noise = jax.random.split(key, 3)
        h, logits, object_index = self.trunk.sample_object(inputs, present, key_object)
        means, log_stds = self._heads(h)
        shape = object_index.shape
        component_index = jax.random.randint(key_component, shape, 0, self.components_per_object)
        log_stds = clip_log_std(log_stds, self.log_std_min, self.log_std_max)
        mean = _select_object(means, component_index)
        log_std = _select_object(log_stds, component_index)
        noise = jax.random.normal(key_noise, mean.shape, mean.dtype)
        action = jnp.tanh(mean + jnp.exp(log_std) * noise)
        return FastSample(action, object_index, component_index, logits, (means, log_stds))


class MixtureCategoricalActor(nn.Module):
    """XDSAC per-object actor (§2.4, §4.3): per object N action logits (centred over actions) and a
    mixture logit. The reference always branches φ off the last hidden layer; ``weight_depth``
    generalises this as for XSAC (paper Table I).
    """

    num_actions: int = 12
    width: int = 256
    depth: int = 3
    weight_depth: int | None = None
    set_key: str | None = None
    neutral_object: bool = False
    neutral_flag: bool = False
    uniform_mixture: bool = False

    def setup(self):
        if self.depth < 1 or self.num_actions < 1:
            raise ValueError("depth and num_actions must be >= 1")
        weight_depth = _resolve_weight_depth(self.weight_depth, self.depth)
        self.trunk = _MyopicTrunk(self.width, self.depth, weight_depth, self.uniform_mixture)
        self.logit_head = nn.Dense(self.num_actions, name="logits")

    def __call__(self, obs: Observation) -> CategoricalMixtureOutput:
        inputs, present = object_inputs(obs, self.set_key, self.neutral_object, self.neutral_flag)
        h, mixture_logits = self.trunk(inputs)
        return CategoricalMixtureOutput(centre(self.logit_head(h)), mixture_logits, present)

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Ancestral sampling (paper eq. after (3)): object from the weights, action from its head only."""
        inputs, present = object_inputs(obs, self.set_key, self.neutral_object, self.neutral_flag)
        key_object, key_action = jax.random.split(key)
        h, logits, object_index = self.trunk.sample_object(inputs, present, key_object)
        action_logits = centre(self.logit_head(h))
        action = jax.random.categorical(key_action, action_logits, axis=-1).astype(jnp.int32)
        return FastSample(action, object_index, jnp.zeros_like(object_index), logits, action_logits)


# ---------------------------------------------------------------------------------------------
# Baseline actors (SAC, DSAC)
# ---------------------------------------------------------------------------------------------


@struct.dataclass
class GaussianOutput:
    """SAC actor output: pre-tanh mean and raw (not clipped) log-std, each (..., A)."""

    mean: Array
    log_std: Array


class GaussianActor(nn.Module):
    """SAC actor (§2.1): own extractor → MLP → linear μ and log σ.

    The squashed-Gaussian sample is tanh(μ + σ ε); clipping, sampling and log-prob live in
    ``distributions`` (``squashed_gaussian``).
    """

    extractor: nn.Module
    action_dim: int = 3
    widths: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, obs: Observation) -> GaussianOutput:
        h = MLP(self.widths, name="mlp")(self.extractor(obs))
        mean = nn.Dense(self.action_dim, name="mean")(h)
        return GaussianOutput(mean, nn.Dense(self.action_dim, name="log_std")(h))


class CategoricalActor(nn.Module):
    """DSAC actor (§2.2): own extractor → MLP → N logits centred over actions, (..., N)."""

    extractor: nn.Module
    num_actions: int = 12
    widths: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        logits = nn.Dense(self.num_actions, name="logits")(MLP(self.widths, name="mlp")(self.extractor(obs)))
        return centre(logits)


__all__ = [
    "CategoricalActor",
    "CategoricalMixtureOutput",
    "FastSample",
    "GaussianActor",
    "GaussianMixtureOutput",
    "GaussianOutput",
    "MixtureCategoricalActor",
    "MixtureGaussianActor",
    "centre",
]
