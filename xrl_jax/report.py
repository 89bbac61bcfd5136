"""The report over many result folders: a results table per env with the paper's published numbers
beside ours, final-performance panels and learning curves per env (the paper's Fig. 5-7), the κ
sweep (Fig. 8), and the probability that each explainable agent improves on its baseline.

Everything is read from the folders' records (``config.json``, ``eval/``), so a folder that is still
running or lost a seed is reported as far as it goes, and says so. The report keeps a copy of those
records (``runs/<folder>``, ~30 kB for 4 seeds and 20 evaluations), so that it can be written again,
or with another run added, after the run folders themselves are gone.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from xrl_jax import stats
from xrl_jax.config import scenario
from xrl_jax.evaluation import evaluate_yardstick, has_yardstick
from xrl_jax.runs.folder import RunFolderError, first_nonfinite_metric, read_run_config
from xrl_jax.runs.kept import distinct_runs, keep_records, protocol_groups
from xrl_jax.runs.plots import format_step_axis, plot_sweep
from xrl_jax.runs.summary import summarize_pooled, summarize_run, summary_metrics
from xrl_jax.runs.tables import curve_label
from xrl_jax.train.kinds import scenario_kind

PAPER_RESULTS = Path(__file__).resolve().parents[1] / "docs" / "paper_results.json"
BASELINES = {"xsac": "sac", "xdsac": "dsac"}  # each explainable agent against the agent it extends
ALGO_ORDER = ("sac", "xsac", "dsac", "xdsac")


class ReportError(ValueError):
    """A folder that is not a run, or a report folder that cannot be written; the message is one line."""


@dataclass(frozen=True)
class Run:
    """One result folder as the report sees it, or several runs of one protocol pooled (:func:`read_runs`)."""

    folders: tuple[Path, ...]
    cfg: Any  # of the first folder; num_seeds counts the seeds of them all
    summary: dict

    @property
    def name(self) -> str:
        return " + ".join(folder.name for folder in self.folders)

    @property
    def label(self) -> str:
        return f"{self.cfg.algo} ({self.cfg.preset}, {self.name})"

    @property
    def is_sweep(self) -> bool:
        return self.cfg.num_points > 1

    def final_scores(self, metric: str) -> np.ndarray:
        """Every seed's final value of ``metric`` (seeds without a final evaluation left out)."""
        rows = self.summary["per_seed"].values()
        return np.array([row[metric] for row in rows if metric in row], np.float64)

    def status(self) -> str:
        """'complete', or what is missing (a run still going, a lost seed), and where it diverged."""
        cfg, done = self.cfg, len(self.summary["seeds"])
        if self.summary["complete"]:
            return "complete"
        missing = f"{done} of {cfg.num_members} seeds have their final evaluation"
        diverged = min(filter(None, map(first_nonfinite_metric, self.folders)), default=None)
        return f"diverged: {diverged}; {missing}" if diverged else f"incomplete: {missing}"


def read_run(folder: str | Path) -> Run:
    """A results folder's config and its summary, recomputed from the records."""
    (run,) = read_runs([Path(folder)])
    return run


def _read_config(folder: Path):
    try:
        return read_run_config(folder)
    except RunFolderError as err:
        raise ReportError(str(err)) from None


def read_runs(folders: list[Path], note=None) -> list[Run]:
    """The runs of ``folders``, with the plain runs of one protocol that each started from their own
    base seed pooled into one (:func:`~xrl_jax.runs.kept.protocol_groups`,
    :func:`~xrl_jax.runs.summary.summarize_pooled`); ``note`` takes a line about every pool."""
    runs = []
    for parts in protocol_groups([(folder, _read_config(folder)) for folder in folders], note):
        if len(parts) == 1:
            ((folder, cfg),) = parts
            runs.append(Run((folder,), cfg, summarize_run(folder, cfg)))
        else:
            cfg = parts[0][1].replace(num_seeds=sum(c.num_seeds for _, c in parts))
            runs.append(Run(tuple(folder for folder, _ in parts), cfg, summarize_pooled(parts)))
    return runs


def paper_values() -> dict[tuple[str, str, str], dict]:
    """The paper's published numbers by (env, algo, metric) (docs/paper_results.json)."""
    data = json.loads(PAPER_RESULTS.read_text())
    return {(r["env"], r["algo"], r["metric"]): r for r in data["results"]}


def table_metrics(env: str) -> tuple[tuple[str, str], ...]:
    """The (key, label) pairs of ``env``'s table; the first two are its figure's (the paper's Fig. 5/6:
    return and early-termination rate; on the Intersection Fig. 7's trips and early terminations)."""
    return scenario(env).table_metrics


def yardstick_name(env: str, speed: float) -> str:
    return f"{scenario(env).yardstick} ({speed:g} m/s)"


