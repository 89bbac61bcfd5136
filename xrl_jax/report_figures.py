"""The report's figures: final performance and learning curves per env (the paper's Fig. 5-7) and
each explainable agent against its baseline (Fig. 7's layout). Every agent has one colour in every
figure, and legends sit outside the axes, so that no curve is hidden behind one."""

from __future__ import annotations

from typing import Any

from xrl_jax.config import BASELINES, scenario
from xrl_jax.runs.plots import format_step_axis
from xrl_jax.runs.tables import curve_label

Run = Any  # xrl_jax.report.Run (a run's cfg, summary and label); that module sits above this one

ALGO_ORDER = ("sac", "xsac", "dsac", "xdsac", "ppo", "xppo", "dppo", "xdppo")  # rows: each baseline, its X
# One colour per agent in every figure: a baseline and its explainable agent in one hue family's
# neighbours would be hard to tell apart, so the pairs get contrasting colours.
AGENT_COLOURS = {
    "sac": "tab:blue", "xsac": "tab:orange", "dsac": "tab:green", "xdsac": "tab:red",
    "ppo": "tab:cyan", "xppo": "tab:brown", "dppo": "tab:olive", "xdppo": "tab:purple",  # on-policy
}  # fmt: skip
# A second run of one agent (another preset or folder) keeps the agent's colour with its own line style.
RUN_STYLES = ("-", "--", ":", "-.")


def table_metrics(env: str) -> tuple[tuple[str, str], ...]:
    """The (key, label) pairs of ``env``'s table; the first two are its figure's (the paper's Fig. 5/6:
    return and early-termination rate; on the Intersection Fig. 7's trips and early terminations)."""
    return scenario(env).table_metrics


def yardstick_name(env: str, speed: float) -> str:
    return f"{scenario(env).yardstick} ({speed:g} m/s)"


def _plain_runs(runs: list[Run], env: str) -> list[Run]:
    """The env's runs that are not sweeps and have a learning curve: the ones the figures draw."""
    return [r for r in runs if r.cfg.env == env and not r.is_sweep and r.summary["curve"]]


def run_styles(runs: list[Run]) -> list[tuple[str, str]]:
    """(colour, line style) of each run: its agent's colour, and a line style that tells apart several
    runs of one agent (in the order given)."""
    seen: dict[str, int] = {}
    styles = []
    for run in runs:
        nth = seen[run.cfg.algo] = seen.get(run.cfg.algo, -1) + 1
        styles.append((AGENT_COLOURS.get(run.cfg.algo, "tab:gray"), RUN_STYLES[nth % len(RUN_STYLES)]))
    return styles


def _draw_curve(ax, run: Run, key: str, style: tuple[str, str], label: str) -> None:
    """``run``'s curve of ``key``: IQM line, 95 % CI band, markers (a one-point curve shows too)."""
    colour, line = style
    points = [p for p in run.summary["curve"] if key in p]
    steps = [p["step"] for p in points]
    ax.plot(steps, [p[key]["estimate"] for p in points], color=colour, linestyle=line, marker="o",
            markersize=3, label=label)  # fmt: skip
    ax.fill_between(steps, [p[key]["low"] for p in points], [p[key]["high"] for p in points],
                    color=colour, alpha=0.2, linewidth=0)  # fmt: skip


def _legend_below(figure, axes) -> None:
    """One legend for the whole figure, under its panels: inside an axes it hid curve segments."""
    entries = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    if entries:
        figure.legend(list(entries.values()), list(entries), loc="outside lower center",
                      ncols=min(len(entries), 5), fontsize="small")  # fmt: skip


