"""Explanation figures over the bird view (the paper's Fig. 1, 3, 4), PNG / GIF / MP4, and attributions.

Host side only (numpy + matplotlib); the episode itself is rolled out on the device by
:func:`xrl_jax.explain.make_episode_rollout`. How to read a figure:

* Every observed object whose mixture weight w_o is at least ``threshold`` (default 0.05) gets a
  *glyph* next to it, joined to the object by a thin black line. The glyph's **area is
  proportional to w_o** (side = ``max_side`` · √w_o, so w_o = 1 fills the full ``max_side`` box),
  which keeps sizes comparable across frames. Lighter objects are left unmarked.
* Discrete actions (DSAC / XDSAC): the paper's 3 × 4 matrix of the object's 12 probabilities q_o(a).
  Columns are the steering command, ordered so that the left column steers towards the left of
  the screen (steer +1 on the left in the default view; −1, 0, +1 in the ``mirrored`` view, as in
  the paper). Rows from top: throttle only (green), coast (white), throttle and brake (orange),
  brake only (red); the cell colour is the row colour times q / (max q over the frame's glyphs),
  so black means no probability.
* Continuous actions (SAC / XSAC): an image of the probability mass of the object's distribution
  over steering (x, same left/right rule as above, 21 bins) × longitudinal control
  l = throttle position − brake position (y, +1 = full throttle at the top, −1 = full brake at the
  bottom, 21 values), after the pedal map of ``envs.actions`` (raw pedals below −0.9 are released).
  Colours: ``inferno``, normalised per glyph (black = no mass). The mass per cell is exact for
  steering (CDF differences of the squashed Gaussian) and for each pedal; l's distribution is
  the discrete convolution of the two pedal distributions on a 0.1 grid.
* The inset at the top left shows the combined policy π(·|s) = Σ_o w_o π_o, which is exactly the
  weighted sum of the glyphs' distributions. Baselines (SAC / DSAC) have no objects: they show only
  the inset.

Scenario adapters (:class:`Scene`) say where the observed objects are: rows of the observation's
object set hold ego-frame positions times a sensor normaliser, mapped to the world with the ego
pose. Multi-agent actors with a neutral (state-only) component put it at the ego vehicle.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from matplotlib import colormaps
from matplotlib.patches import Rectangle
from scipy.special import ndtr

STEER_BINS = 21
PEDAL_LEVELS = 11  # pedal positions 0, 0.1, ..., 1; longitudinal l = throttle - brake on 21 levels
LONGITUDINAL_LEVELS = 2 * PEDAL_LEVELS - 1
DEFAULT_THRESHOLD = 0.05
DEFAULT_MAX_SIDE = 7.0  # metres of view: a weight-1 glyph is ~90 px wide in a 720 px tall frame
DEFAULT_OFFSET = 2.5  # metres between an object and the near edge of its glyph
PEDAL_SCALE, PEDAL_OFFSET = 1.8, 0.5  # envs.actions pedal map: position = clip(raw / 1.8 + 0.5, 0, 1)

# Discrete layout (docs/algorithms.md §6.3): action index 4*i_steer + j, j = 2*i_throttle + i_brake.
DISCRETE_ROW_J = (2, 0, 3, 1)  # top to bottom: throttle only, coast, both pedals, brake only
DISCRETE_ROW_COLOURS = np.array([(0, 1, 0), (1, 1, 1), (1, 0.6, 0), (1, 0, 0)], np.float64)
DISCRETE_ROW_NAMES = ("throttle", "coast", "both", "brake")
CONTINUOUS_CMAP = "inferno"

GLYPH_Z, LINE_Z, INSET_Z = 13, 12, 25


# ------------------------------------------------------------------------------------------------
# Glyph contents
# ------------------------------------------------------------------------------------------------


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


# ------------------------------------------------------------------------------------------------
# One step's explanation on the host
# ------------------------------------------------------------------------------------------------


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


# ------------------------------------------------------------------------------------------------
# Where the objects are (scenario adapters)
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ObjectSet:
    """The explanation's objects of one step, aligned with its weights (O,)."""

    world_xy: np.ndarray  # (O, 2); NaN for objects without a place (a baseline's whole observation)
    present: np.ndarray  # (O,) bool
    labels: tuple[dict, ...]  # per object, e.g. {"type": "cone", "colour": "blue"}
    side: np.ndarray  # (O,) where the glyph goes: +1 the ego's left, -1 its right, 0 up-right on screen
    ego_theta: float = 0.0  # the ego heading, which turns ``side`` into a direction