def _cell(agg: dict | None) -> str:
    return f"{agg['estimate']:.2f} [{agg['low']:.2f}, {agg['high']:.2f}]" if agg else "-"


def _paper_cell(value: dict | None) -> str:
    if value is None:
        return "-"
    ci = f" [{value['ci'][0]:.2f}, {value['ci'][1]:.2f}]" if value["ci"] else ""
    return f"{value['iqm']:.2f}{ci}"


def results_rows(runs: list[Run], env: str) -> list[dict[str, str]]:
    """The table of one env: a row per plain run (sweeps have their own figure), ordered by agent;
    the paper's value beside ours only where the run used the paper's protocol."""
    published = paper_values()
    published_envs = {published_env for published_env, _, _ in published}
    metrics = table_metrics(env)
    rows = []
    plain = [r for r in runs if r.cfg.env == env and not r.is_sweep]
    for run in sorted(plain, key=lambda r: (ALGO_ORDER.index(r.cfg.algo), r.cfg.preset, r.name)):
        row = {
            "agent": run.cfg.algo,
            "preset": run.cfg.preset,
            "steps": f"{run.cfg.total_steps:,}",
            "seeds": f"{len(run.summary['seeds'])}/{run.cfg.num_seeds}",
            "folder": run.name,
        }
        for key, label in metrics:
            row[label] = _cell(run.summary["aggregate"].get(key))
            if env not in published_envs:  # a user's env: the paper has no value to stand beside it
                continue
            same_protocol = run.cfg.preset == "paper"
            row[f"paper: {label}"] = _paper_cell(
                published.get((env, run.cfg.algo, key)) if same_protocol else None
            )
        row["status"] = run.status()
        rows.append(row)
    return rows


def controller_rows(
    runs: list[Run], env: str, target_speed: float | None = None
) -> tuple[list[dict[str, str]], list[dict]]:
    """The yardstick's rows of ``env``'s table and its results, one per evaluation the env's plain
    runs used (normally one): its mean over the evaluation's episodes (a deterministic driver has no
    seeds to take an IQM over). Racing: the hand controller of docs/carenv-single-agent.md §8.3 on
    the runs' held-out tracks; Intersection: the scripted driver of :mod:`envs.intersection_driver`
    on the runs' evaluation episodes. ``target_speed`` None is the driver's own default."""
    metrics = table_metrics(env)
    seeded = scenario_kind(env).seeded_evaluation  # the Intersection's episodes are fixed: no seed
    track_sets = sorted({(r.cfg.eval_track_seed if seeded else None, r.cfg.eval_episodes) for r in runs
                         if r.cfg.env == env and not r.is_sweep}, key=str)  # fmt: skip
    rows, results = [], []
    for seed, episodes in track_sets:
        result = evaluate_yardstick(env, seed, episodes, target_speed)
        where = {"eval_track_seed": seed, "episodes": episodes} if seeded else {"episodes": episodes}
        results.append({"env": env, **where, **result})
        seeds = f"{episodes} tracks (seed {seed})" if seeded else f"{episodes} episodes"
        row = {"agent": yardstick_name(env, result["target_speed"]), "preset": "-", "steps": "-",
               "seeds": seeds, "folder": "-"}  # fmt: skip
        for key, label in metrics:
            row[label] = f"{result[key]:.2f} (mean)"
            row[f"paper: {label}"] = "-"
        row["status"] = "complete"
        rows.append(row)
    return rows, results


def markdown_table(rows: list[dict[str, str]]) -> str:
    if not rows:
        return "(no runs)"
    header = list(rows[0])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row[h] for h in header) + " |" for row in rows]
    return "\n".join(lines)


