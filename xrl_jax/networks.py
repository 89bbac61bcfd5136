"""Flax (linen) networks for SAC, discrete SAC and their explainable mixture variants XSAC / XDSAC.

Reference: docs/algorithms.md §2-§4 and §7; paper §III-F and Table I.

Conventions shared by every module here:

* Observations are dicts ``{"state": (..., S), "<name>_set": (..., O, F_obj)}``; column 0 of the set is
  the present flag. Every module accepts arbitrary leading batch axes ``...`` (also none).
* Absent object rows are masked with ``where`` (never boolean indexing), so shapes never depend on
  data and absent rows may hold any finite values without changing any output.
* Ensembles of critics are stacked on a new **leading** axis: ``(n_critics, ...)``.
* All layers use Flax defaults (LeCun-normal kernels, zero biases) except the Fourier layer (§4.4).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax.distributions import masked_softmax

Array = jax.Array
Observation = Mapping[str, Array]

STATE_KEY = "state"
# Finite stand-in for -inf on absent objects' mixture logits (§7.3): finite so that 0 * logit = 0.
MASKED_LOGIT = -1e20
# log-std clips: XSAC mixtures (CleanRL-style, §2.3) and the SAC baseline (SB3 limits, §2.1).
MIXTURE_LOG_STD_RANGE = (-5.0, 2.0)
BASELINE_LOG_STD_RANGE = (-20.0, 2.0)


def _float_dtype():
    return jnp.result_type(float)


# ---------------------------------------------------------------------------------------------
# Observation helpers (no parameters)
# ---------------------------------------------------------------------------------------------


def find_set_key(obs: Observation) -> str:
    """Return the single observation key ending in ``_set`` (§0), with a clear error otherwise."""
    set_keys = [k for k in obs if k.endswith("_set")]
    if len(set_keys) != 1 or STATE_KEY not in obs or len(obs) != 2:
        raise ValueError(
            f"observation must have exactly the keys 'state' and one '*_set' key, got {sorted(obs)}"
        )
    return set_keys[0]


def _split_observation(obs: Observation, set_key: str | None) -> tuple[str, Array, Array]:
    key = find_set_key(obs) if set_key is None else set_key
    if key not in obs or STATE_KEY not in obs:
        raise KeyError(f"observation needs keys 'state' and {key!r}, got {sorted(obs)}")
    objects, state = jnp.asarray(obs[key]), jnp.asarray(obs[STATE_KEY])
    if objects.ndim < 2 or state.ndim < 1:
        raise ValueError(
            f"expected set (..., O, F) and state (..., S), got {objects.shape} and {state.shape}"
        )
    if objects.shape[:-2] != state.shape[:-1]:
        raise ValueError(
            f"set {objects.shape} and state {state.shape} must share their leading batch axes "
            f"({objects.shape[:-2]} vs {state.shape[:-1]})"
        )
    return key, objects, state


def present_mask(objects: Array) -> Array:
    """Boolean (..., O) mask from the present flag in column 0 (§4.1: ``x[..., 0] > 0``)."""
    return objects[..., 0] > 0


def object_inputs(
    obs: Observation, set_key: str | None = None, neutral_slot: bool = False
) -> tuple[Array, Array]:
    """The X-actor observation reshaper (§4.1): per-object rows ``[x_o, z]`` and the present mask.

    The object row keeps its present flag (and, for tracking, the index column); the state ``z`` is
    broadcast to every slot. ``neutral_slot`` prepends a present, all-zero object (multi-agent only),
    whose component therefore sees only the state.

    Returns ``(inputs (..., O[+1], F_obj + S), present (..., O[+1]) bool)``.
    """
    _, objects, state = _split_observation(obs, set_key)
    dtype = jnp.result_type(objects, state)
    objects, state = objects.astype(dtype), state.astype(dtype)
    if neutral_slot:
        neutral = jnp.zeros((*objects.shape[:-2], 1, objects.shape[-1]), dtype).at[..., 0].set(1.0)
        objects = jnp.concatenate([neutral, objects], axis=-2)
    tiled_state = jnp.broadcast_to(state[..., None, :], objects.shape[:-1] + state.shape[-1:])
    return jnp.concatenate([objects, tiled_state], axis=-1), present_mask(objects)


def tracking_index_feature(length: int) -> Array:
    """Index column of the tracking set: ``2 i / L - 1`` for ``i = 0..L-1`` (§4.2, §7.2.10).

    **Quirk kept for parity:** divides by L, not L - 1, so it spans [-1, 1 - 2/L] (-1 ... 0.92 for L = 25).
    """
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}")
    return 2.0 * jnp.arange(length, dtype=_float_dtype()) / length - 1.0


def trajectory_to_set(trajectory: Array) -> Array:
    """Sequence → set conversion (§4.2): flat (..., 2L) points → rows ``[1, index_i, x_i, y_i]``."""
    trajectory = jnp.asarray(trajectory)
    if trajectory.shape[-1] % 2:
        raise ValueError(f"flat trajectory must have an even last axis (x, y pairs), got {trajectory.shape}")
    length = trajectory.shape[-1] // 2
    points = trajectory.reshape((*trajectory.shape[:-1], length, 2))
    index = tracking_index_feature(length).astype(points.dtype)
    batch = points.shape[:-1]
    return jnp.concatenate(
        [jnp.ones((*batch, 1), points.dtype), jnp.broadcast_to(index[:, None], (*batch, 1)), points],
        axis=-1,
    )


def positional_encoding(values: Array, num_freqs: int = 4, include_input: bool = True) -> Array:
    """Fourier positional encoding of a vector (§4.4), frequency-major layout.

    ``[cos(π 2^k v)]_k ⊕ [sin(π 2^k v)]_k ⊕ v`` as a (2F[+1], D) array flattened row by row,
    giving (2F + 1)·D features (9·D for the default F = 4).
    """
    values = jnp.asarray(values)
    scales = jnp.pi * 2.0 ** jnp.arange(num_freqs, dtype=values.dtype)
    angles = scales[:, None] * values[..., None, :]  # (..., F, D)
    rows = [jnp.cos(angles), jnp.sin(angles)]
    if include_input:
        rows.append(values[..., None, :])
    stacked = jnp.concatenate(rows, axis=-2)
    return stacked.reshape((*values.shape[:-1], -1))


def masked_mixture_weights(logits: Array, present: Array) -> Array:
    """Masked softmax over the object axis (§3.1 steps 3-4): ``distributions.masked_softmax``.

    Absent slots get exactly 0 and no gradient whatever their logit; a sample without any present
    slot falls back to uniform 1/O.
    """
    return masked_softmax(logits, present)


def centre_and_mask_logits(raw_logits: Array, present: Array) -> Array:
    """Centre over **all** slots (§3.1 step 2, a no-op for the softmax), then mask absent slots."""
    centred = raw_logits - jnp.mean(raw_logits, axis=-1, keepdims=True)
    return jnp.where(present, centred, MASKED_LOGIT)


# ---------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------


class MLP(nn.Module):
    """Dense + ReLU per width (§4: ReLU everywhere); ``activate_final=False`` keeps the last linear."""

    widths: Sequence[int]
    activate_final: bool = True

    @nn.compact
    def __call__(self, x: Array) -> Array:
        for i, width in enumerate(self.widths):
            x = nn.Dense(width, name=f"dense_{i}")(x)
            if self.activate_final or i + 1 < len(self.widths):
                x = nn.relu(x)
        return x


def fourier_kernel_init(scale: float):
    """W ~ N(0, (scale / d_in)²), plain (not truncated) normal (§4.4, §7.2.11)."""

    def init(key, shape, dtype=jnp.float32):
        return (scale / shape[0]) * jax.random.normal(key, shape, dtype)

    return init


def uniform_symmetric_init(key, shape, dtype=jnp.float32):
    """b ~ U(-1, 1) (§4.4)."""
    return jax.random.uniform(key, shape, dtype, -1.0, 1.0)


class FourierFeatures(nn.Module):
    """Learned Fourier features ``sin(π (W x + b))`` (LFF, §4.4); no ReLU afterwards, W and b trained."""

    features: int
    scale: float = 30.0

    @nn.compact
    def __call__(self, x: Array) -> Array:
        projected = nn.Dense(
            self.features,
            kernel_init=fourier_kernel_init(self.scale),
            bias_init=uniform_symmetric_init,
            name="linear",
        )(x)
        return jnp.sin(jnp.pi * projected)


class DeepSet(nn.Module):
    """Deep Set with learned Fourier features (LFF-DS, §4.4) on a padded set (..., O, F_obj).

    The present column (0) is dropped from the items; item encodings of absent slots are zeroed before
    the sum, so the output is invariant to slot order and to the contents of absent rows.
    ``fourier_scale=None`` replaces the Fourier layer by Dense + ReLU (``set_ffn: false``).
    """

    width: int = 128
    item_depth: int = 3
    set_depth: int = 2
    fourier_scale: float | None = 30.0

    @nn.compact
    def __call__(self, objects: Array) -> Array:
        if self.item_depth < 1:
            raise ValueError(f"item_depth must be >= 1, got {self.item_depth}")
        present = present_mask(objects)
        items = objects[..., 1:]
        if self.fourier_scale is None:
            h = nn.relu(nn.Dense(self.width, name="item_0")(items))
        else:
            h = FourierFeatures(self.width, self.fourier_scale, name="item_0")(items)
        for i in range(1, self.item_depth):
            h = nn.relu(nn.Dense(self.width, name=f"item_{i}")(h))
        pooled = jnp.sum(jnp.where(present[..., None], h, 0.0), axis=-2)
        return MLP((self.width,) * self.set_depth, name="set_encoder")(pooled)


class DeepSetExtractor(nn.Module):
    """Country Road / intersection critic and baseline-actor extractor (§4.4, ``deepset``).

    Concatenates, in sorted key order (``cones_set`` then ``state``), the LFF Deep Set of the set and
    Dense(state_width) + ReLU of the state: 128 + 128 = 256 features by default. The intersection
    (Appendix A, docs/carenv-intersection.md §8.7) uses width 256 and no Fourier layer (``vehicles_set``
    then ``state``: 256 + 256 features); the layer counts (item 3, set 2) are the same.
    """

    width: int = 128
    item_depth: int = 3
    set_depth: int = 2
    fourier_scale: float | None = 30.0
    state_width: int = 128

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        set_key, objects, state = _split_observation(obs, None)
        parts = {
            set_key: DeepSet(
                self.width, self.item_depth, self.set_depth, self.fourier_scale, name="deep_set"
            )(objects),
            STATE_KEY: nn.relu(nn.Dense(self.state_width, name="state_encoder")(state)),
        }
        return jnp.concatenate([parts[k] for k in sorted(parts)], axis=-1)


class FlatPEExtractor(nn.Module):
    """Parameter-free tracking extractor (§4.4, ``tracking_flat``).

    In sorted key order (``state`` then ``trajectory_set``): PE(state) ⊕ PE(flattened points), where the
    points drop the first ``meta_columns`` columns (present and index). 9·S + 9·2L features by default.
    """

    num_freqs: int = 4
    include_input: bool = True
    meta_columns: int = 2

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        set_key, objects, state = _split_observation(obs, None)
        points = objects[..., self.meta_columns :]
        flat = points.reshape((*points.shape[:-2], -1))
        parts = {
            set_key: positional_encoding(flat, self.num_freqs, self.include_input),
            STATE_KEY: positional_encoding(state, self.num_freqs, self.include_input),
        }
        return jnp.concatenate([parts[k] for k in sorted(parts)], axis=-1)


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
    """Full XSAC actor output for every object slot (§4.3 explanation outputs).

    means, log_stds: (..., O, C, A), log_stds already clipped; mixture_logits: (..., O), centred over all
    slots and set to MASKED_LOGIT on absent slots; weights: (..., O) object weights w_o (absent → 0);
    present: (..., O) bool.
    """

    means: Array
    log_stds: Array
    mixture_logits: Array
    weights: Array
    present: Array

    @property
    def component_weights(self) -> Array:
        """w_{o,c} = w_o / C (within-object weights are uniform, §3.1.5): (..., O, C)."""
        num_components = self.means.shape[-2]
        return jnp.broadcast_to(self.weights[..., None] / num_components, self.means.shape[:-1])


@struct.dataclass
class CategoricalMixtureOutput:
    """Full XDSAC actor output (§2.4, §4.3).

    logits: (..., O, N) per-object action logits, centred over actions, zeros on absent slots;
    mixture_logits: (..., O) as in GaussianMixtureOutput; weights: (..., O); present: (..., O) bool.
    """

    logits: Array
    mixture_logits: Array
    weights: Array
    present: Array

    @property
    def object_probs(self) -> Array:
        """q_o = softmax(logits_o): (..., O, N) (absent slots uniform)."""
        return jax.nn.softmax(self.logits, axis=-1)

    @property
    def probs(self) -> Array:
        """Mixture π(a|s) = Σ_o w_o q_o(a): (..., N)."""
        return jnp.einsum("...o,...on->...n", self.weights, self.object_probs)


@struct.dataclass
class FastSample:
    """Result of an actor's fast acting path (§3.7).

    action: (..., A) float (continuous) or (...,) int32 (discrete); object_index: (...,) sampled object;
    component_index: (...,) sampled component (always 0 for discrete); mixture_logits: (..., O) as in the
    full output; head: the head outputs of the chosen object only, for checks and explanations —
    continuous ``(means (..., C, A), log_stds (..., C, A))``, discrete ``logits (..., N)``.
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

    def raw_logit(self, h: Array) -> Array:
        if self.uniform_mixture:  # ablation of §3.1.6: no φ, uniform weights over present objects
            return jnp.zeros(h.shape[:-1], h.dtype)
        return self.mixture_logit(h)[..., 0]

    def __call__(self, x: Array) -> tuple[Array, Array]:
        h = self.branch(x)
        return self.rest(h), self.raw_logit(h)