@dataclasses.dataclass(frozen=True)
class Scene:
    """What figures need to know about one scenario's observations.

    ``scale(env, params)`` is the sensor normaliser: ego-frame metres = row[x_col, y_col] · scale.
    ``label(row_index, row)`` names an object for the attribution export. ``offset_rule`` puts
    the glyphs beside the objects: "colour" (cones: yellow/left-boundary cones to the ego's left,
    blue ones to its right, i.e. off the road), "alternate" (sequence points: even indices left,
    odd right), "fixed" (up and to the right on the screen).
    """

    set_key: str
    x_col: int
    y_col: int
    scale: Callable[[Any, Any], float]
    label: Callable[[int, np.ndarray], dict]
    offset_rule: str


def _cone_label(index: int, row: np.ndarray) -> dict:
    return {"type": "cone", "colour": "blue" if row[3] > 0.5 else "yellow" if row[4] > 0.5 else "unknown"}


def _trajectory_label(index: int, row: np.ndarray) -> dict:
    return {"type": "trajectory_point", "trajectory_index": index}


def _vehicle_label(index: int, row: np.ndarray) -> dict:
    return {"type": "vehicle", "row": index}


SCENES: dict[str, Scene] = {
    "country_road": Scene("cones_set", 1, 2, lambda env, p: float(p.cone_normaliser), _cone_label, "colour"),
    "tracking": Scene(
        "trajectory_set",
        2,
        3,
        lambda env, p: math.sqrt(2.0) * float(p.lookahead_spacing) * int(env.lookahead_points),
        _trajectory_label,
        "alternate",
    ),
    # Multi-agent (docs/carenv-intersection.md §7.1): rows (present, x/30, y/30, ...) of the other
    # vehicles; the base frame comes from envs.render.render_intersection_state (see render_base).
    "intersection": Scene("vehicles_set", 1, 2, lambda env, p: 30.0, _vehicle_label, "fixed"),
}


def scene_for(env_name: str) -> Scene:
    base = env_name.removesuffix("_discrete")
    if base not in SCENES:
        raise ValueError(f"no explanation figures for env {env_name!r}; known: {', '.join(SCENES)}")
    return SCENES[base]


def ego_to_world(points, pose) -> np.ndarray:
    """Ego-frame points (..., 2) (x forward, y left) to the world with pose (x, y, θ)."""
    points = np.asarray(points, np.float64)
    x, y, theta = (float(v) for v in pose)
    c, s = math.cos(theta), math.sin(theta)
    return np.stack(
        [x + c * points[..., 0] - s * points[..., 1], y + s * points[..., 0] + c * points[..., 1]], -1
    )