def csv_table(rows: list[dict[str, str]]) -> str:
    out = io.StringIO()
    if rows:
        writer = csv.DictWriter(out, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return out.getvalue()


def improvement_metrics(env: str) -> tuple[str, ...]:
    """The metrics P(explainable > baseline) is taken on: return; on the Intersection, Fig. 7's
    completed trips and early terminations (there a value below 0.5 favours the explainable agent)."""
    return scenario(env).improvement_keys


def _scores_at(run: Run, metric: str, step: int | None) -> np.ndarray:
    """Every seed's ``metric`` at evaluation ``step`` (None: the final one); empty where not all
    seeds have reached the step."""
    if step is None:
        return run.final_scores(metric)
    point = next((p for p in run.summary["curve"] if p["step"] == step and metric in p), None)
    return np.array(point[metric]["per_seed"] if point else [], np.float64)


def early_step(x: Run, y: Run, fraction: float) -> int | None:
    """The evaluation step both runs have that lies nearest ``fraction`` of the way through x's run
    (the 'early stage of training' of Fig. 7); None if they share no evaluation step."""
    shared = sorted({p["step"] for p in x.summary["curve"]} & {p["step"] for p in y.summary["curve"]})
    if not shared:
        return None
    return min(shared, key=lambda step: (abs(step - fraction * x.cfg.total_steps), step))


def improvements(
    runs: list[Run], env: str, metric: str | None = None, early_fraction: float | None = None
) -> list[dict[str, Any]]:
    """P(X > Y) with its 95 % bootstrap CI of each explainable agent X against its baseline Y, for
    every pair of complete-enough plain runs of ``env`` with the same preset, on each seed's final
    ``metric`` (default: each of :func:`improvement_metrics`) and, with ``early_fraction``, also at the shared
    evaluation step nearest that fraction of the run (:func:`early_step`; ``"step"`` in the record)."""
    metrics = (metric,) if metric else improvement_metrics(env)
    plain = [r for r in runs if r.cfg.env == env and not r.is_sweep]
    out = []
    for x in plain:
        for y in plain:
            if BASELINES.get(x.cfg.algo) != y.cfg.algo or x.cfg.preset != y.cfg.preset:
                continue
            early = None if early_fraction is None else early_step(x, y, early_fraction)
            for name in metrics:
                for step in [early, None] if early is not None else [None]:
                    xs, ys = _scores_at(x, name, step), _scores_at(y, name, step)
                    if xs.size == 0 or ys.size == 0:
                        continue
                    interval = stats.probability_of_improvement_ci(xs, ys)
                    out.append({"x": x.label, "y": y.label, "metric": name, "step": step or "final",
                                **interval.as_dict(), "seeds": [int(xs.size), int(ys.size)]})  # fmt: skip
    return out


def _plain_runs(runs: list[Run], env: str) -> list[Run]:
    """The env's runs that are not sweeps and have a learning curve: the ones the figures draw."""
    return [r for r in runs if r.cfg.env == env and not r.is_sweep and r.summary["curve"]]


def _draw_curve(ax, run: Run, key: str, colour: str, label: str) -> None:
    """``run``'s curve of ``key``: IQM line, 95 % CI band, markers (a one-point curve shows too)."""
    points = [p for p in run.summary["curve"] if key in p]
    steps = [p["step"] for p in points]
    ax.plot(steps, [p[key]["estimate"] for p in points], color=colour, marker="o", markersize=3, label=label)
    ax.fill_between(steps, [p[key]["low"] for p in points], [p[key]["high"] for p in points],
                    color=colour, alpha=0.2, linewidth=0)  # fmt: skip


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
    figure = Figure(figsize=(10.0, 6.5), layout="constrained")
    axes = figure.subplots(2, 2)
    for column, (key, label) in enumerate(metrics):
        bars, curves = axes[0][column], axes[1][column]
        names = []  # the agents with a final evaluation (an unfinished run has a curve only)
        for index, (run, label_of_run) in enumerate(zip(plain, labels, strict=True)):
            colour = f"C{index}"
            agg = run.summary["aggregate"].get(key)
            if agg:
                error = [[agg["estimate"] - agg["low"]], [agg["high"] - agg["estimate"]]]
                bars.errorbar(agg["estimate"], len(names), xerr=error, fmt="o", capsize=4, color=colour)
                names.append(label_of_run)
            _draw_curve(curves, run, key, colour, label_of_run)
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
    axes[1][0].legend(fontsize="small")
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
    figure = Figure(figsize=(10.0, 3.2 * len(pairs)), layout="constrained")
    axes = figure.subplots(len(pairs), len(metrics), squeeze=False)
    for row, pair in enumerate(pairs):
        for column, (key, label) in enumerate(metrics):
            ax = axes[row][column]
            for colour, run in zip(("C0", "C3"), pair, strict=True):
                first = next((p for p in run.summary["curve"] if key in p), None)
                seeds = len(first[key]["per_seed"]) if first else 0
                _draw_curve(ax, run, key, colour, f"{run.cfg.algo} ({seeds} seeds)")
            for reference in references or []:
                ax.axhline(reference[key], color="black", linestyle="--", linewidth=1,
                           label=yardstick_name(env, reference["target_speed"]))  # fmt: skip
            ax.set_title(f"{curve_label(label)} (IQM, 95 % CI)")
            ax.set_xlabel("environment steps per seed")
            format_step_axis(ax)
            ax.grid(alpha=0.3)
            ax.legend(fontsize="small")
    figure.suptitle(f"{env}: each explainable agent against its baseline")
    return figure


EARLY_FRACTION = 0.25  # "early stages of training" (Fig. 7): the evaluation nearest a quarter of the run


def write_report(
    folders: list[str | Path],
    out: str | Path,
    controller_speed: float | None = None,
    controller: bool = False,
    early_fraction: float = EARLY_FRACTION,
    note=None,
) -> Path:
    """Read ``folders`` and write ``out``/report.md with the tables (``results_<env>.md/.csv``), figures
    (``<env>.png``, ``sweep_<folder>.png``) and improvement probabilities (``improvement.json``, at
    the end and at the evaluation nearest ``early_fraction`` of the run), and the records it read
    (``runs/``, :func:`~xrl_jax.runs.kept.keep_records`); returns the path of report.md. With
    ``controller`` or a ``controller_speed`` (m/s; None: each driver's default), the tables and
    figures also show each scenario's yardstick driven on the runs' evaluation (``controller.json``):
    the hand controller on the racing tracks, the scripted driver on the Intersection. A folder given
    twice, or also as a report's copy of its records, is reported once (``note`` takes a line about
    it; :func:`~xrl_jax.runs.kept.distinct_runs`); :class:`ReportError` (one line) when a folder is not
    a run or ``out`` cannot be written."""
    controller = controller or controller_speed is not None
    out = Path(out)
    _make_report_folder(out)
    runs = read_runs(distinct_runs(folders, note), note)
    try:
        keep_records([folder for run in runs for folder in run.folders], out)
        return _write_report(runs, out, controller_speed, controller, early_fraction)
    except OSError as err:  # a folder that turned unwritable, a full disk
        raise ReportError(f"cannot write the report into {out}: {err.strerror or err}") from None


def _make_report_folder(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise ReportError(f"--out {out} is a file; give a folder for the report")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ReportError(f"cannot create the report folder --out {out}: {err.strerror or err}") from None


def _write_report(
    runs: list[Run], out: Path, controller_speed, controller: bool, early_fraction: float
) -> Path:
    lines = ["# Results report", "",
             "IQM with its 95 % stratified bootstrap CI over seeds (final evaluation). The paper's value "
             "stands beside a run that used its protocol (`--preset paper`); other presets are shorter "
             "runs and are not comparable with it. Source of the paper's numbers: docs/paper_results.json.",
             ""]  # fmt: skip
    all_improvements, all_references = [], []
    for env in sorted({r.cfg.env for r in runs}):
        lines += [f"## {env}", ""]
        rows = results_rows(runs, env)
        references = []
        if controller and has_yardstick(env):  # a user's env has none
            reference_rows, references = controller_rows(runs, env, controller_speed)
            rows += reference_rows
            all_references += references
        (out / f"results_{env}.md").write_text(markdown_table(rows) + "\n")
        (out / f"results_{env}.csv").write_text(csv_table(rows))
        lines += [markdown_table(rows), ""]
        figure = env_figure(runs, env, references)
        if figure is not None:
            figure.savefig(out / f"{env}.png", dpi=110)
            lines += [f"![{env}]({env}.png)", ""]
        if scenario_kind(env).pairs_figure:  # the paper's Fig. 7: learning curves of each pair
            pairs = pairs_figure(runs, env, references)
            if pairs is not None:
                pairs.savefig(out / f"{env}_pairs.png", dpi=110)
                lines += [f"![{env}: pairs]({env}_pairs.png)", ""]
        found = improvements(runs, env, early_fraction=early_fraction)
        all_improvements += found
        labels = dict(summary_metrics(env))
        for item in found:
            interval = f"{item['estimate']:.2f} [{item['low']:.2f}, {item['high']:.2f}]"
            seeds = f"{item['seeds'][0]} vs {item['seeds'][1]} seeds"
            when = "final evaluation" if item["step"] == "final" else f"evaluation at step {item['step']:,}"
            metric = labels[item["metric"]].removeprefix("final ")
            lines.append(f"- P({item['x']} > {item['y']}) on {metric}, {when}: {interval} ({seeds})")
        finished = [r for r in runs if r.cfg.env == env and not r.is_sweep and r.summary["aggregate"]]
        for run in (r for r in runs if r.cfg.env == env and r.is_sweep):
            baseline = next((b for b in finished if b.cfg.algo == BASELINES.get(run.cfg.algo)), None)
            path = out / f"sweep_{run.name}.png"
            if run.summary["sweep"]["points"] and any(p["aggregate"] for p in run.summary["sweep"]["points"]):
                plot_sweep(run.summary, path, baseline.summary if baseline else None)
                lines += ["", f"Sweep {run.label}: {run.status()}", "", f"![sweep]({path.name})"]
        lines.append("")
    (out / "improvement.json").write_text(json.dumps(all_improvements, indent=2) + "\n")
    if controller:
        lines += ["The hand controller (docs/carenv-single-agent.md §8.3) follows the centre line at a "
                  "target speed; the scripted Intersection driver (envs/intersection_driver.py) follows "
                  "its route, slows for turns and gives way to a car that reaches a crossing point first. "
                  "Their values are means over the evaluation's tracks or episodes.", ""]  # fmt: skip
        (out / "controller.json").write_text(json.dumps(all_references, indent=2) + "\n")
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    return report
