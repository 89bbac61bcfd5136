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

from xrl_jax.comparisons import improvements, interval_paragraph, sweep_comparisons, verdict
from xrl_jax.config import BASELINES
from xrl_jax.evaluation import evaluate_yardstick, has_yardstick
from xrl_jax.report_figures import (
    ALGO_ORDER,
    env_figure,
    pairs_figure,
    table_metrics,
    yardstick_name,
)
from xrl_jax.runs.folder import RunFolderError, first_nonfinite_metric, read_run_config, run_paths
from xrl_jax.runs.kept import distinct_runs, keep_records, protocol_groups
from xrl_jax.runs.plots import plot_sweep
from xrl_jax.runs.summary import pooled_config, summarize_pooled, summarize_run, summary_metrics
from xrl_jax.train.kinds import scenario_kind

PAPER_RESULTS = Path(__file__).resolve().parents[1] / "docs" / "paper_results.json"


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
    """The runs of ``folders``, with the runs of one protocol that each started from their own base
    seed, or trained other values of one sweep, pooled into one (:func:`~xrl_jax.runs.kept.protocol_groups`,
    :func:`~xrl_jax.runs.summary.summarize_pooled`); ``note`` takes a line about every pool."""
    runs = []
    for parts in protocol_groups([(folder, _read_config(folder)) for folder in folders], note):
        if len(parts) == 1:
            ((folder, cfg),) = parts
            runs.append(Run((folder,), cfg, summarize_run(folder, cfg)))
        else:
            pooled = tuple(folder for folder, _ in parts)
            runs.append(Run(pooled, pooled_config(parts), summarize_pooled(parts)))
    return runs


def paper_values() -> dict[tuple[str, str, str], dict]:
    """The paper's published numbers by (env, algo, metric) (docs/paper_results.json)."""
    data = json.loads(PAPER_RESULTS.read_text())
    return {(r["env"], r["algo"], r["metric"]): r for r in data["results"]}


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


EARLY_FRACTION = 0.25  # "early stages of training" (Fig. 7): the evaluation nearest a quarter of the run


def write_report(
    folders: list[str | Path],
    out: str | Path,
    controller_speed: float | None = None,
    controller: bool = False,
    early_fraction: float = EARLY_FRACTION,
    note=None,
    policy_costs=None,
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
    a run or ``out`` cannot be written. With runs of the paper's Table I (XSAC on continuous Country
    Road with its weights from hidden layer φ_d, beside SAC), ``policy_costs`` (an ``AgentConfig`` ->
    parameters and FLOPs per action, :func:`xrl_jax.benchmarks.table_one.policy_costs`) gives the
    table's costs beside the returns."""
    controller = controller or controller_speed is not None
    out = Path(out)
    _make_report_folder(out)
    runs = read_runs(distinct_runs(folders, note), note)
    try:
        keep_records([folder for run in runs for folder in run.folders], out)
        return _write_report(runs, out, controller_speed, controller, early_fraction, policy_costs)
    except OSError as err:  # a folder that turned unwritable, a full disk
        raise ReportError(f"cannot write the report into {out}: {err.strerror or err}") from None