def scene_objects(
    scene: Scene, obs, pose, env, params, neutral: bool = False, is_mixture: bool = True
) -> ObjectSet:
    """World positions and labels of one step's observed objects (plus the neutral one at the ego).

    ``obs`` is one unbatched observation (numpy); ``pose`` = (x, y, θ) of the ego vehicle.
    Baselines get one pseudo-object without a position.
    """
    if not is_mixture:
        return ObjectSet(
            np.full((1, 2), np.nan), np.ones(1, bool), ({"type": "whole_observation"},), np.zeros(1)
        )
    rows = np.asarray(obs[scene.set_key], np.float64)
    present = rows[:, 0] > 0
    ego_xy = rows[:, [scene.x_col, scene.y_col]] * scene.scale(env, params)
    world = ego_to_world(ego_xy, pose)
    labels = tuple(scene.label(i, row) for i, row in enumerate(rows))
    if scene.offset_rule == "colour":
        side = np.array([1.0 if label.get("colour") == "yellow" else -1.0 for label in labels])
    elif scene.offset_rule == "alternate":
        side = np.where(np.arange(len(rows)) % 2 == 0, 1.0, -1.0)
    else:
        side = np.zeros(len(rows))
    if neutral:
        world = np.concatenate([np.asarray(pose, np.float64)[None, :2], world])
        present = np.concatenate([[True], present])
        labels = ({"type": "neutral"}, *labels)
        side = np.concatenate([[0.0], side])
    return ObjectSet(world, present, labels, side, float(pose[2]))


# ------------------------------------------------------------------------------------------------
# Drawing (through envs.render.render_frame's overlay callback, in view metres)
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Glyph:
    """One drawn explanation box (view metres), returned by :func:`draw_explanation` for inspection."""

    index: int  # explanation slot; -1 for the inset (the combined policy)
    weight: float
    anchor: np.ndarray  # the object's view position (the inset: the glyph centre)
    centre: np.ndarray
    width: float
    height: float
    values: np.ndarray  # the matrix (4, 3) of probabilities or the (21, 21) mass image
    kind: str


def _glyph_shape(kind: str, side: float) -> tuple[float, float]:
    return (side, side * 4 / 3) if kind == "discrete" else (side, side)


def _draw_values(
    ax, kind: str, values: np.ndarray, centre, width: float, height: float, norm: float, z: float
):
    left, bottom = centre[0] - width / 2, centre[1] - height / 2
    if kind == "discrete":
        cell_w, cell_h = width / 3, height / 4
        shade = np.clip(values / max(norm, 1e-12), 0.0, 1.0)
        for r in range(4):
            for c in range(3):
                colour = tuple(DISCRETE_ROW_COLOURS[r] * shade[r, c])
                ax.add_patch(
                    Rectangle(
                        (left + c * cell_w, bottom + (3 - r) * cell_h),
                        cell_w,
                        cell_h,
                        facecolor=colour,
                        edgecolor="black",
                        lw=0.5,
                        zorder=z,
                    )
                )
    else:
        ax.imshow(
            values / max(norm, 1e-300),
            cmap=colormaps[CONTINUOUS_CMAP],
            vmin=0.0,
            vmax=1.0,
            extent=(left, left + width, bottom, bottom + height),
            origin="upper",
            interpolation="nearest",
            aspect="auto",
            zorder=z,
        )
    ax.add_patch(
        Rectangle((left, bottom), width, height, facecolor="none", edgecolor="black", lw=1.0, zorder=z)
    )