def env_figure(runs: list[Run], env: str, references: list[dict] | None = None):
    """Final performance per agent (IQM and 95 % CI, the paper's Fig. 5/6) and the learning curves
    (IQM line and CI band per agent, Fig. 7) of the env's plain runs, one colour per agent in all
    four panels; each of ``references`` (the hand controller's results) is a dashed line."""
    from matplotlib.figure import Figure

    plain = _plain_runs(runs, env)
    if not plain:
        return None
    metrics = table_metrics(env)[:2]
    algos = [r.cfg.algo for r in plain]
    # The agent's name says it all when each agent has one run here; otherwise preset and folder too.
    labels = [r.cfg.algo if algos.count(r.cfg.algo) == 1 else r.label for r in plain]
    figure = Figure(figsize=(10.0, 7.0), layout="constrained")
    axes = figure.subplots(2, 2)
    styles = run_styles(plain)
    for column, (key, label) in enumerate(metrics):
        bars, curves = axes[0][column], axes[1][column]
        names = []  # the agents with a final evaluation (an unfinished run has a curve only)
        for run, label_of_run, style in zip(plain, labels, styles, strict=True):
            agg = run.summary["aggregate"].get(key)
            if agg:
                error = [[agg["estimate"] - agg["low"]], [agg["high"] - agg["estimate"]]]
                bars.errorbar(agg["estimate"], len(names), xerr=error, fmt="o", capsize=4, color=style[0])
                names.append(label_of_run)
            _draw_curve(curves, run, key, style, label_of_run)
        if names:
            bars.set_yticks(range(len(names)), names)
        for reference in references or []:
            name = yardstick_name(env, reference["target_speed"])
            bars.axvline(reference[key], color="black", linestyle="--", linewidth=1, label=name)
            curves.axhline(reference[key], color="black", linestyle="--", linewidth=1, label=name)
        bars.set_title(f"{label} (IQM, 95 % CI)")
        curves.set_title(curve_label(label))
        curves.set_xlabel("environment steps per seed")
        format_step_axis(curves)
        curves.grid(alpha=0.3)
        bars.grid(alpha=0.3)
    _legend_below(figure, axes[1])
    figure.suptitle(env)
    return figure


def pairs_figure(runs: list[Run], env: str, references: list[dict] | None = None):
    """The paper's Fig. 7 layout: one row per pair of an explainable agent and its baseline (XSAC
    against SAC, XDSAC against DSAC), one column per figure metric (on the Intersection, completed
    trips and early terminations), each run's learning curve as IQM with its 95 % CI band, and the
    yardstick of ``references`` as a dashed line. None if no pair has a curve."""
    from matplotlib.figure import Figure

    plain = _plain_runs(runs, env)
    pairs = [(x, y) for x in plain for y in plain
             if BASELINES.get(x.cfg.algo) == y.cfg.algo and x.cfg.preset == y.cfg.preset]  # fmt: skip
    if not pairs:
        return None
    metrics = table_metrics(env)[:2]
    figure = Figure(figsize=(10.0, 3.2 * len(pairs) + 0.6), layout="constrained")
    axes = figure.subplots(len(pairs), len(metrics), squeeze=False)
    styles = dict(zip(map(id, plain), run_styles(plain), strict=True))
    for row, pair in enumerate(pairs):
        for column, (key, label) in enumerate(metrics):
            ax = axes[row][column]
            for run in pair:
                first = next((p for p in run.summary["curve"] if key in p), None)
                seeds = len(first[key]["per_seed"]) if first else 0
                _draw_curve(ax, run, key, styles[id(run)], f"{run.cfg.algo} ({seeds} seeds)")
            for reference in references or []:
                ax.axhline(reference[key], color="black", linestyle="--", linewidth=1,
                           label=yardstick_name(env, reference["target_speed"]))  # fmt: skip
            ax.set_title(f"{curve_label(label)} (IQM, 95 % CI)")
            ax.set_xlabel("environment steps per seed")
            format_step_axis(ax)
            ax.grid(alpha=0.3)
    _legend_below(figure, axes.ravel())
    figure.suptitle(f"{env}: each explainable agent against its baseline")
    return figure