class MixtureGaussianActor(nn.Module):
    """XSAC per-object actor (§2.3, §4.3): one squashed-Gaussian mixture component per object.

    For every slot o: μ, log σ ∈ R^{C×A} (log σ clipped to ``log_std_range``) and a mixture logit from
    a linear φ on hidden layer ``weight_depth`` (φ_d ∈ 1..depth, default the last, as in every config).
    No feature extractor: the input is the fixed reshaper ``object_inputs``.
    """

    action_dim: int = 3
    width: int = 256
    depth: int = 3
    weight_depth: int | None = None
    num_components: int = 1
    log_std_range: tuple[float, float] = MIXTURE_LOG_STD_RANGE
    set_key: str | None = None
    neutral_slot: bool = False
    uniform_mixture: bool = False

    def setup(self):
        if self.depth < 1 or self.num_components < 1 or self.action_dim < 1:
            raise ValueError("depth, num_components and action_dim must be >= 1")
        weight_depth = _resolve_weight_depth(self.weight_depth, self.depth)
        self.trunk = _MyopicTrunk(self.width, self.depth, weight_depth, self.uniform_mixture)
        self.mean_head = nn.Dense(self.action_dim * self.num_components, name="mean")
        self.log_std_head = nn.Dense(self.action_dim * self.num_components, name="log_std")

    def _heads(self, h: Array) -> tuple[Array, Array]:
        shape = (*h.shape[:-1], self.num_components, self.action_dim)
        means = self.mean_head(h).reshape(shape)
        log_stds = jnp.clip(self.log_std_head(h).reshape(shape), *self.log_std_range)
        return means, log_stds

    def __call__(self, obs: Observation) -> GaussianMixtureOutput:
        """Full path: every object's component parameters and the mixture weights."""
        inputs, present = object_inputs(obs, self.set_key, self.neutral_slot)
        h, raw_logits = self.trunk(inputs)
        means, log_stds = self._heads(h)
        logits = centre_and_mask_logits(raw_logits, present)
        return GaussianMixtureOutput(
            means, log_stds, logits, masked_mixture_weights(raw_logits, present), present
        )

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Fast acting path (§3.7): sample the object first, then run the rest for it alone.

        Layers 1..φ_d and φ run for all O objects (the logits need them); layers φ_d+1..depth and the
        μ / log σ heads run once per sample. Distributionally identical to full-mixture sampling.
        """
        inputs, present = object_inputs(obs, self.set_key, self.neutral_slot)
        h = self.trunk.branch(inputs)
        logits = centre_and_mask_logits(self.trunk.raw_logit(h), present)
        key_object, key_component, key_noise = jax.random.split(key, 3)
        any_present = jnp.any(present, axis=-1, keepdims=True)
        object_index = jax.random.categorical(key_object, jnp.where(any_present, logits, 0.0), axis=-1)
        means, log_stds = self._heads(self.trunk.rest(_select_object(h, object_index)))
        component_index = jax.random.randint(key_component, object_index.shape, 0, self.num_components)
        mean = _select_object(means, component_index)
        log_std = _select_object(log_stds, component_index)
        noise = jax.random.normal(key_noise, mean.shape, mean.dtype)
        action = jnp.tanh(mean + jnp.exp(log_std) * noise)
        return FastSample(action, object_index, component_index, logits, (means, log_stds))


class MixtureCategoricalActor(nn.Module):
    """XDSAC per-object actor (§2.4, §4.3): per object N action logits (centred over actions,
    zero on absent slots) and a mixture logit. The reference always branches φ off the last hidden
    layer; ``weight_depth`` generalises this as for XSAC (paper Table I).
    """

    num_actions: int = 12
    width: int = 256
    depth: int = 3
    weight_depth: int | None = None
    set_key: str | None = None
    neutral_slot: bool = False
    uniform_mixture: bool = False

    def setup(self):
        if self.depth < 1 or self.num_actions < 1:
            raise ValueError("depth and num_actions must be >= 1")
        weight_depth = _resolve_weight_depth(self.weight_depth, self.depth)
        self.trunk = _MyopicTrunk(self.width, self.depth, weight_depth, self.uniform_mixture)
        self.logit_head = nn.Dense(self.num_actions, name="logits")

    def _head(self, h: Array) -> Array:
        logits = self.logit_head(h)
        return logits - jnp.mean(logits, axis=-1, keepdims=True)

    def __call__(self, obs: Observation) -> CategoricalMixtureOutput:
        inputs, present = object_inputs(obs, self.set_key, self.neutral_slot)
        h, raw_logits = self.trunk(inputs)
        logits = jnp.where(present[..., None], self._head(h), 0.0)
        mixture_logits = centre_and_mask_logits(raw_logits, present)
        return CategoricalMixtureOutput(
            logits, mixture_logits, masked_mixture_weights(raw_logits, present), present
        )

    def sample_fast(self, obs: Observation, key: Array) -> FastSample:
        """Ancestral sampling (paper eq. after (3)): object from the weights, action from its head only."""
        inputs, present = object_inputs(obs, self.set_key, self.neutral_slot)
        h = self.trunk.branch(inputs)
        logits = centre_and_mask_logits(self.trunk.raw_logit(h), present)
        key_object, key_action = jax.random.split(key)
        any_present = jnp.any(present, axis=-1, keepdims=True)
        object_index = jax.random.categorical(key_object, jnp.where(any_present, logits, 0.0), axis=-1)
        action_logits = self._head(self.trunk.rest(_select_object(h, object_index)))
        action = jax.random.categorical(key_action, action_logits, axis=-1).astype(jnp.int32)
        return FastSample(action, object_index, jnp.zeros_like(object_index), logits, action_logits)


# ---------------------------------------------------------------------------------------------
# Baseline actors (SAC, DSAC)
# ---------------------------------------------------------------------------------------------


@struct.dataclass
class GaussianOutput:
    """SAC actor output: pre-tanh mean and clipped log-std, each (..., A)."""

    mean: Array
    log_std: Array


class GaussianActor(nn.Module):
    """SAC actor (§2.1): own extractor → MLP → linear μ and log σ (clipped to [-20, 2]).

    The squashed-Gaussian sample is tanh(μ + σ ε); sampling/log-prob live in ``distributions``.
    """

    extractor: nn.Module
    action_dim: int = 3
    widths: Sequence[int] = (256, 256)
    log_std_range: tuple[float, float] = BASELINE_LOG_STD_RANGE

    @nn.compact
    def __call__(self, obs: Observation) -> GaussianOutput:
        h = MLP(self.widths, name="mlp")(self.extractor(obs))
        mean = nn.Dense(self.action_dim, name="mean")(h)
        log_std = jnp.clip(nn.Dense(self.action_dim, name="log_std")(h), *self.log_std_range)
        return GaussianOutput(mean, log_std)


class CategoricalActor(nn.Module):
    """DSAC actor (§2.2): own extractor → MLP → N logits centred over actions, (..., N)."""

    extractor: nn.Module
    num_actions: int = 12
    widths: Sequence[int] = (256, 256)

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        h = MLP(self.widths, name="mlp")(self.extractor(obs))
        logits = nn.Dense(self.num_actions, name="logits")(h)
        return logits - jnp.mean(logits, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Critics
# ---------------------------------------------------------------------------------------------


def broadcast_features(features: Array, action: Array) -> Array:
    """Insert singleton axes after the batch axes of ``features`` so it broadcasts against ``action``.

    features (..., F) and action (..., k..., A) → features (..., 1..., F) (§4.5 broadcasting).
    """
    extra = action.ndim - features.ndim
    if extra < 0 or features.shape[:-1] != action.shape[: features.ndim - 1]:
        raise ValueError(
            f"action {action.shape} must start with the feature batch axes {features.shape[:-1]} "
            "(extra action axes, e.g. a K axis, may follow them)"
        )
    return features.reshape(features.shape[:-1] + (1,) * extra + features.shape[-1:])


class FeatureActionDense(nn.Module):
    """Dense on ``[F(s), a]`` with the F(s) half computed once per state.

    Same parameters as ``nn.Dense`` on the concatenation (kernel (F + A, width), bias). Splitting the
    matmul means evaluating K actions per state costs K·A·width instead of K·(F + A)·width multiplies
    for the first layer: the feature part is never tiled.
    """

    features: int

    @nn.compact
    def __call__(self, state_features: Array, action: Array) -> Array:
        num_features = state_features.shape[-1]
        dtype = jnp.result_type(state_features, action)
        kernel = self.param(
            "kernel",
            nn.initializers.lecun_normal(),
            (num_features + action.shape[-1], self.features),
            jnp.float32,
        ).astype(dtype)
        bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(dtype)
        per_state = state_features @ kernel[:num_features] + bias
        return broadcast_features(per_state, action) + action @ kernel[num_features:]


class ContinuousQHead(nn.Module):
    """One continuous critic head C(F(s), a): Dense(width) + ReLU per width, then Dense(1)."""

    widths: Sequence[int]

    @nn.compact
    def __call__(self, state_features: Array, action: Array) -> Array:
        h = nn.relu(FeatureActionDense(self.widths[0], name="dense_0")(state_features, action))
        for i, width in enumerate(self.widths[1:], start=1):
            h = nn.relu(nn.Dense(width, name=f"dense_{i}")(h))
        return nn.Dense(1, name="q")(h)[..., 0]


def critic_ensemble(head: type[nn.Module], num_critics: int) -> type[nn.Module]:
    """``num_critics`` independently initialised copies of ``head``, parameters stacked on axis 0,
    all fed the same inputs; outputs get a leading critic axis."""
    return nn.vmap(
        head,
        variable_axes={"params": 0},
        split_rngs={"params": True},
        in_axes=None,
        out_axes=0,
        axis_size=num_critics,
    )


class ContinuousCritic(nn.Module):
    """SAC / XSAC critic ensemble (§2.1, §4.5): one shared extractor F, ``num_critics`` heads.

    ``__call__(obs, action)`` → (num_critics, *action.shape[:-1]). ``action`` may carry extra axes after
    the observation batch axes (e.g. (B, O, C, A) for all mixture components): F(s) is computed once and
    only the head runs per action. ``features`` / ``q_from_features`` expose the two stages.
    """

    extractor: nn.Module
    widths: Sequence[int] = (256, 256)
    num_critics: int = 2

    def setup(self):
        if not self.widths:
            raise ValueError("critic widths must not be empty")
        self.heads = critic_ensemble(ContinuousQHead, self.num_critics)(tuple(self.widths), name="heads")

    def features(self, obs: Observation) -> Array:
        return self.extractor(obs)

    def q_from_features(self, state_features: Array, action: Array) -> Array:
        return self.heads(state_features, action)

    def __call__(self, obs: Observation, action: Array) -> Array:
        return self.q_from_features(self.features(obs), action)


class DiscreteQHead(nn.Module):
    """One discrete critic head: MLP then duelling ``V + Adv - mean_a Adv`` or a plain N-unit layer."""

    widths: Sequence[int]
    num_actions: int
    duelling: bool = True

    @nn.compact
    def __call__(self, state_features: Array) -> Array:
        h = MLP(self.widths, name="mlp")(state_features)
        if not self.duelling:
            return nn.Dense(self.num_actions, name="q")(h)
        advantage = nn.Dense(self.num_actions, name="advantage")(h)
        value = nn.Dense(1, name="value")(h)
        return value + advantage - jnp.mean(advantage, axis=-1, keepdims=True)


class DiscreteCritic(nn.Module):
    """DSAC / XDSAC critic ensemble (§2.2, §4.5): all action values, (num_critics, ..., N)."""

    extractor: nn.Module
    num_actions: int = 12
    widths: Sequence[int] = (256, 256)
    num_critics: int = 2
    duelling: bool = True

    def setup(self):
        ensemble = critic_ensemble(DiscreteQHead, self.num_critics)
        self.heads = ensemble(tuple(self.widths), self.num_actions, self.duelling, name="heads")

    def features(self, obs: Observation) -> Array:
        return self.extractor(obs)

    def q_from_features(self, state_features: Array) -> Array:
        return self.heads(state_features)

    def __call__(self, obs: Observation) -> Array:
        return self.q_from_features(self.features(obs))


# ---------------------------------------------------------------------------------------------
# Configuration and constructors
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ObservationShape:
    """Fixed observation layout of one scenario (§0)."""

    set_key: str
    num_objects: int
    object_features: int
    state_dim: int


ENV_OBSERVATIONS: dict[str, ObservationShape] = {
    "country_road": ObservationShape("cones_set", 100, 5, 6),
    "tracking": ObservationShape("trajectory_set", 25, 4, 6),
    # per agent: 8 other-vehicle slots (present, rel x/y, vel x/y, dir cos/sin) and odometry + route
    "intersection": ObservationShape("vehicles_set", 8, 7, 66),
}
ALGORITHMS = ("sac", "dsac", "xsac", "xdsac")


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Static network sizes for one (env, algo) pair; ``make_network_config`` fills the §4.7 defaults."""

    env: str
    algo: str
    obs_shape: ObservationShape
    actor_width: int
    actor_depth: int
    critic_width: int
    critic_depth: int
    weight_depth: int  # φ_d, 1-based hidden layer feeding the mixture logit (X actors only)
    num_components: int = 1
    uniform_mixture: bool = False  # ablation (§3.1.6), off in every config
    # X actors only: an always-present all-zero object row is prepended (§4.1 / Appendix A), so
    # the mixture has obs_shape.num_objects + 1 objects and object index 0 is the state-only component.
    neutral_object: bool = False
    num_critics: int = 2
    duelling: bool = True
    action_dim: int = 3
    num_actions: int = 12
    extractor: str = "deepset"  # "deepset" (Country Road) or "flat_pe" (tracking)
    fe_width: int = 128
    fe_item_depth: int = 3  # Deep Set item-encoder layers, the Fourier / first Dense layer included
    fe_set_depth: int = 2  # Deep Set set-encoder layers
    fourier_scale: float | None = 30.0
    pe_freqs: int = 4

    @property
    def continuous(self) -> bool:
        return self.algo in ("sac", "xsac")

    @property
    def explainable(self) -> bool:
        return self.algo in ("xsac", "xdsac")

    @property
    def neutral_slot(self) -> bool:
        """Alias of ``neutral_object`` (the actors' argument name)."""
        return self.neutral_object

    @property
    def num_mixture_objects(self) -> int:
        """Objects of the X actors' mixture: O, plus one for the neutral object (1 for the baselines)."""
        if not self.explainable:
            return 1
        return self.obs_shape.num_objects + int(self.neutral_object)