def draw_explanation(
    ax,
    to_view: Callable[[np.ndarray], np.ndarray],
    step: StepExplanation,
    objects: ObjectSet,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    max_side: float = DEFAULT_MAX_SIDE,
    offset: float = DEFAULT_OFFSET,
    inset: bool = True,
    title: str = "",
) -> list[Glyph]:
    """Draw the object glyphs and the combined-policy inset on ``ax``; return what was drawn.

    Objects with weight < ``threshold`` (and absent ones) are left unmarked; a glyph's side is
    ``max_side`` · √w (area ∝ weight). Baselines (``step.is_mixture`` False) get only the inset.
    """
    if len(objects.present) != len(step.weights):
        raise ValueError(f"{len(objects.present)} objects for {len(step.weights)} explanation weights")
    drawn: list[Glyph] = []
    show = step.is_mixture & step.present & objects.present & (step.weights >= threshold)
    norm_discrete = float(step.object_values[show].max()) if step.kind == "discrete" and show.any() else 1.0
    anchors = to_view(np.nan_to_num(objects.world_xy)) if show.any() else np.zeros((len(show), 2))
    order = np.flatnonzero(show)
    for index in order[np.argsort(-step.weights[order], kind="stable")]:  # lighter glyphs on top
        weight = float(step.weights[index])
        width, height = _glyph_shape(step.kind, max_side * math.sqrt(weight))
        anchor = anchors[index]
        side = float(objects.side[index])
        if side == 0.0:
            direction = np.array([1.0, 1.0]) / math.sqrt(2.0)
        else:  # the ego's left (side +1) or right in view coordinates (also right in a mirrored view)
            world = objects.world_xy[index]
            left = side * np.array([-math.sin(objects.ego_theta), math.cos(objects.ego_theta)])
            direction = to_view(world + left) - to_view(world)
            direction = direction / max(float(np.linalg.norm(direction)), 1e-12)
        reach = offset + 0.5 * np.array([width, height])
        centre = anchor + direction * reach * (np.abs(direction) > 0)
        ax.plot([anchor[0], centre[0]], [anchor[1], centre[1]], color="black", lw=0.8, zorder=LINE_Z)
        values = step.object_values[index]
        norm = norm_discrete if step.kind == "discrete" else float(values.max())
        _draw_values(ax, step.kind, values, centre, width, height, norm, GLYPH_Z)
        drawn.append(Glyph(int(index), weight, anchor, centre, width, height, values, step.kind))
    if inset:
        drawn.append(_draw_inset(ax, step, max_side, title))
    return drawn


def _draw_inset(ax, step: StepExplanation, max_side: float, title: str) -> Glyph:
    """White box at the top left with the combined policy's glyph (full size) and its legend."""
    x_min, (y_min, y_max) = ax.get_xlim()[0], ax.get_ylim()
    margin = 0.02 * (y_max - y_min)
    width, height = _glyph_shape(step.kind, max_side * 1.2)
    box_w, box_h = width + 16 * margin, height + 2 * margin
    left, top = x_min + margin, y_max - margin
    ax.add_patch(
        Rectangle(
            (left, top - box_h),
            box_w,
            box_h,
            facecolor="white",
            edgecolor="black",
            lw=1.0,
            alpha=0.95,
            zorder=INSET_Z,
        )
    )
    centre = np.array([left + margin + width / 2, top - margin - height / 2])
    _draw_values(ax, step.kind, step.combined, centre, width, height, float(step.combined.max()), INSET_Z + 1)
    if step.kind == "discrete":
        legend = "rows: throttle,\ncoast, both,\nbrake\ncols: steer\nleft | 0 | right"
    else:
        legend = "x: steer\nleft | right\ny: throttle\n− brake"
    lines = [title, "π(a|s)", legend] if title else ["π(a|s)", legend]
    if not step.is_mixture:
        lines.append("(baseline: no\nper-object\nexplanation)")
    ax.text(
        left + 2 * margin + width,
        top - margin,
        "\n".join(lines),
        ha="left",
        va="top",
        fontsize=7,
        color="black",
        zorder=INSET_Z + 2,
    )
    return Glyph(-1, 1.0, centre, centre, width, height, step.combined, step.kind)


# ------------------------------------------------------------------------------------------------
# Episodes: frames, files, attributions
# ------------------------------------------------------------------------------------------------


def _at(tree, t: int):
    return jax.tree.map(lambda x: np.asarray(x)[t], tree)


def ego_pose(state) -> tuple[float, float, float]:
    """(x, y, θ) of the ego vehicle of a racing state (one step)."""
    vehicle = state.vehicle
    return float(np.asarray(vehicle.x)), float(np.asarray(vehicle.y)), float(np.asarray(vehicle.theta))