def _make_report_folder(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise ReportError(f"--out {out} is a file; give a folder for the report")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ReportError(f"cannot create the report folder --out {out}: {err.strerror or err}") from None


def ending_rows(runs: list[Run], env: str) -> list[dict[str, str]]:
    """Why and where each plain run's final-evaluation episodes end, a mean over the seeds whose final
    evaluation records it: on the racing scenarios the share of episodes that left the track, hit the
    time limit, idled out or sent an invalid action, and the distance driven along the track at the
    end (m, ``avg_end_*``, :func:`xrl_jax.evaluation.summarize_episodes`); on the Intersection the
    cars per episode that completed their trip, left the road or collided (the scenario kind's
    :attr:`~xrl_jax.train.kinds.base.ScenarioKind.endings`). Empty where none does."""
    columns = scenario_kind(env).endings
    if not columns:  # a user's env: its evaluation records no ending
        return []
    rows = []
    plain = [r for r in runs if r.cfg.env == env and not r.is_sweep]
    for run in sorted(plain, key=lambda r: (ALGO_ORDER.index(r.cfg.algo), r.cfg.preset, r.name)):
        recorded = [
            row for row in run.summary["per_seed"].values() if all(key in row for _, key, _ in columns)
        ]
        if not recorded:
            continue
        row = {"agent": run.label, "seeds": str(len(recorded))}
        for label, key, decimals in columns:
            value = float(np.mean([seed_row[key] for seed_row in recorded]))
            row[label] = f"{value:.{decimals}f}"
        rows.append(row)
    return rows


# The paper's Table I: continuous Country Road, SAC against XSAC with its weights from each layer.
TABLE_ONE = ("country_road", ("sac", "xsac"))


def table_one_rows(runs: list[Run], policy_costs=None) -> list[dict[str, str]]:
    """The paper's Table I at the runs' scale: SAC and every XSAC run on continuous Country Road, by
    preset, each with its final return (IQM [95 % CI]) and, with ``policy_costs``, its actor's
    parameters and FLOPs per action (as run, and on every cone slot); the paper's numbers beside
    the runs of its protocol. Empty unless some XSAC run takes its weights from an earlier layer
    (``weight_depth``), which is what makes the table."""
    env, algos = TABLE_ONE
    plain = [r for r in runs if r.cfg.env == env and not r.is_sweep and r.cfg.algo in algos]
    if not any(r.cfg.algo == "xsac" and r.cfg.agent.weight_depth is not None for r in plain):
        return []
    published_rows = json.loads(PAPER_RESULTS.read_text())["table_1_country_road_continuous"]
    paper = {row.get("weight_depth"): row for row in published_rows}  # the baseline has none

    def depth(run: Run) -> int | None:
        return None if run.cfg.algo == "sac" else (run.cfg.agent.weight_depth or run.cfg.agent.actor_depth)

    rows = []
    for run in sorted(plain, key=lambda r: (r.cfg.preset, depth(r) or 0, r.name)):
        d = depth(run)
        row = {"model": "SAC (baseline)" if d is None else f"XSAC, weights from hidden layer {d}",
               "preset": run.cfg.preset, "seeds": f"{len(run.summary['seeds'])}/{run.cfg.num_seeds}",
               "final return": _cell(run.summary["aggregate"].get("avg_return"))}  # fmt: skip
        if policy_costs is not None:
            costs = policy_costs(run.cfg.agent)
            row["parameters"] = f"{costs['params']:,}"
            row["FLOPs per action (as run)"] = f"{costs['flops_as_run']:,.0f}"
            row["FLOPs per action (every slot)"] = f"{costs['flops_xla']:,.0f}"
        published = paper.get(d) if run.cfg.preset == "paper" else None
        row["paper: final return"] = f"{published['return_iqm']:.2f}" if published else "-"
        row["paper: parameters"] = f"{published['params']:,}" if published else "-"
        row["paper: FLOPs per action"] = f"{published['flops']:,}" if published else "-"
        rows.append(row)
    return rows


def explanation_rows(runs: list[Run]) -> list[dict[str, str]]:
    """One row per run folder with explanation statistics (``explain.py --stats``): the explanation's
    size and step-to-step change, how alike the seeds are, where the weight goes by object kind, and
    the deletion curves against random order (mean over k > 0, mean over seeds [95 % CI]); by scenario,
    then agent as the results tables, so that the order does not depend on the folders' order."""
    rows = []
    for run in sorted(runs, key=lambda r: (r.cfg.env, ALGO_ORDER.index(r.cfg.algo), r.name)):
        for folder in run.folders:
            path = run_paths(folder)["explain_stats"] / "stats.json"
            if not path.is_file():
                continue
            stats = json.loads(path.read_text())
            row = {"agent": f"{run.cfg.algo} ({folder.name})", "seeds": str(stats["seeds"])}
            if "size" in stats:
                kinds = sorted(
                    zip(stats["kinds"], stats["kind"]["share"], strict=True), key=lambda k: -k[1]["estimate"]
                )
                alike = stats["agreement"]["mean_similarity_between_seeds"]
                by_kind = ", ".join(f"{k} {s['estimate']:.2f}" for k, s in kinds)
                row |= {"objects for 90 %": _interval_cell(stats["size"]["mean"]),
                        "step-to-step TV": _interval_cell(stats["stability"]["mean_change"], 3),
                        "seeds alike (1 - TV)": f"{alike:.2f}", "weight by kind": by_kind}  # fmt: skip
            rankings = stats.get("deletion", {}).get("against_random", {})
            if rankings:
                row["deleting the top-ranked objects, against random"] = "; ".join(
                    f"by {ranker.replace('_', ' ')}: " + ", ".join(map(_difference_cell, differences.items()))
                    for ranker, differences in rankings.items()
                )
            rows.append(row)
    header = [key for key in EXPLANATION_COLUMNS if any(key in row for row in rows)]
    return [{key: row.get(key, "-") for key in header} for row in rows]


EXPLANATION_COLUMNS = ("agent", "seeds", "objects for 90 %", "step-to-step TV", "seeds alike (1 - TV)",
                       "weight by kind", "deleting the top-ranked objects, against random")  # fmt: skip


def _difference_cell(item: tuple[str, dict]) -> str:
    name, interval = item
    return f"{name.replace('_', ' ')} {_interval_cell(interval, 3 if name == 'tv' else 2, sign=True)}"


def _interval_cell(interval: dict, digits: int = 2, sign: bool = False) -> str:
    form = f"{'+' if sign else ''}.{digits}f"
    return f"{interval['estimate']:{form}} [{interval['low']:{form}}, {interval['high']:{form}}]"


def _write_report(
    runs: list[Run], out: Path, controller_speed, controller: bool, early_fraction: float, policy_costs=None
) -> Path:
    lines = ["# Results report", "",
             "IQM with its 95 % stratified bootstrap CI over seeds (final evaluation). The paper's value "
             "stands beside a run that used its protocol (`--preset paper`); other presets are shorter "
             "runs and are not comparable with it. Source of the paper's numbers: docs/paper_results.json.",
             "", *interval_paragraph(runs), ""]  # fmt: skip
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
        endings = ending_rows(runs, env)
        if endings:
            unit = scenario_kind(env).ending_unit
            lines += [f"How the final evaluation's episodes end ({unit}; mean over seeds; from runs whose "
                      "evaluations record it):", "", markdown_table(endings), ""]  # fmt: skip
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
            test = f"Mann-Whitney p = {item['p_value']:.2g}{verdict(item['p_value'])}"
            held = 100 * item["coverage_without_difference"]
            held = f"the interval holds 0.5 without a difference {held:.0f} %"
            lines.append(f"- P({item['x']} > {item['y']}) on {metric}, {when}: {interval} "
                         f"({seeds}; {test}; {held})")  # fmt: skip
        finished = [r for r in runs if r.cfg.env == env and not r.is_sweep and r.summary["aggregate"]]
        for run in (r for r in runs if r.cfg.env == env and r.is_sweep):
            baseline = next((b for b in finished if b.cfg.algo == BASELINES.get(run.cfg.algo)), None)
            path = out / f"sweep_{'+'.join(folder.name for folder in run.folders)}.png"  # a link: no spaces
            if run.summary["sweep"]["points"] and any(p["aggregate"] for p in run.summary["sweep"]["points"]):
                plot_sweep(run.summary, path, baseline.summary if baseline else None)
                lines += ["", f"Sweep {run.label}: {run.status()}", "", f"![sweep]({path.name})", ""]
                lines += [f"- {line}" for line in sweep_comparisons(run, baseline)]
        lines.append("")
    table_one = table_one_rows(runs, policy_costs)
    if table_one:
        (out / "table_one.md").write_text(markdown_table(table_one) + "\n")
        lines += ["## Table I: where the mixture weights come from", "",
                  "XSAC with its mixture weights taken from hidden layer φ_d (docs/algorithms.md §3.7: the "
                  "layers up to φ_d run for every cone, the rest for the sampled one only), beside SAC, on "
                  "continuous Country Road. FLOPs per action are XLA's count of one action's computation "
                  "(xrl_jax/benchmarks/table_one.py): as run, on the present cones packed, and on every "
                  "cone slot (the paper's count).", "", markdown_table(table_one), ""]  # fmt: skip
    explained = explanation_rows(runs)
    if explained:
        lines += ["## Explanations over the evaluation", "",
                  "From `explain.py --stats` (xrl_jax/explain/run_statistics.py): the fewest objects that "
                  "carry 90 % of the weight, IQM over seeds [95 % CI]; the weight's step-to-step change, "
                  "following each object (total variation); the seeds' weights on the same observations; the "
                  "share of the weight per object kind. Deletion curves: removing the objects ranked first "
                  "from every observation against removing as many at random: the difference in the "
                  "policy's change (TV) and in the evaluation's metrics (mean over 1-8 objects removed; mean "
                  "over seeds [95 % CI]).", "",
                  markdown_table(explained), ""]  # fmt: skip
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
