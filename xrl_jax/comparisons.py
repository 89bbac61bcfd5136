"""What the runs of a report say against each other: P(X > Y) of each explainable agent against its
baseline with the Mann-Whitney U test behind it, the points of a sweep against the baseline and
against its best point, and a paragraph on what the printed intervals cover (xrl_jax.stats)."""

from __future__ import annotations

from typing import Any

import numpy as np

from xrl_jax import stats
from xrl_jax.config import BASELINES, scenario
from xrl_jax.runs.folder import member_stem
from xrl_jax.runs.tables import coverage_note, point_label

Run = Any  # xrl_jax.report.Run (a run's cfg, summary and label); that module sits above this one


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
    """P(X > Y) with its 95 % bootstrap CI, the Mann-Whitney U test's two-sided p-value (``p_value``) and
    the share of samples without a difference whose interval holds 0.5 at these seed counts
    (``coverage_without_difference``), of each explainable agent X against its baseline Y, for
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
                    held = stats.improvement_interval_coverage(int(xs.size), int(ys.size))
                    out.append({"x": x.label, "y": y.label, "metric": name, "step": step or "final",
                                **interval.as_dict(), "seeds": [int(xs.size), int(ys.size)],
                                "p_value": stats.improvement_test(xs, ys),
                                "coverage_without_difference": held})  # fmt: skip
    return out


def interval_paragraph(runs: list[Run]) -> list[str]:
    """What the report's intervals are and what they cover at the seed counts of ``runs``."""
    aggregates = [agg for run in runs if not run.is_sweep for agg in run.summary["aggregate"].values()]
    aggregates += [agg for run in runs if run.is_sweep for point in run.summary["sweep"]["points"]
                   for agg in point["aggregate"].values()]  # fmt: skip
    note = coverage_note(aggregates)
    if note is None:
        return []
    return [
        f"{note} (`xrl_jax.stats.iqm_interval_coverage`: below 5 seeds the interval is [lowest, highest "
        "seed] and holds the median 1 - 2^(1-n) of the time). P(X > Y) is the chance that a seed of X "
        "beats a seed of Y, with its percentile bootstrap interval (X's and Y's seeds resampled apart); "
        "beside it the two-sided Mann-Whitney U test's p-value (exact over every split of the seeds up to "
        "20,000 splits), the test behind any \"difference\" said here, and the share of samples without a "
        "difference whose interval holds 0.5 at those seed counts."
    ]


def _point_scores(run: Run, point: int, metric: str) -> np.ndarray:
    """Final ``metric`` of every seed of sweep point ``point`` that has its final evaluation."""
    stems = {member_stem(run.cfg, m) for m in run.cfg.point_members(point)}
    rows = [row for stem, row in run.summary["per_seed"].items() if stem in stems]
    return np.array([row[metric] for row in rows if metric in row], np.float64)


def sweep_comparisons(run: Run, baseline: Run | None, metric: str = "avg_return") -> list[str]:
    """One line per point of sweep ``run`` on its final ``metric``: P(point > baseline) with its interval
    and the Mann-Whitney p (the paper's Fig. 8 reading: is any value significantly below the
    baseline?), then the point with the highest IQM against every other point (is the best one
    better with significance?). Points without final evaluations are left out."""
    points = run.summary["sweep"]["points"]
    scores = {p["point"]: _point_scores(run, p["point"], metric) for p in points}
    scores = {p: s for p, s in scores.items() if s.size}
    names = {p["point"]: point_label(p["values"]) for p in points}
    lines = []
    base = baseline.final_scores(metric) if baseline is not None else np.array([])
    for point, values in scores.items():
        if base.size:
            interval = stats.probability_of_improvement_ci(values, base)
            p_value = stats.improvement_test(values, base)
            lines.append(f"{names[point]}: P(> {baseline.cfg.algo}) = {interval.estimate:.2f} "
                         f"[{interval.low:.2f}, {interval.high:.2f}] ({values.size} vs {base.size} seeds; "
                         f"Mann-Whitney p = {p_value:.2g}{verdict(p_value)})")  # fmt: skip
    if len(scores) > 1:
        best = max(scores, key=lambda p: stats.iqm(scores[p]))
        against = ", ".join(f"{names[p]} p = {stats.improvement_test(scores[best], s):.2g}"
                            f"{verdict(stats.improvement_test(scores[best], s))}"
                            for p, s in scores.items() if p != best)  # fmt: skip
        lines.append(f"best IQM: {names[best]}; against every other point (Mann-Whitney): {against}")
    return lines


def verdict(p_value: float) -> str:
    """What a report adds to a p-value: only below 0.05 is a difference called one."""
    return ", a difference at the 5 % level" if p_value < 0.05 else ""
