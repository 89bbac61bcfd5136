"""The figures of a run's explanation statistics (``experiments/explain.py --stats``): one PNG with
where the weight goes (ego-frame map, object kinds, distance, time to contact), how many objects an
explanation needs (by speed), how steady it is and how alike the seeds are, and one of the deletion
curves (policy change and return as the top-ranked objects are removed); curves carry their interval
over seeds. Reads only the summary that :mod:`xrl_jax.explain.run_statistics` writes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _centres(edges) -> np.ndarray:
    edges = np.asarray(edges, np.float64)
    return 0.5 * (edges[:-1] + edges[1:])


def _band(ax, x, intervals, colour: str, label: str | None = None, style: str = "-", alpha: float = 0.25):
    """IQM over seeds as a line, its 95 % interval as a band (bins without data left out)."""
    estimate = np.array([i["estimate"] for i in intervals], np.float64)
    low = np.array([i["low"] for i in intervals], np.float64)
    high = np.array([i["high"] for i in intervals], np.float64)
    ax.plot(x, estimate, color=colour, linestyle=style, marker="o", markersize=3, label=label)
    ax.fill_between(x, low, high, color=colour, alpha=alpha, linewidth=0)


def _save(fig, path: str | Path) -> Path:
    """The figure written whole or not at all: into a temporary file beside it, then renamed (a run
    killed mid-write leaves the previous figure, never a truncated one)."""
    import matplotlib.pyplot as plt

    path = Path(path)
    partial = path.with_name(f".{path.name}.partial")
    fig.savefig(partial, dpi=110, format="png")
    plt.close(fig)
    os.replace(partial, path)
    return path


def _kind_bars(ax, summary: dict, colour: str) -> None:
    """Each object kind's share of the weight (bars with the interval over seeds)."""
    kinds, shares = summary["kinds"], summary["kind"]["share"]
    estimate = [s["estimate"] for s in shares]
    errors = np.array([[s["estimate"] - s["low"], s["high"] - s["estimate"]] for s in shares]).T
    ax.bar(range(len(kinds)), estimate, yerr=errors, color=colour, alpha=0.8, capsize=4)
    per_step = [s["estimate"] for s in summary["kind"]["objects_per_step"]]
    labels = [f"{k}\n({n:.1f} per step)" for k, n in zip(kinds, per_step, strict=True)]
    ax.set_xticks(range(len(kinds)), labels)
    ax.set(ylabel="share of the weight", ylim=(0, 1), title="weight by object kind")


def draw_statistics(summary: dict, path: str | Path, title: str = "") -> Path:
    """Six panels of ``summary`` into ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    colour = "#d62728"

    ax = axes[0, 0]
    share = np.asarray(summary["map"]["share"], np.float64).T  # (Y, X) for imshow: rows are y
    x_edges, y_edges = summary["map"]["x_edges"], summary["map"]["y_edges"]
    positive = share[share > 0]
    if positive.size:
        # y (left) up and x (forward) to the right: the car drives to the right of the picture.
        image = ax.imshow(
            np.where(share > 0, share, np.nan),
            origin="lower",
            extent=(x_edges[0], x_edges[-1], y_edges[0], y_edges[-1]),
            norm=LogNorm(vmin=max(positive.min(), positive.max() * 1e-4), vmax=positive.max()),
            cmap="viridis",
        )
        fig.colorbar(image, ax=ax, label="weight per step and cell")
    ax.plot([0], [0], marker=">", color="black", markersize=9)
    ax.set(xlabel="ahead (m)", ylabel="left (m)", title="where the weight goes (ego frame)")

    ax = axes[0, 1]
    kinds = summary["kinds"]
    if len(kinds) == 1:  # one kind of object (Tracking's points): the weight by slot, i.e. rank ahead
        slots = summary["slot"]["share"]
        _band(ax, np.arange(len(slots)), slots, colour)
        ax.set(xlabel=f"{kinds[0]}: slot in the observation", ylabel="share of the weight per step",
               title="weight by slot")  # fmt: skip
    else:
        _kind_bars(ax, summary, colour)

    ax = axes[0, 2]
    distance = summary["distance"]
    _band(ax, _centres(distance["edges"]), distance["share"], colour, "share of the weight")
    ax.set(
        xlabel="distance from the ego (m)", ylabel="share of the weight per step", title="weight by distance"
    )

    ax = axes[1, 0]
    contact = summary["time_to_contact"]
    _band(ax, _centres(contact["edges"]), contact["share"], colour)
    ax.set(
        xlabel="time to contact (s), objects approached",
        ylabel="share of the weight per step",
        title="weight by time to contact",
    )

    ax = axes[1, 1]
    size = summary["size"]
    counts = np.asarray(size["steps_by_speed"])
    keep = counts > 0
    centres = _centres(size["speed_edges"])
    _band(ax, centres[keep], [s for s, k in zip(size["by_speed"], keep, strict=True) if k], colour)
    ax.set(
        xlabel="ego speed (m/s)",
        ylabel=f"objects carrying {size['share']:.0%} of the weight",
        title=f"explanation size: {size['mean']['estimate']:.2f} objects on average",
    )

    ax = axes[1, 2]
    similarity = np.asarray(summary["agreement"]["similarity"], np.float64)
    image = ax.imshow(similarity, vmin=0, vmax=1, cmap="magma")
    ax.set_xticks(range(len(similarity)))
    ax.set_yticks(range(len(similarity)))
    fig.colorbar(image, ax=ax, label="1 − TV of the weights, same observations")
    stability = summary["stability"]["mean_change"]
    ax.set(
        xlabel="seed",
        ylabel="seed",
        title=(
            f"seeds alike: {summary['agreement']['mean_similarity_between_seeds']:.2f}; "
            f"step to step TV {stability['estimate']:.3f}"
        ),
    )
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


RANKER_STYLES = {  # the explanation's own order solid, the post-hoc ones dashed, the control grey
    "weight": ("#d62728", "-", "by mixture weight"),
    "occlusion": ("#1f77b4", "--", "by occlusion"),
    "gradient_x_input": ("#2ca02c", "--", "by gradient × input"),
    "random": ("#7f7f7f", ":", "in random order"),
}
METRIC_LABELS = {
    "tv": "policy change (total variation)",
    "return": "evaluation return",
    "trips_completed": "completed trips",
    "early_terminations": "early terminations (off the road, collided)",
}


def draw_deletion(deletion: dict, path: str | Path, title: str = "") -> Path:
    """One panel per metric: its IQM over seeds (band: 95 % interval) against the objects deleted,
    one line per ranker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = deletion["metrics"]
    columns = min(len(metrics), 2)  # the Intersection's four metrics in a square, not a strip
    rows = -(-len(metrics) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(5.6 * columns, 3.8 * rows + 0.6), squeeze=False)
    ks = np.asarray(deletion["ks"])
    for ax, metric in zip(axes.flat, metrics, strict=True):
        for ranker, curves in deletion["rankers"].items():
            colour, style, label = RANKER_STYLES[ranker]
            _band(ax, ks, curves[metric]["over_seeds"], colour, label, style, alpha=0.2)
        ax.set(xlabel="objects deleted from every observation", ylabel=METRIC_LABELS[metric])
        ax.set_xticks(ks)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.06 / rows, 1, 1))
    return _save(fig, path)
