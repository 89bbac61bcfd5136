"""A run's figures: its learning curve (with the training episodes and the scenario's yardstick
where known) and, for a sweep, the scores against the swept value (the paper's Fig. 8). Matplotlib
without pyplot: no GUI backend, safe in threads and on servers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from xrl_jax.runs.references import MeasuredYardstick
from xrl_jax.runs.summary import summary_metrics
from xrl_jax.runs.tables import curve_label, format_value, point_label

TrainingCurve = dict[str, tuple[list[int], list[float]]]  # summary.training_curve's
REFERENCE_STYLE = {"color": "tab:red", "linestyle": "--", "linewidth": 1.2}


def plot_learning_curve(
    summary: dict[str, Any], path: str | Path, metrics: int = 2,
    reference: MeasuredYardstick | None = None, training: TrainingCurve | None = None,
) -> Path:  # fmt: skip
    """Save :func:`learning_curve_figure` as a PNG; returns ``path``."""
    path = Path(path)
    learning_curve_figure(summary, metrics, reference, training).savefig(path, dpi=110)
    return path


def learning_curve_figure(
    summary: dict[str, Any], metrics: int = 2, reference: MeasuredYardstick | None = None,
    training: TrainingCurve | None = None,
) -> Any:  # fmt: skip
    """The learning curve of the first ``metrics`` summary metrics, one panel each (a matplotlib
    ``Figure``): the evaluations' IQM line with its 95 % CI band and thin per-seed lines; the
    training episodes' mean over seeds as a lighter line (``training``:
    :func:`~xrl_jax.runs.summary.training_curve`), since evaluations are few (a quick-start run of
    80k steps evaluates at 40k and 80k) while a metrics line comes every ``log_interval``; and the
    scenario's yardstick as a dashed horizontal line (``reference``: a
    :class:`~xrl_jax.runs.references.MeasuredYardstick` measured on the run's evaluation, or None).
    For a sweep, one IQM line (and a light CI band) per point, labelled by its values, without
    per-seed or training lines."""
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, safe in threads and on servers

    chosen = summary_metrics(summary["env"])[:metrics]
    if summary.get("sweep"):
        return _sweep_curves_figure(summary, chosen, reference)
    curve = summary.get("curve", [])
    training = training or {}
    figure = Figure(figsize=(4.2 * len(chosen), 3.2), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        points = [p for p in curve if key in p]
        steps = np.array([p["step"] for p in points])
        if points:
            per_seed = np.array([p[key]["per_seed"] for p in points])
            ax.plot(steps, per_seed, color="0.75", linewidth=0.8)
            ax.fill_between(
                steps, [p[key]["low"] for p in points], [p[key]["high"] for p in points],
                color="tab:blue", alpha=0.25, linewidth=0, label="95 % CI",
            )  # fmt: skip
            ax.plot(steps, [p[key]["estimate"] for p in points], color="tab:blue", marker="o", label="IQM")
        if key in training:
            ax.plot(*training[key], color="tab:orange", alpha=0.6, linewidth=1.0,
                    label="training episodes (seeds' mean)")  # fmt: skip
        _draw_reference(ax, reference, key)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="small")
        ax.set_xlabel("environment steps per seed")
        format_step_axis(ax)
        ax.set_title(curve_label(label))
        ax.grid(alpha=0.3)
    seeds = max((p[key]["n"] for p in curve for key, _ in chosen if key in p), default=0)
    figure.suptitle(f"{summary['env']} / {summary['algo']} ({summary['preset']}), {seeds} seeds")
    return figure


def _draw_reference(ax: Any, reference: MeasuredYardstick | None, key: str) -> None:
    """The yardstick's score on metric ``key`` as a labelled horizontal line, where it has one."""
    if reference is not None and key in reference.scores:
        ax.axhline(reference.scores[key], label=reference.label(key), **REFERENCE_STYLE)


def _sweep_curves_figure(summary: dict[str, Any], chosen, reference: MeasuredYardstick | None) -> Any:
    from matplotlib.figure import Figure

    points = summary["sweep"]["points"]
    figure = Figure(figsize=(4.2 * len(chosen), 3.2), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        for index, point in enumerate(points):
            rows = [p for p in point["curve"] if key in p]
            if not rows:
                continue
            color = f"C{index % 10}"
            steps = [p["step"] for p in rows]
            low, high = [p[key]["low"] for p in rows], [p[key]["high"] for p in rows]
            ax.fill_between(steps, low, high, color=color, alpha=0.12, linewidth=0)
            ax.plot(steps, [p[key]["estimate"] for p in rows], color=color, marker="o", markersize=3,
                    label=point_label(point["values"]))  # fmt: skip
        _draw_reference(ax, reference, key)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="x-small")
        ax.set_xlabel("environment steps per seed")
        format_step_axis(ax)
        ax.set_title(curve_label(label) + " (IQM, 95 % CI)")
        ax.grid(alpha=0.3)
    figure.suptitle(f"{summary['env']} / {summary['algo']} ({summary['preset']}), sweep over "
                    f"{', '.join(summary['sweep']['fields'])}")  # fmt: skip
    return figure


