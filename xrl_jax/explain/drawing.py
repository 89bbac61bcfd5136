"""Drawing an explanation onto the bird view of ``envs.render`` (matplotlib, in view metres).

Glyphs are drawn through the renderer's overlay callback, so they share its view transform
(following the ego car, optionally mirrored) and land exactly on the objects they explain.
How to read a figure: :mod:`xrl_jax.explain.figures`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import numpy as np
from matplotlib import colormaps
from matplotlib.patches import Rectangle

from xrl_jax.explain.glyphs import StepExplanation
from xrl_jax.explain.scenes import ObjectSet

DEFAULT_THRESHOLD = 0.05
DEFAULT_MAX_SIDE = 7.0  # metres of view: the side of a weight-1 glyph
DEFAULT_OFFSET = 2.5  # metres between an object and the near edge of its glyph
DRAW_OPTIONS = ("threshold", "max_side", "offset")  # the frame options that go to draw_explanation

DISCRETE_ROW_COLOURS = np.array([(0, 1, 0), (1, 1, 1), (1, 0.6, 0), (1, 0, 0)], np.float64)
CONTINUOUS_CMAP = "inferno"

GLYPH_Z, LINE_Z, INSET_Z = 13, 12, 25


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


def _intersection_view(state, params, control, overlay, objects, ego_slot, **frame_options) -> np.ndarray:
    """The Intersection's bird view following ``ego_slot`` (``control``: all slots' controls, (8, 3))."""
    from envs import render

    del objects
    if ego_slot is None:
        raise ValueError("intersection explanations need the ego_slot whose policy is explained")
    return render.render_intersection_state(
        state, params, ego_slot=ego_slot, controls=control, overlay=overlay, **frame_options
    )


def _racing_view(
    state,
    params,
    control,
    overlay,
    objects,
    ego_slot,
    *,
    show_cones: bool,
    show_points: bool,
    **frame_options,
) -> np.ndarray:
    """A racing scene's bird view, with its cones or the observed centre-line points."""
    from envs import render

    del ego_slot
    points = None
    if show_points and objects.present.any() and np.isfinite(objects.world_xy).all():
        points = objects.world_xy[objects.present]
    return render.render_racing_state(
        state,
        params,
        control,
        show_cones=show_cones,
        points=points,
        overlay=overlay,
        **frame_options,
    )


# The bird view of each scenario (its discrete variant alike).
BIRD_VIEWS: dict[str, Callable[..., np.ndarray]] = {
    "country_road": functools.partial(_racing_view, show_cones=True, show_points=False),
    "tracking": functools.partial(_racing_view, show_cones=False, show_points=True),
    "intersection": _intersection_view,
}


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
    """The scenario's bird view of one step with ``overlay`` drawn on it (:data:`BIRD_VIEWS`).

    Racing scenes draw through ``envs.render.render_racing_state`` (Tracking also shows the
    observed trajectory points); the intersection through ``render_intersection_state`` following
    ``ego_slot`` (``control`` then holds all slots' controls, (8, 3)).
    """
    base = env_name.removesuffix("_discrete")
    if base not in BIRD_VIEWS:
        raise ValueError(f"no bird view of env {env_name!r}; known: {', '.join(BIRD_VIEWS)}")
    return BIRD_VIEWS[base](state, params, control, overlay, objects, ego_slot, **frame_options)


def explained_frame(
    env_name: str,
    state,
    params,
    control,
    step: StepExplanation,
    objects: ObjectSet,
    *,
    title: str = "",
    ego_slot: int | None = None,
    mirrored: bool = False,
    **options,
) -> tuple[np.ndarray, list[Glyph]]:
    """The bird view of one step with its explanation drawn on it, and the glyphs drawn.

    ``options``: :func:`draw_explanation`'s threshold, max_side, offset; the rest go to the
    renderer (width, height, hud).
    """
    draw_options = {k: options.pop(k) for k in DRAW_OPTIONS if k in options}
    glyphs: list[Glyph] = []

    def overlay(ax, to_view):
        glyphs.extend(draw_explanation(ax, to_view, step, objects, title=title, **draw_options))

    frame = render_base(
        env_name, state, params, control, overlay, objects, ego_slot=ego_slot, mirrored=mirrored, **options
    )
    return frame, glyphs
