"""Glyph contents: what one object's (or the whole policy's) action distribution looks like.

Discrete actions become the paper's 4 × 3 matrix of probabilities; continuous ones an exact
probability-mass image over steering × longitudinal control (throttle − brake), so a glyph shows
the distribution itself rather than a sample of it. How to read them: :mod:`xrl_jax.explain.figures`.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from scipy.special import ndtr

STEER_BINS = 21
PEDAL_LEVELS = 11  # pedal positions 0, 0.1, ..., 1; longitudinal l = throttle - brake on 21 levels
LONGITUDINAL_LEVELS = 2 * PEDAL_LEVELS - 1
PEDAL_SCALE, PEDAL_OFFSET = 1.8, 0.5  # envs.actions pedal map: position = clip(raw / 1.8 + 0.5, 0, 1)

# Discrete layout (docs/algorithms.md §6.3): action index 4*i_steer + j, j = 2*i_throttle + i_brake.
DISCRETE_ROW_J = (2, 0, 3, 1)  # top to bottom: throttle only, coast, both pedals, brake only


def steer_column_order(mirrored: bool = False) -> tuple[int, ...]:
    """Steering indices (0: −1 right, 1: 0, 2: +1 left) of the glyph columns, left to right.

    The left column steers towards the screen's left: +1 in the physically correct view, −1 in
    the mirrored one (the paper's pictures).
    """
    return (0, 1, 2) if mirrored else (2, 1, 0)


def discrete_matrix(probs, mirrored: bool = False) -> np.ndarray:
    """Probabilities (..., 12) -> the paper's matrix (..., 4, 3): rows of DISCRETE_ROW_J, steering columns."""
    probs = np.asarray(probs, np.float64)
    if probs.shape[-1:] != (12,):
        raise ValueError(f"discrete probabilities must have shape (..., 12), got {probs.shape}")
    index = np.array([[4 * s + j for s in steer_column_order(mirrored)] for j in DISCRETE_ROW_J])
    return probs[..., index]


def _squashed_cdf(edges_raw, loc, scale):
    """P(tanh(u) <= e) for u ~ N(loc, scale) at raw action edges e (..., n) for components (...)."""
    edges = np.clip(edges_raw, -1.0, 1.0)
    with np.errstate(divide="ignore"):
        pre = np.arctanh(edges)
    return ndtr((pre - loc[..., None]) / scale[..., None])


def _bin_masses(cdf_at_inner_edges):
    """Masses of the bins delimited by ``-inf, inner edges..., +inf`` from the CDF at the inner edges."""
    shape = cdf_at_inner_edges.shape[:-1]
    cdf = np.concatenate([np.zeros((*shape, 1)), cdf_at_inner_edges, np.ones((*shape, 1))], axis=-1)
    return np.clip(np.diff(cdf, axis=-1), 0.0, None)


def steering_masses(loc, scale, bins: int = STEER_BINS) -> np.ndarray:
    """Mass of the squashed steering action in ``bins`` equal bins of [−1, 1] (..., bins), exact."""
    inner = np.linspace(-1.0, 1.0, bins + 1)[1:-1]
    return _bin_masses(_squashed_cdf(inner, np.asarray(loc), np.asarray(scale)))


def pedal_masses(loc, scale) -> np.ndarray:
    """Mass of the pedal *position* at 0, 0.1, ..., 1 (..., 11): each level takes ±0.05 around it.

    Position = clip(raw / 1.8 + 0.5, 0, 1), so the released pedal (level 0) also collects every raw
    value below −0.9, full pedal every value above 0.9.
    """
    levels = np.linspace(0.0, 1.0, PEDAL_LEVELS)
    inner_positions = (levels[:-1] + levels[1:]) / 2
    inner_raw = PEDAL_SCALE * (inner_positions - PEDAL_OFFSET)
    return _bin_masses(_squashed_cdf(inner_raw, np.asarray(loc), np.asarray(scale)))


def _difference_matrix() -> np.ndarray:
    """(11·11, 21) 0/1 map from (throttle level i, brake level k) to the level of i − k (top row: +1)."""
    i, k = np.meshgrid(np.arange(PEDAL_LEVELS), np.arange(PEDAL_LEVELS), indexing="ij")
    level = (PEDAL_LEVELS - 1) - (i - k)  # row 0 = l = +1 (full throttle, released brake)
    out = np.zeros((PEDAL_LEVELS * PEDAL_LEVELS, LONGITUDINAL_LEVELS))
    out[np.arange(PEDAL_LEVELS * PEDAL_LEVELS), level.reshape(-1)] = 1.0
    return out


_DIFFERENCE = _difference_matrix()


def component_density_images(loc, log_scale, mirrored: bool = False, bins: int = STEER_BINS) -> np.ndarray:
    """Per-component probability mass over (longitudinal, steering): (..., K, 21, bins), each sums to 1.

    ``loc`` and ``log_scale`` (..., K, 3) are the pre-squash parameters of diagonal squashed
    Gaussians over (steer, throttle pedal, brake pedal).
    """
    loc = np.asarray(loc, np.float64)
    scale = np.exp(np.asarray(log_scale, np.float64))
    if loc.shape[-1:] != (3,) or loc.shape != scale.shape:
        raise ValueError(f"loc and log_scale must share a shape (..., K, 3), got {loc.shape}, {scale.shape}")
    steer = steering_masses(loc[..., 0], scale[..., 0], bins)
    if not mirrored:  # left column = steer +1 (left)
        steer = steer[..., ::-1]
    throttle = pedal_masses(loc[..., 1], scale[..., 1])
    brake = pedal_masses(loc[..., 2], scale[..., 2])
    joint = (throttle[..., :, None] * brake[..., None, :]).reshape(*throttle.shape[:-1], -1)
    longitudinal = joint @ _DIFFERENCE
    return longitudinal[..., :, None] * steer[..., None, :]


def mixture_image(images, weights) -> np.ndarray:
    """Σ_k w_k image_k over the component axis: images (..., K, L, S), weights (..., K)."""
    return np.einsum("...k,...kls->...ls", np.asarray(weights, np.float64), np.asarray(images))


@dataclasses.dataclass(frozen=True)
class StepExplanation:
    """The explanation of one step as numpy: what each object would draw and the combined policy.

    * ``weights``, ``present``: (O,) object weights (sum 1 over present objects) and the mask.
    * ``object_values``: (O, 4, 3) discrete matrices or (O, 21, 21) continuous mass images.
    * ``combined``: the policy's own matrix / image, equal to Σ_o w_o object_values[o].
    * ``is_mixture``: False for baselines (one pseudo-object: the whole observation).
    """

    kind: str  # "discrete" or "continuous"
    weights: np.ndarray
    present: np.ndarray
    object_values: np.ndarray
    combined: np.ndarray
    is_mixture: bool


def step_explanation(explanation, mirrored: bool = False) -> StepExplanation:
    """Numpy glyph contents of one unbatched :class:`xrl_jax.explain.Explanation`."""
    explanation = jax.device_get(explanation)
    policy = explanation.policy
    weights = np.asarray(explanation.weights, np.float64)
    present = np.asarray(explanation.present, bool)
    num_objects = weights.shape[-1]
    if weights.ndim != 1:
        raise ValueError(f"step_explanation needs one step (weights (O,)), got weights {weights.shape}")
    if hasattr(policy, "component_logits"):
        probs = np.asarray(jax.nn.softmax(np.asarray(policy.component_logits, np.float64), axis=-1))
        values = discrete_matrix(probs, mirrored)
        combined = np.einsum("o,orc->rc", weights, values)
        return StepExplanation("discrete", weights, present, values, combined, explanation.is_mixture)
    images = component_density_images(policy.loc, policy.log_scale, mirrored)  # (K, L, S)
    component_weights = np.exp(np.asarray(policy.log_weights, np.float64))
    per_object = images.shape[0] // num_objects
    grouped = images.reshape(num_objects, per_object, *images.shape[1:])
    within = component_weights.reshape(num_objects, per_object)
    totals = within.sum(-1, keepdims=True)
    within = np.where(totals > 0, within / np.where(totals > 0, totals, 1.0), 1.0 / per_object)
    values = mixture_image(grouped, within)
    combined = mixture_image(images, component_weights)
    return StepExplanation("continuous", weights, present, values, combined, explanation.is_mixture)