def render_base(
    env_name: str,
    state,
    params,
    control,
    overlay,
    objects: ObjectSet,
    ego_slot: int | None = None,
    **frame_options,
) -> np.ndarray:
    """The scenario's bird view of one step with ``overlay`` drawn on it.

    Racing scenes draw through ``envs.render.render_racing_state`` (Tracking also shows the
    observed trajectory points); the intersection through ``render_intersection_state`` following
    ``ego_slot`` (``control`` then holds all slots' controls, (8, 3)).
    """
    from envs import render

    base = env_name.removesuffix("_discrete")
    if base == "intersection":
        if ego_slot is None:
            raise ValueError("intersection explanations need the ego_slot whose policy is explained")
        return render.render_intersection_state(
            state, params, ego_slot=ego_slot, controls=control, overlay=overlay, **frame_options
        )
    points = None
    if base == "tracking" and objects.present.any() and np.isfinite(objects.world_xy).all():
        points = objects.world_xy[objects.present]
    return render.render_racing_state(
        state,
        params,
        control,
        show_cones=base == "country_road",
        points=points,
        overlay=overlay,
        **frame_options,
    )


def slot_pose(state, slot: int) -> tuple[float, float, float]:
    """(x, y, θ) of vehicle slot ``slot`` of a multi-agent state (one step)."""
    vehicle = jax.device_get(state.vehicle)
    return tuple(float(np.asarray(getattr(vehicle, k))[slot]) for k in ("x", "y", "theta"))


def intersection_frame(
    state,
    params,
    obs,
    explanation,
    ego_slot: int,
    *,
    neutral: bool = True,
    controls=None,
    mirrored: bool = False,
    title: str = "",
    threshold: float = DEFAULT_THRESHOLD,
    max_side: float = DEFAULT_MAX_SIDE,
    offset: float = DEFAULT_OFFSET,
    **frame_options,
) -> tuple[np.ndarray, list[Glyph]]:
    """One intersection frame following ``ego_slot`` with that vehicle's explanation drawn on it.

    ``obs`` is the env's per-slot observation (``vehicles_set`` (8, 8, 7), ``state`` (8, 66)) and
    ``explanation`` the unbatched :class:`~xrl_jax.explain.Explanation` of the ego slot's policy
    (9 objects with the neutral component first when ``neutral``, as the multi-agent X actors
    have). The neutral component is drawn at the ego car (offset up and right), the others at the
    vehicles their observation rows describe.
    """
    step = step_explanation(explanation, mirrored)
    objects = intersection_objects(state, obs, ego_slot, neutral, step.is_mixture)
    glyphs: list[Glyph] = []

    def overlay(ax, to_view):
        glyphs.extend(
            draw_explanation(ax, to_view, step, objects, threshold=threshold, max_side=max_side,
                             offset=offset, title=title)
        )  # fmt: skip

    frame = render_base(
        "intersection", state, params, controls, overlay, objects, ego_slot=ego_slot, mirrored=mirrored,
        **frame_options,
    )  # fmt: skip
    return frame, glyphs


