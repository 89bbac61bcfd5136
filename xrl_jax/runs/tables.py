"""A run's summary as plain text: the aggregate table, the learning curve, the training tracks."""

from __future__ import annotations

from typing import Any

from xrl_jax import stats
from xrl_jax.runs.summary import summary_metrics


def format_training_tracks(summary: dict[str, Any]) -> str | None:
    """One line on the training tracks (None for intersection runs and older summaries)."""
    tracks = summary.get("training_tracks")
    if tracks is None:
        return None
    if not tracks["fresh"]:
        return f"training tracks: a fixed bank of {tracks['bank']}"
    used = list(tracks["distinct_per_seed"].values())
    if not used:
        return "training tracks: fresh (no metrics yet)"
    reused = sum(tracks["reused_per_seed"].values())
    spread = f" (min {min(used):,}, max {max(used):,})" if len(used) > 1 else ""
    return (
        f"training tracks: fresh, {sum(used) / len(used):,.0f} distinct per {_run_unit(summary)}{spread}; "
        f"{reused:,} resets reused a track"
    )


def _run_unit(summary: dict[str, Any]) -> str:
    """What a summary's rows are: seeds, or members (a seed at a sweep point) in a sweep."""
    return "member" if summary.get("sweep") else "seed"


def format_value(value: Any) -> str:
    return f"{value:g}" if isinstance(value, int | float) else str(value)


def format_interval(agg: dict[str, Any] | None) -> str:
    return f"{agg['estimate']:.3f} [{agg['low']:.3f}, {agg['high']:.3f}]" if agg else "-"


def interval_coverage(agg: dict[str, Any], confidence: float = 0.95) -> float:
    """The actual coverage of ``agg``'s interval at its number of seeds (a summary written before the
    summaries kept it: measured now)."""
    if "coverage" in agg:
        return float(agg["coverage"])
    return stats.iqm_interval_coverage(int(agg["n"]), float(agg.get("confidence", confidence)))


def coverage_note(aggregates: list[dict[str, Any]]) -> str | None:
    """One line naming the interval's method and its actual coverage at each number of seeds in
    ``aggregates`` (``None`` when there are none)."""
    by_n = {int(agg["n"]): interval_coverage(agg) for agg in aggregates if agg}
    if not by_n:
        return None
    held = "; ".join(f"at {n} seed{'s' * (n != 1)} {100 * c:.0f} %" for n, c in sorted(by_n.items()))
    return (f"95% CI: percentile bootstrap of the IQM over seeds (2,000 resamples); the share of samples "
            f"of normal scores whose interval holds their IQM: {held}")  # fmt: skip


def format_table(summary: dict[str, Any]) -> str:
    """A plain-text table of the aggregate scores (IQM and 95 % stratified bootstrap CI over seeds);
    for a sweep, one row per point: its values, IQM [95 % CI] of the first two summary metrics
    (final return and early-termination rate; for intersection, return and completed trips) and its
    number of seeds with a final evaluation (``*``: not all of them have one yet)."""
    title = f"{summary['env']} / {summary['algo']} ({summary['preset']}), {summary['steps']} steps per seed"
    if summary.get("sweep"):
        return _format_sweep_table(summary, title)
    lines = [title, f"{'metric':<26} {'IQM':>10} {'95% CI':>22} {'mean':>10} {'seeds':>6}"]
    for key, label in summary_metrics(summary["env"]):
        agg = summary["aggregate"].get(key)
        if agg is None:
            continue
        ci = f"[{agg['low']:.3f}, {agg['high']:.3f}]"
        lines.append(f"{label:<26} {agg['estimate']:>10.3f} {ci:>22} {agg['mean']:>10.3f} {agg['n']:>6d}")
    if not summary["aggregate"]:
        lines.append("(no final evaluation yet)")
    note = coverage_note(list(summary["aggregate"].values()))
    if note:
        lines.append(note)
    tracks = format_training_tracks(summary)
    if tracks:
        lines.append(tracks)
    return "\n".join(lines)


def _format_sweep_table(summary: dict[str, Any], title: str) -> str:
    sweep = summary["sweep"]
    chosen = summary_metrics(summary["env"])[:2]
    widths = [max(8, len(name)) for name in sweep["fields"]]
    header = "".join(f"{name:>{w}} " for name, w in zip(sweep["fields"], widths, strict=True))
    header += "".join(f" {label + ' IQM [95% CI]':>34}" for _, label in chosen) + f" {'seeds':>6}"
    lines = [title, header]
    for point in sweep["points"]:
        values = [format_value(point["values"][name]) for name in sweep["fields"]]
        row = "".join(f"{value:>{w}} " for value, w in zip(values, widths, strict=True))
        row += "".join(f" {format_interval(point['aggregate'].get(key)):>34}" for key, _ in chosen)
        seeds = f"{len(point['seeds'])}{'' if point['complete'] else '*'}"
        lines.append(row + f" {seeds:>6}")
    if not all(point["complete"] for point in sweep["points"]):
        lines.append("* not every seed of the point has a final evaluation yet")
    note = coverage_note([point["aggregate"].get(key) for point in sweep["points"] for key, _ in chosen])
    if note:
        lines.append(note)
    tracks = format_training_tracks(summary)
    if tracks:
        lines.append(tracks)
    return "\n".join(lines)


def point_label(values: dict[str, Any]) -> str:
    """``{"kappa": 0.01, "gamma": 0.99}`` -> ``"kappa=0.01, gamma=0.99"``."""
    return ", ".join(f"{name}={format_value(value)}" for name, value in values.items())


def curve_label(label: str) -> str:
    """'final return' -> 'return': a curve point is not final."""
    return label.removeprefix("final ")


def format_curve(summary: dict[str, Any], metrics: int = 2) -> str:
    """The learning curve as a plain-text table: per evaluation step, IQM [95 % CI] of the first
    ``metrics`` summary metrics."""
    chosen = summary_metrics(summary["env"])[:metrics]
    header = f"{'step':>10}" + "".join(f"  {curve_label(label):>30}" for _, label in chosen)
    if summary.get("sweep"):  # one line per point: the last step all its seeds reached
        title = "learning curves per sweep point: IQM [95% CI] at the last step all its seeds reached"
        lines = [f"{title} (every step: summary.json)", header + "  point"]
        for point in summary["sweep"]["points"]:
            last = point["curve"][-1] if point["curve"] else {"step": "-"}
            cells = "".join(f"  {format_interval(last.get(key)):>30}" for key, _ in chosen)
            lines.append(f"{last['step']:>10}{cells}  {point_label(point['values'])}")
        return "\n".join(lines)
    lines = ["learning curve (IQM [95% CI] over seeds)", header]
    for point in summary.get("curve", []):
        cells = []
        for key, _ in chosen:
            agg = point.get(key)
            cells.append(f"{agg['estimate']:.3f} [{agg['low']:.3f}, {agg['high']:.3f}]" if agg else "-")
        lines.append(f"{point['step']:>10}" + "".join(f"  {cell:>30}" for cell in cells))
    return "\n".join(lines)