def make_network_config(env: str, algo: str, **overrides: Any) -> NetworkConfig:
    """§4.7 / §5.7 sizes for ``env`` ∈ {country_road, tracking, intersection}, ``algo`` ∈ {sac, dsac,
    xsac, xdsac}; intersection per docs/carenv-intersection.md §8.7 (baseline actors 2 × 256: not specified).

    Any field of NetworkConfig can be overridden (e.g. tiny widths for tests).
    """
    if env not in ENV_OBSERVATIONS:
        raise ValueError(f"unknown env {env!r}; expected one of {sorted(ENV_OBSERVATIONS)}")
    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algo {algo!r}; expected one of {ALGORITHMS}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(NetworkConfig)}
    if unknown:
        raise ValueError(f"unknown NetworkConfig fields {sorted(unknown)}")
    deep_set = env in ("country_road", "intersection")  # else tracking
    explainable = algo in ("xsac", "xdsac")
    actor_depth = overrides.pop("actor_depth", 3 if (explainable or env == "tracking") else 2)
    defaults = dict(
        env=env,
        algo=algo,
        obs_shape=ENV_OBSERVATIONS[env],
        actor_width=256,
        actor_depth=actor_depth,
        critic_width=256,
        critic_depth=2 if deep_set else 3,
        weight_depth=actor_depth,
        extractor="deepset" if deep_set else "flat_pe",
    )
    if env == "intersection":
        defaults.update(fe_width=256, fourier_scale=None, neutral_object=explainable)
    defaults.update(overrides)
    config = NetworkConfig(**defaults)
    validate_network_config(config)
    return config