@dataclasses.dataclass
class EpisodeFigures:
    """Everything needed to draw any step of a recorded episode (host copies of the record)."""

    env_name: str
    env: Any
    params: Any
    record: Any  # xrl_jax.explain.EpisodeRecord as numpy
    neutral: bool = False
    mirrored: bool = False

    @property
    def length(self) -> int:
        return int(np.sum(np.asarray(self.record.valid)))

    def step(self, t: int) -> tuple[StepExplanation, ObjectSet, Any]:
        if not 0 <= t < self.length:
            raise ValueError(f"step {t} is beyond the episode ({self.length} steps: 0..{self.length - 1})")
        explanation = _at(self.record.explanations, t)
        step = step_explanation(explanation, self.mirrored)
        state = _at(self.record.states, t)
        objects = scene_objects(
            scene_for(self.env_name),
            _at(self.record.obs, t),
            ego_pose(state),
            self.env,
            self.params,
            neutral=self.neutral and step.is_mixture,
            is_mixture=step.is_mixture,
        )
        return step, objects, state

    def frame(self, t: int, *, title: str = "", **options) -> tuple[np.ndarray, list[Glyph]]:
        """The frame of step ``t`` and its glyphs. ``options``: threshold, max_side, offset, and
        render_frame's width, height, hud."""
        draw_keys = ("threshold", "max_side", "offset")
        draw_options = {k: options.pop(k) for k in draw_keys if k in options}
        step, objects, state = self.step(t)
        glyphs: list[Glyph] = []

        def overlay(ax, to_view):
            glyphs.extend(draw_explanation(ax, to_view, step, objects, title=title, **draw_options))

        control = np.asarray(self.record.controls)[t]
        frame = render_base(
            self.env_name, state, self.params, control, overlay, objects, mirrored=self.mirrored, **options
        )
        return frame, glyphs

    def frames(self, steps: Sequence[int] | None = None, **options) -> list[np.ndarray]:
        steps = range(self.length) if steps is None else steps
        title = options.pop("title", "")
        return [self.frame(t, title=f"{title} step {t}".strip(), **dict(options))[0] for t in steps]

    def attributions(self, threshold: float = 0.0) -> list[dict]:
        """One JSON-ready row per step: ego pose, action, control, reward and every present object's
        weight, world position and label (objects with weight < ``threshold`` left out)."""
        rows = []
        actions = np.asarray(self.record.actions)
        for t in range(self.length):
            step, objects, state = self.step(t)
            x, y, theta = ego_pose(state)
            items = attribution_items(step, objects, threshold)
            rows.append(
                {
                    "step": t,
                    "ego": {"x": x, "y": y, "theta": theta},
                    "action": np.asarray(actions[t]).tolist(),
                    "control": np.asarray(self.record.controls[t], np.float64).tolist(),
                    "reward": float(np.asarray(self.record.rewards)[t]),
                    "explained": bool(step.is_mixture),
                    "objects": items,
                }
            )
        return rows


def attribution_items(step: StepExplanation, objects: ObjectSet, threshold: float) -> list[dict]:
    """One step's attribution records: index, weight, world position and label of every present
    object with weight >= ``threshold`` (none for baselines, which have no per-object weights)."""
    if not step.is_mixture:
        return []
    items = []
    for i in np.flatnonzero(step.present & objects.present):
        if step.weights[i] >= threshold:
            wx, wy = objects.world_xy[i]
            items.append(
                {"index": int(i), "weight": float(step.weights[i]), "x": float(wx), "y": float(wy)}
                | objects.labels[i]
            )
    return items


def intersection_objects(state, obs, slot: int, neutral: bool = True, is_mixture: bool = True) -> ObjectSet:
    """The explanation objects of slot ``slot``'s policy at one intersection step, labelled by car.

    ``obs`` is the env's per-slot observation; row k of the slot's ``vehicles_set`` (weight index
    k + 1 after the neutral component) is matched to the nearest other car of ``state`` and labelled
    ``{"type": "vehicle", "row": k, "slot": ..., "car": spawn_seq}``; the neutral component sits
    at the ego car.
    """
    ego_obs = jax.tree.map(lambda x: np.asarray(x)[slot], jax.device_get(obs))
    objects = scene_objects(
        SCENES["intersection"], ego_obs, slot_pose(state, slot), None, None,
        neutral=neutral and is_mixture, is_mixture=is_mixture,
    )  # fmt: skip
    if not is_mixture:
        return objects
    vehicle = jax.device_get(state.vehicle)
    cars_xy = np.stack([np.asarray(vehicle.x, np.float64), np.asarray(vehicle.y, np.float64)], -1)
    others = np.asarray(state.alive, bool).copy()
    others[slot] = False
    seq = np.asarray(state.spawn_seq)
    first_row = 1 if neutral else 0
    labels = list(objects.labels)
    for i in np.flatnonzero(objects.present[first_row:]) + first_row:
        if not others.any():
            break
        distance = np.where(others, np.linalg.norm(cars_xy - objects.world_xy[i], axis=-1), np.inf)
        match = int(np.argmin(distance))
        labels[i] = {**labels[i], "slot": match, "car": int(seq[match])}
    return dataclasses.replace(objects, labels=tuple(labels))


