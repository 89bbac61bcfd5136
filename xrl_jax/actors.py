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

from xrl_jax import sets
from xrl_jax.distributions import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, clip_log_std, masked_logits, sample_slot
from xrl_jax.extractors import MLP, ObjectStateDense, Observation, object_rows

Array = jax.Array


def centre(logits: Array) -> Array:
    """Logits minus their mean over the last axis: the action logits of the categorical heads; a no-op
    for the softmax."""
    return logits - jnp.mean(logits, axis=-1, keepdims=True)


def centre_over(logits: Array, mask: Array) -> Array:
    """Mixture logits minus their mean over the slots of ``mask`` (§3.1 step 2, over the slots that
    carry weight: §3.1 allows dropping the centring, a no-op for the masked softmax and its gradient;
    centring over the weighted slots only keeps it computable from the present objects alone)."""
    count = jnp.maximum(jnp.sum(mask, axis=-1, keepdims=True), 1).astype(logits.dtype)
    return logits - jnp.sum(jnp.where(mask, logits, 0.0), axis=-1, keepdims=True) / count


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

    means, log_stds: (..., O, C, A), log_stds not clipped; mixture_logits: (..., O), centred over the
    slots that carry weight, absent slots not masked; present: (..., O) bool. Slots without weight
    hold the network's output on the padding row, or zeros when computed on present rows only.
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

    ``branch(objects, state)`` runs layers 1..φ_d (the part needed for the mixture logits, all
    objects; the first layer joins each object to the state, :class:`ObjectStateDense`);
    ``rest(h)`` runs layers φ_d+1..depth (only needed for the action head, so the fast path runs it
    for the sampled object only). ``raw_logits`` is φ (uncentred); ``uniform_mixture`` drops φ.
    """

    width: int
    depth: int
    weight_depth: int
    uniform_mixture: bool = False

    def setup(self):
        first = ObjectStateDense(self.width, name="hidden_0")
        self.layers = [first] + [nn.Dense(self.width, name=f"hidden_{i}") for i in range(1, self.depth)]
        if not self.uniform_mixture:
            self.mixture_logit = nn.Dense(1, name="mixture_logit")

    def branch(self, objects: Array, state: Array, plan: sets.PresentRows | None = None) -> Array:
        x = nn.relu(self.layers[0](objects, state, plan))
        for layer in self.layers[1 : self.weight_depth]:
            x = nn.relu(layer(x))
        return x

    def rest(self, h: Array) -> Array:
        for layer in self.layers[self.weight_depth :]:
            h = nn.relu(layer(h))
        return h

    def raw_logits(self, h: Array) -> Array:
        """Mixture logits (...) from the branch output, before centring."""
        if self.uniform_mixture:  # ablation of §3.1.6: no φ, uniform weights over present objects
            return jnp.zeros(h.shape[:-1], h.dtype)
        return self.mixture_logit(h)[..., 0]


def _dense_objects(mdl, objects: Array, state: Array) -> tuple[Array, ...]:
    return mdl.per_object(objects, state)


def _packed_objects(mdl, plan: sets.PresentRows, objects: Array, state: Array) -> tuple[Array, ...]:
    packed = mdl.per_object(sets.pack(objects, plan), state, plan)
    return tuple(sets.unpack(x, plan) for x in packed)


def _dense_pick(mdl, objects: Array, state: Array, weighted: Array, present: Array, key: Array):
    h = mdl.trunk.branch(objects, state)
    logits = masked_logits(centre_over(mdl.trunk.raw_logits(h), weighted), present)
    index = sample_slot(key, logits, present)
    return _select_object(h, index), logits, index


def _packed_pick(mdl, plan, objects: Array, state: Array, weighted: Array, present: Array, key: Array):
    h = mdl.trunk.branch(sets.pack(objects, plan), state, plan)
    raw = sets.unpack(mdl.trunk.raw_logits(h), plan)
    logits = masked_logits(centre_over(raw, weighted), present)
    index = sample_slot(key, logits, present)  # drawn over every slot: the same draw as dense
    rows = jnp.take_along_axis(plan.row.reshape(present.shape), index[..., None], axis=-1)[..., 0]
    chosen = jnp.concatenate([h, jnp.zeros((1, h.shape[-1]), h.dtype)])[rows]
    return chosen, logits, index


class _MixtureActor(nn.Module):
    """What both mixture actors share: the object rows, the packing of their weighted rows, the
    full path's per-object outputs and the fast path's object draw. Subclasses hold the fields
    ``set_key``, ``neutral_object``, ``neutral_flag`` and ``packing``, a ``trunk`` and ``per_object``."""

    def rows(self, obs: Observation) -> tuple[Array, Array, Array, Array]:
        """Objects (..., O, F), state (..., S), the present mask and the slots carrying weight (the
        present ones, or all of a set without any, §3.1.4): those the per-object layers must see."""
        objects, state, present = object_rows(obs, self.set_key, self.neutral_object, self.neutral_flag)
        return objects, state, present, present | ~jnp.any(present, axis=-1, keepdims=True)

    def all_objects(self, obs: Observation) -> tuple[tuple[Array, ...], Array, Array]:
        """``per_object`` outputs for every slot (zeros where no weight falls when packed), the
        mixture logits centred over the weighted slots, and the present mask."""
        objects, state, present, weighted = self.rows(obs)
        plan = sets.plan_for(weighted, self.packing)
        *heads, logits = sets.packed_or_dense(self, plan, _packed_objects, _dense_objects, objects, state)
        return tuple(heads), centre_over(logits, weighted), present

    def pick_object(self, obs: Observation, key: Array) -> tuple[Array, Array, Array]:
        """Fast path, first half: the branch for all objects, then an object drawn from the masked
        mixture logits. Returns (the chosen object's last hidden layer, those masked logits, the index)."""
        objects, state, present, weighted = self.rows(obs)
        plan = sets.plan_for(weighted, self.packing)
        h, logits, index = sets.packed_or_dense(
            self, plan, _packed_pick, _dense_pick, objects, state, weighted, present, key
        )
        return self.trunk.rest(h), logits, index


class MixtureGaussianActor(_MixtureActor):
    """XSAC per-object actor (§2.3, §4.3): one squashed-Gaussian mixture component per object.

    For every slot o: μ, log σ ∈ R^{C×A} and a mixture logit from a linear φ on hidden layer
    ``weight_depth`` (φ_d ∈ 1..depth, default the last, as in every config). No feature extractor: the
    input is the fixed reshaper ``object_inputs``. ``log_std_min`` / ``log_std_max`` clip the fast
    path's log σ (the full path's outputs are raw). With ``packing`` the per-object layers run on the
    slots that carry weight only (:mod:`xrl_jax.sets`); the result is the same.
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
    packing: sets.Packing | None = None

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

    def per_object(self, objects: Array, state: Array, plan=None) -> tuple[Array, Array, Array]:
        h = self.trunk.branch(objects, state, plan)
        means, log_stds = self._heads(self.trunk.rest(h))
        return means, log_stds, self.trunk.raw_logits(h)

    def __call__(self, obs: Observation) -> GaussianMixtureOutput:
        """Full path: every object's component parameters and mixture logit."""
        (means, log_stds), mixture_logits, present = self.all_objects(obs)
        return GaussianMixtureOutput(means, log_stds, mixture_logits, present)

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Fast acting path (§3.7): sample the object first, then run the rest for it alone.

        Layers 1..φ_d and φ run for all O objects (the logits need them); layers φ_d+1..depth and the
        μ / log σ heads run once per sample. Distributionally identical to full-mixture sampling.
        """
        key_object, key_component, key_noise = jax.random.split(key, 3)
        h, logits, object_index = self.pick_object(obs, key_object)
        means, log_stds = self._heads(h)
        shape = object_index.shape
        component_index = jax.random.randint(key_component, shape, 0, self.components_per_object)
        log_stds = clip_log_std(log_stds, self.log_std_min, self.log_std_max)
        mean = _select_object(means, component_index)
        log_std = _select_object(log_stds, component_index)
        noise = jax.random.normal(key_noise, mean.shape, mean.dtype)
        action = jnp.tanh(mean + jnp.exp(log_std) * noise)
        return FastSample(action, object_index, component_index, logits, (means, log_stds))


class MixtureCategoricalActor(_MixtureActor):
    """XDSAC per-object actor (§2.4, §4.3): per object N action logits (centred over actions) and a
    mixture logit. The reference always branches φ off the last hidden layer; ``weight_depth``
    generalises this as for XSAC (paper Table I). ``packing`` as for :class:`MixtureGaussianActor`.
    """

    num_actions: int = 12
    width: int = 256
    depth: int = 3
    weight_depth: int | None = None
    set_key: str | None = None
    neutral_object: bool = False
    neutral_flag: bool = False
    uniform_mixture: bool = False
    packing: sets.Packing | None = None

    def setup(self):
        if self.depth < 1 or self.num_actions < 1:
            raise ValueError("depth and num_actions must be >= 1")
        weight_depth = _resolve_weight_depth(self.weight_depth, self.depth)
        self.trunk = _MyopicTrunk(self.width, self.depth, weight_depth, self.uniform_mixture)
        self.logit_head = nn.Dense(self.num_actions, name="logits")

    def per_object(self, objects: Array, state: Array, plan=None) -> tuple[Array, Array]:
        h = self.trunk.branch(objects, state, plan)
        return centre(self.logit_head(self.trunk.rest(h))), self.trunk.raw_logits(h)

    def __call__(self, obs: Observation) -> CategoricalMixtureOutput:
        (logits,), mixture_logits, present = self.all_objects(obs)
        return CategoricalMixtureOutput(logits, mixture_logits, present)

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Ancestral sampling (paper eq. after (3)): object from the weights, action from its head only."""
        key_object, key_action = jax.random.split(key)
        h, logits, object_index = self.pick_object(obs, key_object)
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
    "centre_over",
]
