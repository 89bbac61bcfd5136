"""Observation helpers, layers and the feature extractors of the networks (docs/algorithms.md §4).

Conventions shared by every network module (``extractors``, ``actors``, ``critics``):

* Observations are dicts ``{"state": (..., S), "<name>_set": (..., O, F_obj)}``; column 0 of the set is
  the present flag. Every module accepts arbitrary leading batch axes ``...`` (also none).
* Absent object rows are masked with ``where`` (never boolean indexing), so shapes never depend on
  data and absent rows may hold any finite values without changing any output. Per-object layers
  given a :class:`~xrl_jax.sets.Packing` run on the present rows only, with the same result.
* Ensembles of critics are stacked on a new **leading** axis: ``(n_critics, ...)``.
* All layers use Flax defaults (LeCun-normal kernels, zero biases) except the Fourier layer (§4.4).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from xrl_jax import sets
from xrl_jax.trig import cos_pi, sin_pi

Array = jax.Array
Observation = Mapping[str, Array]

STATE_KEY = "state"


def float_dtype():
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


def split_observation(obs: Observation, set_key: str | None) -> tuple[str, Array, Array]:
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


def object_rows(
    obs: Observation, set_key: str | None = None, neutral_object: bool = False, neutral_flag: bool = False
) -> tuple[Array, Array, Array]:
    """The X actors' objects, state and present mask (§4.1), before the state is joined to each object.

    ``neutral_object`` prepends a neutral object (multi-agent only), whose component therefore sees
    only the state. As in the original its row is all zero, present column included, while the mask
    counts it as present (docs/algorithms.md §4.1); ``neutral_flag`` writes 1 into that column instead.

    Returns ``(objects (..., O[+1], F_obj), state (..., S), present (..., O[+1]) bool)``.
    """
    _, objects, state = split_observation(obs, set_key)
    dtype = jnp.result_type(objects, state)
    objects, state = objects.astype(dtype), state.astype(dtype)
    present = present_mask(objects)
    if neutral_object:
        neutral = jnp.zeros((*objects.shape[:-2], 1, objects.shape[-1]), dtype)
        objects = jnp.concatenate([neutral.at[..., 0].set(float(neutral_flag)), objects], axis=-2)
        present = jnp.concatenate([jnp.ones((*present.shape[:-1], 1), bool), present], axis=-1)
    return objects, state, present


def object_inputs(
    obs: Observation, set_key: str | None = None, neutral_object: bool = False, neutral_flag: bool = False
) -> tuple[Array, Array]:
    """The X-actor observation reshaper (§4.1): per-object rows ``[x_o, z]`` and the present mask.

    The object row keeps its present flag (and, for tracking, the index column); the state ``z`` is
    broadcast to every slot; the neutral object as in :func:`object_rows`. The actors never build
    this array (their first layer splits into an object part and a state part computed once per
    observation); it states what their input is.

    Returns ``(inputs (..., O[+1], F_obj + S), present (..., O[+1]) bool)``.
    """
    objects, state, present = object_rows(obs, set_key, neutral_object, neutral_flag)
    tiled_state = jnp.broadcast_to(state[..., None, :], objects.shape[:-1] + state.shape[-1:])
    return jnp.concatenate([objects, tiled_state], axis=-1), present


def tracking_index_feature(length: int) -> Array:
    """Index column of the tracking set: ``2 i / L - 1`` for ``i = 0..L-1`` (§4.2, §7.2.10).

    **Quirk kept for parity:** divides by L, not L - 1, so it spans [-1, 1 - 2/L] (-1 ... 0.92 for L = 25).
    """
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}")
    return 2.0 * jnp.arange(length, dtype=float_dtype()) / length - 1.0


def positional_encoding(values: Array, num_freqs: int = 4, include_input: bool = True) -> Array:
    """Fourier positional encoding of a vector (§4.4), frequency-major layout.

    ``[cos(π 2^k v)]_k ⊕ [sin(π 2^k v)]_k ⊕ v`` as a (2F[+1], D) array flattened row by row,
    giving (2F + 1)·D features (9·D for the default F = 4).
    """
    values = jnp.asarray(values)
    scales = 2.0 ** jnp.arange(num_freqs, dtype=values.dtype)
    half_turns = scales[:, None] * values[..., None, :]  # (..., F, D), angles in units of π
    rows = [cos_pi(half_turns), sin_pi(half_turns)]
    if include_input:
        rows.append(values[..., None, :])
    stacked = jnp.concatenate(rows, axis=-2)
    return stacked.reshape((*values.shape[:-1], -1))


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
        return sin_pi(projected)


class ObjectStateDense(nn.Module):
    """Dense layer on ``[x_o, z]`` (an object row joined to its observation's state).

    Same parameters as ``nn.Dense`` on the joined row (kernel (F_obj + S, width), bias). For every slot
    (``objects`` (..., O, F_obj)) the state half ``z·W_z + b`` is computed once per observation and
    added to every slot's ``x_o·W_x``, so the joined rows are never built; for packed rows
    (``objects`` (P, F_obj) with their ``plan``, :mod:`xrl_jax.sets`) each row is joined to its own
    observation's state, a narrower copy than the state half would be.
    """

    features: int

    @nn.compact
    def __call__(self, objects: Array, state: Array, plan: sets.PresentRows | None = None) -> Array:
        num_object_features = objects.shape[-1]
        dtype = jnp.result_type(objects, state)
        kernel = self.param(
            "kernel",
            nn.initializers.lecun_normal(),
            (num_object_features + state.shape[-1], self.features),
            jnp.float32,
        ).astype(dtype)
        bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(dtype)
        if plan is not None:
            rows = jnp.concatenate([objects, sets.broadcast_to_rows(state, plan)], axis=-1)
            return rows @ kernel + bias
        per_state = state @ kernel[num_object_features:] + bias
        return objects @ kernel[:num_object_features] + per_state[..., None, :]


def _deep_set_items(mdl: DeepSet, items: Array) -> Array:
    """The item encoder (its layers named ``item_i`` in ``mdl``'s scope), on rows (..., F_obj - 1)."""
    if mdl.fourier_scale is None:
        h = nn.relu(nn.Dense(mdl.width, name="item_0")(items))
    else:
        h = FourierFeatures(mdl.width, mdl.fourier_scale, name="item_0")(items)
    for i in range(1, mdl.item_depth):
        h = nn.relu(nn.Dense(mdl.width, name=f"item_{i}")(h))
    return h


def _deep_set_sum_dense(mdl: DeepSet, items: Array, present: Array) -> Array:
    h = _deep_set_items(mdl, items)
    return jnp.sum(jnp.where(present[..., None], h, 0.0), axis=-2)


def _deep_set_sum_packed(mdl: DeepSet, plan: sets.PresentRows, items: Array, present: Array) -> Array:
    return sets.sum_rows(_deep_set_items(mdl, sets.pack(items, plan)), plan)


class DeepSet(nn.Module):
    """Deep Set with learned Fourier features (LFF-DS, §4.4) on a padded set (..., O, F_obj).

    The present column (0) is dropped from the items; only present items enter the sum, so the output
    is invariant to slot order and to the contents of absent rows. ``fourier_scale=None`` replaces the
    Fourier layer by Dense + ReLU (``set_ffn: false``). With ``packing`` the item encoder runs on the
    present rows only (:mod:`xrl_jax.sets`); the result is the same.
    """

    width: int = 128
    item_depth: int = 3
    set_depth: int = 2
    fourier_scale: float | None = 30.0
    packing: sets.Packing | None = None

    @nn.compact
    def __call__(self, objects: Array) -> Array:
        if self.item_depth < 1:
            raise ValueError(f"item_depth must be >= 1, got {self.item_depth}")
        present = present_mask(objects)
        plan = sets.plan_for(present, self.packing)
        pooled = sets.packed_or_dense(
            self, plan, _deep_set_sum_packed, _deep_set_sum_dense, objects[..., 1:], present
        )
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
    packing: sets.Packing | None = None

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        set_key, objects, state = split_observation(obs, None)
        parts = {
            set_key: DeepSet(
                self.width, self.item_depth, self.set_depth, self.fourier_scale, self.packing, name="deep_set"
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
        set_key, objects, state = split_observation(obs, None)
        points = objects[..., self.meta_columns :]
        flat = points.reshape((*points.shape[:-2], -1))
        parts = {
            set_key: positional_encoding(flat, self.num_freqs, self.include_input),
            STATE_KEY: positional_encoding(state, self.num_freqs, self.include_input),
        }
        return jnp.concatenate([parts[k] for k in sorted(parts)], axis=-1)


__all__ = [
    "MLP",
    "STATE_KEY",
    "DeepSet",
    "DeepSetExtractor",
    "FlatPEExtractor",
    "FourierFeatures",
    "ObjectStateDense",
    "find_set_key",
    "object_inputs",
    "object_rows",
    "positional_encoding",
    "present_mask",
    "split_observation",
    "tracking_index_feature",
]
