"""A run's results from its folder's records: every seed's final evaluation and, over seeds, the IQM
with its 95 % stratified bootstrap confidence interval (:mod:`xrl_jax.stats`), the paper's protocol,
at the end and at every evaluation step. A hyper-parameter sweep (``--sweep``) is summarised per
sweep point, over that point's seeds, never over points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from xrl_jax import stats
from xrl_jax.config import scenario
from xrl_jax.runs.folder import eval_file, member_stem, metrics_file, read_rows


def summary_metrics(env: str) -> tuple[tuple[str, str], ...]:
    """The (key, label) pairs reported over seeds for ``env``."""
    return scenario(env).summary_metrics


def _member_stems(cfg) -> list[str]:
    """The file stem of every member (point-major): ``seed_<s>``, or ``point_<p>_seed_<s>`` in a sweep."""
    return [member_stem(cfg, member) for member in range(cfg.num_members)]


def _member_evaluations(out: Path, cfg) -> list[dict[int, dict]]:
    """Per member (point-major; in a plain run, per seed), its evaluation rows by step (the last row
    of a step wins: a resumed run rewrites)."""
    return [
        {r["step"]: r for r in read_rows(eval_file(out, stem)) if "step" in r} for stem in _member_stems(cfg)
    ]


def _aggregate(scores: np.ndarray) -> dict[str, Any]:
    """IQM with its 95 % stratified bootstrap CI over seeds, the interval's actual coverage at this
    many seeds (:func:`~xrl_jax.stats.iqm_interval_coverage`), the mean and the number of seeds."""
    interval = stats.stratified_bootstrap_ci(scores, stats.iqm, confidence=0.95)
    coverage = stats.iqm_interval_coverage(int(scores.size), interval.confidence)
    return {**interval.as_dict(), "coverage": coverage, "mean": float(scores.mean()), "n": int(scores.size)}


def aggregate_metrics(rows: list[dict], env: str) -> dict[str, Any]:
    """:func:`_aggregate` of every summary metric over ``rows`` (one per seed); non-finite ones skipped."""
    result = {}
    for key, _ in summary_metrics(env):
        scores = np.array([row.get(key, np.nan) for row in rows], np.float64)
        if np.all(np.isfinite(scores)):
            result[key] = _aggregate(scores)
    return result


def learning_curve(out: str | Path, cfg, point: int | None = None) -> list[dict[str, Any]]:
    """The evaluation curve over seeds: at every evaluation step that all seeds reached, each summary
    metric's IQM, 95 % stratified bootstrap CI, mean and per-seed values. A sweep has one curve per
    point: pass ``point`` (curves never mix points)."""
    evaluations = _member_evaluations(Path(out), cfg)
    if point is None:
        if cfg.num_points > 1:
            raise ValueError(
                f"a sweep has one learning curve per point; pass point= (0..{cfg.num_points - 1})"
            )
        point = 0
    if not 0 <= point < cfg.num_points:
        raise ValueError(f"point {point} is not in 0..{cfg.num_points - 1}")
    return curve_over_seeds([evaluations[m] for m in cfg.point_members(point)], cfg.env)


def curve_over_seeds(evaluations: list[dict[int, dict]], env: str) -> list[dict[str, Any]]:
    """:func:`learning_curve` of evaluation rows by step, one dict per seed."""
    steps = sorted(set.intersection(*(set(rows) for rows in evaluations))) if evaluations else []
    curve = []
    for step in steps:
        rows = [by_step[step] for by_step in evaluations]
        point = {"step": step, **aggregate_metrics(rows, env)}
        for key in point:
            if key != "step":
                point[key]["per_seed"] = [float(row[key]) for row in rows]
        curve.append(point)
    return curve


# Per evaluation metric, the rollout metric of the metrics lines that measures the same of the training
# episodes (each seed's last 100 finished, xrl_jax.train.episodes), on a single-agent scenario.
TRAINING_METRICS = {
    "avg_return": "rollout/avg_episode_return",
    "avg_etr": "rollout/early_termination_rate",
    "avg_episode_length": "rollout/avg_episode_length",
}


def training_curve(out: str | Path, cfg) -> dict[str, tuple[list[int], list[float]]]:
    """The training episodes' curve of a plain run: per evaluation metric with a rollout counterpart
    (:data:`TRAINING_METRICS`), ``(steps, means)``, the mean over seeds at every metrics line (every
    ``log_interval`` steps) where all seeds have a value; a seed has none before its first episode
    ends. Empty for a sweep (one curve per point). The caller knows whether the training episodes
    score what the evaluation does (not on the Intersection: one car's against the whole scene's)."""
    if cfg.num_points > 1:
        return {}
    rows = [
        {r["step"]: r for r in read_rows(metrics_file(Path(out), stem)) if "step" in r}
        for stem in _member_stems(cfg)
    ]
    steps = sorted(set.intersection(*(set(by_step) for by_step in rows))) if rows else []
    curves = {}
    for key, rollout in TRAINING_METRICS.items():
        points = []
        for step in steps:
            values = [by_step[step].get(rollout) for by_step in rows]
            if all(isinstance(v, int | float) and np.isfinite(v) for v in values):
                points.append((step, float(np.mean(values))))
        if points:
            curves[key] = ([step for step, _ in points], [value for _, value in points])
    return curves


# What every record says about its member (run_folder.member_fields): in a plain run "point" is 0
# and "sweep" is {}, which the summary leaves out so that it reads as before sweeps existed.
_SWEEP_RECORD_FIELDS = ("point", "sweep")


def summarize_run(out: str | Path, cfg) -> dict[str, Any]:
    """Final evaluation of every seed and, over seeds, the IQM with its 95 % stratified bootstrap CI;
    ``curve`` holds the same statistics at every evaluation step (:func:`learning_curve`).

    A sweep (``cfg.num_points > 1``) is summarised per point, never over points: top-level
    ``aggregate`` is ``{}`` and ``curve`` is ``[]``; ``seeds`` lists the member stems
    (``point_<p>_seed_<s>``) with a final evaluation, ``complete`` says whether every member has one,
    ``per_seed`` (and ``training_tracks``) are keyed by member stem, and ``sweep`` holds
    ``{"fields": [name, ...], "points": [{"point": p, "values": {name: value}, "seeds": [seed with a
    final evaluation], "complete": bool, "aggregate": {...}, "curve": [...]}, ...]}`` with
    ``aggregate`` and ``curve`` as in a plain run, over that point's seeds.
    """
    out = Path(out)
    summary = _header(cfg) | _over_members(_member_evaluations(out, cfg), cfg)
    if cfg.scenario.on_tracks:
        summary["training_tracks"] = _training_tracks(out, cfg)
    return summary


def pooled_config(parts: list[tuple[str | Path, Any]]):
    """The config of runs ``(folder, cfg)`` of one protocol pooled: the seeds of them all; for pieces
    of one sweep (each some of its values, from its own base seed), the grid of every value any piece
    swept, with as many seeds per point as the fullest point has (a point fewer pieces trained then
    reads as incomplete). Pieces must sweep the same fields."""
    first = parts[0][1]
    if not first.sweep:
        return first.replace(num_seeds=sum(cfg.num_seeds for _, cfg in parts))
    fields = [name for name, _ in first.sweep]
    if any([name for name, _ in cfg.sweep] != fields for _, cfg in parts):
        raise ValueError("pieces of one sweep must sweep the same fields")
    swept = {name: {value for _, cfg in parts for value in dict(cfg.sweep)[name]} for name in fields}
    merged = first.replace(sweep=tuple((name, tuple(sorted(swept[name]))) for name in fields), num_seeds=1)
    per_point = [sum(parts[i][1].num_seeds for i in _pieces_at(parts, p)) for p in merged.sweep_points]
    return merged.replace(num_seeds=max(per_point))


def _pieces_at(parts: list[tuple[str | Path, Any]], values: dict[str, float]) -> list[int]:
    """The indices of the pieces ``(folder, cfg)`` that swept the point ``values``."""
    return [index for index, (_, cfg) in enumerate(parts) if values in cfg.sweep_points]


def summarize_pooled(parts: list[tuple[str | Path, Any]]) -> dict[str, Any]:
    """Runs ``(folder, cfg)`` of one protocol, each trained from its own base seed (say one session's
    seeds and the next's), summarised as one run of :func:`pooled_config` over all their seeds, as
    :func:`summarize_run` would summarise one run of them all: seed ``k`` of the pool (of a sweep
    point) is the ``k``-th seed in the order given. Which seeds trained on which tracks
    (``training_tracks``) is left out."""
    cfg = pooled_config(parts)
    pieces = [_member_evaluations(Path(out), part) for out, part in parts]
    if not cfg.sweep:
        evaluations = [rows for piece in pieces for rows in piece]
    else:
        evaluations = []
        for values in cfg.sweep_points:
            here = []
            for i in _pieces_at(parts, values):
                piece_cfg = parts[i][1]
                point = piece_cfg.sweep_points.index(values)
                here += [pieces[i][member] for member in piece_cfg.point_members(point)]
            evaluations += here + [{}] * (cfg.num_seeds - len(here))  # seeds no piece trained here
    return _header(cfg) | _over_members(evaluations, cfg)


def _over_members(evaluations: list[dict[int, dict]], cfg) -> dict[str, Any]:
    """The summary's results from every member's evaluations (point-major), per point in a sweep."""
    if cfg.num_points == 1:
        return _over_seeds(evaluations, cfg)
    final, stems = cfg.total_steps, _member_stems(cfg)
    finished = [m for m, rows in enumerate(evaluations) if final in rows]
    points = []
    for point, values in enumerate(cfg.sweep_points):
        members = cfg.point_members(point)
        finals = [evaluations[m][final] for m in members if final in evaluations[m]]
        points.append({
            "point": point,
            "values": dict(values),
            "seeds": [cfg.member_point_seed(m)[1] for m in members if final in evaluations[m]],
            "complete": len(finals) == cfg.num_seeds,
            "aggregate": aggregate_metrics(finals, cfg.env) if finals else {},
            "curve": curve_over_seeds([evaluations[m] for m in members], cfg.env),
        })  # fmt: skip
    return {
        "seeds": [stems[m] for m in finished],
        "complete": len(finished) == cfg.num_members,
        "per_seed": {
            stems[m]: _per_seed_row(evaluations[m][final], cfg.member_point_seed(m)) for m in finished
        },
        "aggregate": {},  # over points it would mix hyper-parameters: see sweep.points[i].aggregate
        "curve": [],  # likewise: sweep.points[i].curve
        "sweep": {"fields": [name for name, _ in cfg.sweep], "points": points},
    }


def _header(cfg) -> dict[str, Any]:
    return {"env": cfg.env, "algo": cfg.algo, "preset": cfg.preset, "steps": cfg.total_steps}


def _over_seeds(evaluations: list[dict[int, dict]], cfg) -> dict[str, Any]:
    """The plain run's part of the summary: each seed's final evaluation, their aggregate, the curve."""
    final = cfg.total_steps
    finals = {seed: rows[final] for seed, rows in enumerate(evaluations) if final in rows}
    return {
        "seeds": sorted(finals),
        "complete": len(finals) == cfg.num_seeds,
        "per_seed": {str(s): _per_seed_row(r, (0, s), drop=_SWEEP_RECORD_FIELDS) for s, r in finals.items()},
        "aggregate": aggregate_metrics([finals[s] for s in sorted(finals)], cfg.env) if finals else {},
        "curve": curve_over_seeds(evaluations, cfg.env),
    }


def _per_seed_row(row: dict, member: tuple[int, int], drop: tuple[str, ...] = ()) -> dict:
    """``row`` without its per-episode values, its point and seed those of ``member`` (point, seed) in
    the summary (in a pool, not the piece's own); ``drop``: fields left out."""
    point, seed = member
    row = {k: v for k, v in row.items() if k != "episode_returns"} | {"point": point, "seed": seed}
    return {k: v for k, v in row.items() if k not in drop}


def _training_tracks(out: Path, cfg) -> dict[str, Any]:
    """What the seeds trained on: a fixed bank, or fresh tracks with each seed's count of distinct
    tracks driven and of resets that found its feed empty (from its last metrics line), keyed by
    seed (``"0"``) in a plain run and by member stem (``"point_0_seed_0"``) in a sweep."""
    if cfg.train_tracks > 0:  # a run on tracks: a fixed bank, or fresh tracks with train_tracks 0
        return {"fresh": False, "bank": cfg.train_tracks}
    used, reused = {}, {}
    for member, stem in enumerate(_member_stems(cfg)):
        key = str(cfg.member_point_seed(member)[1]) if cfg.num_points == 1 else stem
        rows = [r for r in read_rows(metrics_file(out, stem)) if "rollout/tracks_used" in r]
        if rows:
            used[key] = int(rows[-1]["rollout/tracks_used"])
            reused[key] = int(rows[-1]["rollout/tracks_reused"])
    return {"fresh": True, "distinct_per_seed": used, "reused_per_seed": reused}