def sweep_x_scale(values) -> tuple[str, float | None]:
    """When the swept values span at least two orders of magnitude: ``("symlog", linthresh)`` if
    they span zero (include it, or both signs; e.g. kappa = -0.01 … 0.1), with the smallest non-zero
    magnitude as the linear threshold, and ``("log", None)`` if they are all positive (e.g. learning
    rates 1e-5 … 1e-3); else ``("linear", None)``."""
    values = np.asarray(values, np.float64)
    magnitudes = np.abs(values[values != 0])
    if magnitudes.size < 2 or magnitudes.max() < 100 * magnitudes.min():
        return "linear", None
    if values.min() <= 0 <= values.max():
        return "symlog", float(magnitudes.min())
    return ("log", None) if values.min() > 0 else ("linear", None)


def plot_sweep(summary: dict[str, Any], path: str | Path, baseline: dict[str, Any] | None = None) -> Path:
    """Save the sweep figure (the paper's Fig. 8 style) as a PNG; returns ``path``.

    Two panels, the first two summary metrics (final return and early-termination rate; for
    intersection, return and completed trips): x is the swept value of the first field, y the IQM
    over the point's seeds with its 95 % CI as error bars. With more than one swept field, one line
    per combination of the other fields' values. ``baseline`` (the summary of a plain run, e.g.
    DSAC) adds a horizontal line at its final IQM with its CI shaded, labelled ``baseline: <algo>``.
    The x scale is symlog when the values span zero and several orders of magnitude, log when they
    are positive and span several, else linear (:func:`sweep_x_scale`).
    """
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, safe in threads and on servers

    sweep = summary.get("sweep")
    if not sweep:
        raise ValueError("plot_sweep needs the summary of a sweep (summary['sweep'] is missing)")
    fields = sweep["fields"]
    first, others = fields[0], fields[1:]
    lines: dict[tuple, list[dict]] = {}  # the other fields' values -> the points on that line
    for point in sweep["points"]:
        lines.setdefault(tuple(point["values"][name] for name in others), []).append(point)
    xs = sorted({point["values"][first] for point in sweep["points"]})
    scale, linthresh = sweep_x_scale(xs)
    chosen = summary_metrics(summary["env"])[:2]
    figure = Figure(figsize=(4.4 * len(chosen), 3.4), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        if scale == "symlog":  # before plotting, so that the margins apply on this scale
            ax.set_xscale("symlog", linthresh=linthresh)
        elif scale == "log":
            ax.set_xscale("log")
        for index, (rest, points) in enumerate(lines.items()):
            done = sorted((p for p in points if key in p["aggregate"]), key=lambda p: p["values"][first])
            if not done:
                continue
            x = np.array([p["values"][first] for p in done], np.float64)
            est = np.array([p["aggregate"][key]["estimate"] for p in done])
            low = np.array([p["aggregate"][key]["low"] for p in done])
            high = np.array([p["aggregate"][key]["high"] for p in done])
            name = point_label(dict(zip(others, rest, strict=True))) if others else "IQM, 95 % CI"
            ax.errorbar(x, est, yerr=[est - low, high - est], color=f"C{index % 10}", marker="o",
                        capsize=3, linewidth=1.2, label=name)  # fmt: skip
        agg = (baseline or {}).get("aggregate", {}).get(key)
        if agg is not None:
            ax.axhspan(agg["low"], agg["high"], color="0.5", alpha=0.2, linewidth=0)
            ax.axhline(agg["estimate"], color="0.3", linestyle="--", linewidth=1.2,
                       label=f"baseline: {baseline['algo']}")  # fmt: skip
        ax.set_xticks(xs, [format_value(x) for x in xs], fontsize="small", rotation=45 if len(xs) > 5 else 0)
        ax.minorticks_off()
        ax.set_xlabel(first)
        ax.set_title(label)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="x-small")
    seeds = max((len(p["seeds"]) for p in sweep["points"]), default=0)
    title = f"{summary['env']} / {summary['algo']} ({summary['preset']})"
    figure.suptitle(f"{title}: IQM over up to {seeds} seeds per point")
    path = Path(path)
    figure.savefig(path, dpi=110)
    return path


def format_step_axis(ax: Any) -> None:
    """Step ticks as 20k, 1M: written out in full they run into each other beyond ~50k steps."""
    from matplotlib.ticker import EngFormatter, MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10], integer=True))
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))