def validate_network_config(config: NetworkConfig) -> None:
    """Raise a clear error for inconsistent sizes / switches (called by the constructors)."""
    _resolve_weight_depth(config.weight_depth, config.actor_depth)
    if config.algo not in ALGORITHMS:
        raise ValueError(f"unknown algo {config.algo!r}; expected one of {ALGORITHMS}")
    if config.algo == "xdsac" and not config.duelling:
        raise ValueError("XDSAC always uses a duelling critic (docs/algorithms.md §2.4)")
    if config.extractor not in ("deepset", "flat_pe"):
        raise ValueError(f"unknown extractor {config.extractor!r}; expected 'deepset' or 'flat_pe'")
    if config.fe_item_depth < 1 or config.fe_set_depth < 0:
        raise ValueError(
            f"fe_item_depth must be >= 1 and fe_set_depth >= 0, got {config.fe_item_depth}, "
            f"{config.fe_set_depth}"
        )
    if config.neutral_object and not config.explainable:
        raise ValueError(
            f"neutral_object only applies to the mixture actors (xsac, xdsac), not {config.algo}"
        )


def make_extractor(config: NetworkConfig) -> nn.Module:
    if config.extractor == "deepset":
        return DeepSetExtractor(
            width=config.fe_width,
            item_depth=config.fe_item_depth,
            set_depth=config.fe_set_depth,
            fourier_scale=config.fourier_scale,
            state_width=config.fe_width,
        )
    return FlatPEExtractor(num_freqs=config.pe_freqs)