def first_alive_slot(record) -> int | None:
    """The first slot holding a car at step 0 of a multi-agent record (the default ego), or None."""
    alive = np.flatnonzero(np.asarray(record.acted)[0])
    return int(alive[0]) if alive.size else None


def _stamp(frame: np.ndarray, text: str) -> np.ndarray:
    """``text`` in black at the top left of an RGB frame (the top view has no overlay hook); it
    also keeps the empty-slot frames of a video distinct, so GIF writers do not merge them."""
    if not text:
        return frame
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.asarray(frame, np.uint8))
    ImageDraw.Draw(image).multiline_text((4, 4), text, fill=(0, 0, 0))
    return np.asarray(image)


@dataclasses.dataclass
class IntersectionEpisodeFigures:
    """Frames and attributions of one recorded Intersection episode (host copy of a
    :class:`xrl_jax.explain.MultiAgentEpisodeRecord`) following vehicle slot ``slot``.

    The figure follows the *slot*, i.e. whichever car occupies it: after its car completed its
    route, left the road or crashed, the slot may be refilled by a new car, which the frames then
    follow (the title names the car by its spawn number and says "new car" where it changed).
    Steps where the slot is empty are drawn as the top view of the whole crossing, without glyphs.
    """

    params: Any
    record: Any
    slot: int
    neutral: bool = True
    mirrored: bool = False

    def __post_init__(self):
        num_slots = np.asarray(self.record.acted).shape[-1]
        if isinstance(self.slot, bool) or not 0 <= int(self.slot) < num_slots:
            raise ValueError(f"slot {self.slot} out of range: the intersection has slots 0..{num_slots - 1}")
        self.slot = int(self.slot)

    @property
    def length(self) -> int:
        return int(np.sum(np.asarray(self.record.valid)))

    def _check_step(self, t: int):
        if not 0 <= t < self.length:
            raise ValueError(f"step {t} is beyond the episode ({self.length} steps: 0..{self.length - 1})")

    def occupied(self, t: int, slot: int | None = None) -> bool:
        """Whether ``slot`` (default: the followed one) holds a car in state s_t."""
        return bool(np.asarray(self.record.acted)[t, self.slot if slot is None else slot])

    def car(self, t: int, slot: int | None = None) -> int | None:
        """Spawn number of the car in ``slot`` at step t (None if empty)."""
        slot = self.slot if slot is None else slot
        return int(np.asarray(self.record.states.spawn_seq)[t, slot]) if self.occupied(t, slot) else None

    def new_car(self, t: int) -> bool:
        """The followed slot holds at step t a different car than at its previous occupied step."""
        occupied = np.asarray(self.record.acted)[: t + 1, self.slot]
        before = np.flatnonzero(occupied[:t])
        if not occupied[t] or before.size == 0:
            return False
        seq = np.asarray(self.record.states.spawn_seq)[:, self.slot]
        return bool(seq[before[-1]] != seq[t])

    def step(self, t: int, slot: int | None = None):
        """``(StepExplanation, ObjectSet, state)`` of ``slot`` at step t; the first two are None
        when the slot is empty."""
        self._check_step(t)
        slot = self.slot if slot is None else slot
        state = _at(self.record.states, t)
        if not self.occupied(t, slot):
            return None, None, state
        explanation = jax.tree.map(lambda x: np.asarray(x)[t, slot], self.record.explanations)
        step = step_explanation(explanation, self.mirrored)
        objects = intersection_objects(state, _at(self.record.obs, t), slot, self.neutral, step.is_mixture)
        return step, objects, state

    def title(self, t: int, prefix: str = "") -> str:
        car = self.car(t)
        who = f"slot {self.slot} empty" if car is None else f"slot {self.slot} car {car}"
        if self.new_car(t):
            who += " (new car)"
        return f"{prefix} step {t}\n{who}".strip()

    def frame(self, t: int, *, title: str = "", **options) -> tuple[np.ndarray, list[Glyph]]:
        """The frame of step ``t`` and its glyphs (none when the slot is empty: top view).
        ``options``: threshold, max_side, offset, and render_frame's width, height, hud."""
        draw_keys = ("threshold", "max_side", "offset")
        draw_options = {k: options.pop(k) for k in draw_keys if k in options}
        step, objects, state = self.step(t)
        if step is None:
            from envs import render

            size = {k: options[k] for k in ("width", "height") if k in options}
            frame = render.render_intersection_state(state, self.params, ego_slot=None, **size)
            return _stamp(frame, title), []
        glyphs: list[Glyph] = []

        def overlay(ax, to_view):
            glyphs.extend(draw_explanation(ax, to_view, step, objects, title=title, **draw_options))

        controls = np.asarray(self.record.controls)[t]
        frame = render_base(
            "intersection", state, self.params, controls, overlay, objects, ego_slot=self.slot,
            mirrored=self.mirrored, **options,
        )  # fmt: skip
        return frame, glyphs

    def frames(self, steps: Sequence[int] | None = None, **options) -> list[np.ndarray]:
        steps = range(self.length) if steps is None else steps
        prefix = options.pop("title", "")
        return [self.frame(t, title=self.title(t, prefix), **dict(options))[0] for t in steps]

    def attributions(self, threshold: float = 0.0, all_slots: bool = False) -> list[dict]:
        """JSON-ready rows: per step one row of the followed slot (also when it is empty:
        ``"alive": false`` and no objects), or with ``all_slots`` one row per occupied slot.
        A row holds step, slot, car, the ego pose, action, control, reward, end flags and every
        present object's index, weight, world position and label ("neutral" or a vehicle with its
        observation row, slot and car)."""
        record = self.record
        num_slots = np.asarray(record.acted).shape[-1]
        rows = []
        for t in range(self.length):
            slots = [s for s in range(num_slots) if self.occupied(t, s)] if all_slots else [self.slot]
            for slot in slots:
                step, objects, state = self.step(t, slot)
                row = {"step": t, "slot": slot, "car": self.car(t, slot), "alive": step is not None}
                if step is None:
                    rows.append({**row, "ego": None, "explained": False, "objects": []})
                    continue
                x, y, theta = slot_pose(state, slot)
                items = attribution_items(step, objects, threshold)
                row.update(
                    ego={"x": x, "y": y, "theta": theta},
                    action=np.asarray(record.actions)[t, slot].tolist(),
                    control=np.asarray(record.controls[t, slot], np.float64).tolist(),
                    reward=float(np.asarray(record.rewards)[t, slot]),
                    terminated=bool(np.asarray(record.terminated)[t, slot]),
                    truncated=bool(np.asarray(record.truncated)[t, slot]),
                    done_reason=int(np.asarray(record.done_reason)[t, slot]),
                    explained=bool(step.is_mixture),
                    objects=items,
                )
                rows.append(row)
        return rows


def write_attributions(rows: Sequence[dict], path: str | Path) -> Path:
    """JSON lines, one per step."""
    path = Path(path)
    with open(path, "w") as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + "\n")
    return path


__all__ = [
    "SCENES",
    "EpisodeFigures",
    "Glyph",
    "IntersectionEpisodeFigures",
    "ObjectSet",
    "Scene",
    "StepExplanation",
    "attribution_items",
    "component_density_images",
    "discrete_matrix",
    "draw_explanation",
    "ego_to_world",
    "first_alive_slot",
    "intersection_frame",
    "intersection_objects",
    "mixture_image",
    "pedal_masses",
    "render_base",
    "scene_for",
    "scene_objects",
    "slot_pose",
    "steer_column_order",
    "steering_masses",
    "step_explanation",
    "write_attributions",
]