@dataclasses.dataclass(frozen=True)
class Networks:
    """The actor and critic modules of one agent plus helpers to initialise them on dummy inputs."""

    config: NetworkConfig
    actor: nn.Module
    critic: nn.Module

    def dummy_observation(self, batch_shape: tuple[int, ...] = ()) -> dict[str, Array]:
        return dummy_observation(self.config.obs_shape, batch_shape)

    def dummy_action(self, batch_shape: tuple[int, ...] = ()) -> Array:
        if self.config.continuous:
            return jnp.zeros((*batch_shape, self.config.action_dim), _float_dtype())
        return jnp.zeros(batch_shape, jnp.int32)

    def init_actor(self, key: Array) -> Any:
        return self.actor.init(key, self.dummy_observation())

    def init_critic(self, key: Array) -> Any:
        if self.config.continuous:
            return self.critic.init(key, self.dummy_observation(), self.dummy_action())
        return self.critic.init(key, self.dummy_observation())


def make_networks(config: NetworkConfig) -> Networks:
    """Build the actor and critic of §4.6 (each with its own extractor where it has one)."""
    c = config
    validate_network_config(c)
    critic_widths = (c.critic_width,) * c.critic_depth
    actor_widths = (c.actor_width,) * c.actor_depth
    set_key = c.obs_shape.set_key
    if c.algo == "sac":
        actor = GaussianActor(make_extractor(c), c.action_dim, actor_widths)
    elif c.algo == "dsac":
        actor = CategoricalActor(make_extractor(c), c.num_actions, actor_widths)
    elif c.algo == "xsac":
        actor = MixtureGaussianActor(
            c.action_dim,
            c.actor_width,
            c.actor_depth,
            c.weight_depth,
            c.num_components,
            set_key=set_key,
            neutral_slot=c.neutral_object,
            uniform_mixture=c.uniform_mixture,
        )
    else:
        actor = MixtureCategoricalActor(
            c.num_actions,
            c.actor_width,
            c.actor_depth,
            c.weight_depth,
            set_key=set_key,
            neutral_slot=c.neutral_object,
            uniform_mixture=c.uniform_mixture,
        )
    if c.continuous:
        critic = ContinuousCritic(make_extractor(c), critic_widths, c.num_critics)
    else:
        critic = DiscreteCritic(make_extractor(c), c.num_actions, critic_widths, c.num_critics, c.duelling)
    return Networks(c, actor, critic)


def dummy_observation(shape: ObservationShape, batch_shape: tuple[int, ...] = ()) -> dict[str, Array]:
    """Zero observation (no object present) with the env's fixed shapes, for initialisation."""
    dtype = _float_dtype()
    return {
        STATE_KEY: jnp.zeros((*batch_shape, shape.state_dim), dtype),
        shape.set_key: jnp.zeros((*batch_shape, shape.num_objects, shape.object_features), dtype),
    }


def count_params(params: Any) -> int:
    """Number of scalar parameters in a pytree (works on arrays and on ``jax.eval_shape`` results)."""
    return int(sum(math.prod(leaf.shape) for leaf in jax.tree_util.tree_leaves(params)))


def dense_flops(fan_in: int, fan_out: int) -> int:
    """FLOPs of one dense layer on one input row: a multiply and an add per weight plus the bias add."""
    return 2 * fan_in * fan_out + fan_out


def mixture_actor_sample_flops(
    num_objects: int, input_dim: int, width: int, depth: int, weight_depth: int, head_outputs: int, fast: bool
) -> int:
    """Analytic dense-layer FLOPs of drawing one action from a myopic mixture actor (ReLU etc. ignored).

    Full path: every layer and head for all O objects. Fast path (§3.7): layers 1..φ_d and φ for
    all O objects, layers φ_d+1..depth and the heads (``head_outputs`` units) for one object only.

    Country Road XSAC (O = 100, 11 inputs, 256×3, heads 6): fast path 0.91 M / 13.9 M / 26.9 M FLOPs
    for φ_d = 1 / 2 / 3 against 27.2 M for the full path. XLA's cost analysis of the jitted
    ``sample_fast`` (CPU) gives 0.991 M / 14.02 M / 27.04 M, within 0.3 % of paper Table I
    (0.988 M / 14.02 M / 27.04 M); the SAC baseline actor forward pass gives 7.09 M (paper 7.10 M).
    """
    fans = [input_dim] + [width] * depth
    layer = [dense_flops(fans[i], fans[i + 1]) for i in range(depth)]
    shared = sum(layer[:weight_depth]) + dense_flops(width, 1)
    rest = sum(layer[weight_depth:]) + dense_flops(width, head_outputs)
    return num_objects * shared + (1 if fast else num_objects) * rest


__all__ = [
    "ALGORITHMS",
    "BASELINE_LOG_STD_RANGE",
    "ENV_OBSERVATIONS",
    "MASKED_LOGIT",
    "MIXTURE_LOG_STD_RANGE",
    "MLP",
    "CategoricalActor",
    "CategoricalMixtureOutput",
    "ContinuousCritic",
    "ContinuousQHead",
    "DeepSet",
    "DeepSetExtractor",
    "DiscreteCritic",
    "DiscreteQHead",
    "FastSample",
    "FeatureActionDense",
    "FlatPEExtractor",
    "FourierFeatures",
    "GaussianActor",
    "GaussianMixtureOutput",
    "GaussianOutput",
    "MixtureCategoricalActor",
    "MixtureGaussianActor",
    "NetworkConfig",
    "Networks",
    "ObservationShape",
    "broadcast_features",
    "centre_and_mask_logits",
    "count_params",
    "dense_flops",
    "dummy_observation",
    "find_set_key",
    "make_extractor",
    "make_network_config",
    "make_networks",
    "masked_mixture_weights",
    "mixture_actor_sample_flops",
    "object_inputs",
    "positional_encoding",
    "present_mask",
    "tracking_index_feature",
    "trajectory_to_set",
    "validate_network_config",
]
