"""The run summary of a hyper-parameter sweep: per-point statistics over that point's seeds only,
incomplete members, the table and the sweep figure; a plain run's summary as before sweeps. Fake
run folders written by hand: no training, no jit."""

import json
import re

import numpy as np
import pytest

from xrl_jax import stats
from xrl_jax.config import parse_sweep, resolve_config
from xrl_jax.runs.folder import member_fields, member_stem
from xrl_jax.runs.plots import plot_learning_curve, plot_sweep, sweep_x_scale
from xrl_jax.runs.summary import learning_curve, summarize_run
from xrl_jax.runs.tables import format_curve, format_table, format_training_tracks

PNG = b"\x89PNG\r\n\x1a\n"
KAPPAS = [-0.01, 0.0, 0.1]


def sweep_config(num_seeds=4, sweep=("kappa=-0.01,0,0.1",), overrides=None):
    sweep = parse_sweep(list(sweep))
    return resolve_config(
        "country_road", "xdsac", "smoke", num_seeds=num_seeds, overrides=overrides, sweep=sweep
    )


def final_return(point, seed):
    # Every point's scores sit far from the others', so a mix of points would show at once.
    return 100.0 * point + [3.0, 1.0, 7.0, 50.0][seed % 4]


def write_run(out, cfg, skip=(), final_steps=None):
    """Eval files of every member (but ``skip``): a first evaluation at step 64 and, unless the
    member is in ``final_steps`` (which stop at 64), a final one."""
    (out / "eval").mkdir(parents=True, exist_ok=True)
    (out / "metrics").mkdir(exist_ok=True)
    for member in range(cfg.num_members):
        if member in skip:
            continue
        point, seed = cfg.member_point_seed(member)
        fields = member_fields(cfg, member)
        rows = [{"step": 64, **fields, "avg_return": -1.0 - seed, "avg_etr": 1.0, "avg_episode_length": 5.0}]
        if final_steps is None or member not in final_steps:
            rows.append({
                "step": cfg.total_steps, **fields,
                "avg_return": final_return(point, seed), "avg_etr": 0.1 * point + 0.01 * seed,
                "avg_episode_length": 10.0 + seed, "avg_sr": 0.5, "episode_returns": [1.0, 2.0],
            })  # fmt: skip
        stem = member_stem(cfg, member)
        (out / "eval" / f"{stem}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        metrics = {"step": 64, **fields, "rollout/tracks_used": 10 + member, "rollout/tracks_reused": member}
        (out / "metrics" / f"{stem}.jsonl").write_text(json.dumps(metrics) + "\n")


def expected_interval(scores):
    scores = np.array(scores, np.float64)
    ci = stats.stratified_bootstrap_ci(scores, stats.iqm, confidence=0.95)
    coverage = stats.iqm_interval_coverage(scores.size)
    return {**ci.as_dict(), "coverage": coverage, "mean": float(scores.mean()), "n": int(scores.size)}


def test_each_point_is_summarised_over_its_own_seeds_only(tmp_path):
    cfg = sweep_config()
    write_run(tmp_path, cfg)
    summary = summarize_run(tmp_path, cfg)
    assert summary["complete"] and summary["aggregate"] == {} and summary["curve"] == []
    assert {"env", "algo", "preset", "steps", "training_tracks"} <= set(summary)
    stems = [f"point_{p}_seed_{s}" for p in range(3) for s in range(4)]
    assert summary["seeds"] == stems and sorted(summary["per_seed"]) == sorted(stems)
    row = summary["per_seed"]["point_2_seed_1"]
    assert (
        row["avg_return"] == final_return(2, 1)
        and row["sweep"] == {"kappa": 0.1}
        and "episode_returns" not in row
    )
    sweep = summary["sweep"]
    assert sweep["fields"] == ["kappa"] and [p["point"] for p in sweep["points"]] == [0, 1, 2]
    for p, point in enumerate(sweep["points"]):
        assert (
            point["values"] == {"kappa": KAPPAS[p]} and point["seeds"] == [0, 1, 2, 3] and point["complete"]
        )
        returns = [final_return(p, s) for s in range(4)]
        assert point["aggregate"]["avg_return"] == expected_interval(returns)
        assert point["aggregate"]["avg_return"]["estimate"] == pytest.approx(100.0 * p + 5.0)  # mean(3, 7)
        assert point["aggregate"]["avg_etr"] == expected_interval([0.1 * p + 0.01 * s for s in range(4)])
        assert [c["step"] for c in point["curve"]] == [64, cfg.total_steps]
        assert point["curve"][-1]["avg_return"]["per_seed"] == returns
        assert point["curve"] == learning_curve(tmp_path, cfg, point=p)
    with pytest.raises(ValueError, match="one learning curve per point"):
        learning_curve(tmp_path, cfg)


def test_a_missing_member_makes_its_point_and_the_run_incomplete(tmp_path):
    cfg = sweep_config()
    missing = 1 * cfg.num_seeds + 2  # point 1, seed 2: no file at all
    stopped = 2 * cfg.num_seeds + 0  # point 2, seed 0: no final evaluation yet
    write_run(tmp_path, cfg, skip={missing}, final_steps={stopped})
    summary = summarize_run(tmp_path, cfg)
    assert not summary["complete"]
    assert "point_1_seed_2" not in summary["seeds"] and "point_2_seed_0" not in summary["seeds"]
    points = summary["sweep"]["points"]
    assert [p["complete"] for p in points] == [True, False, False]
    assert points[1]["seeds"] == [0, 1, 3] and points[2]["seeds"] == [1, 2, 3]
    assert points[1]["aggregate"]["avg_return"] == expected_interval([final_return(1, s) for s in (0, 1, 3)])
    assert points[1]["curve"] == []  # a seed without any evaluation: no step all seeds reached
    assert [c["step"] for c in points[2]["curve"]] == [64]
    table = format_table(summary)
    assert "3*" in table and "not every seed" in table
    assert plot_sweep(summary, tmp_path / "sweep.png").read_bytes()[:8] == PNG


def test_an_empty_sweep_folder_summarises_without_crashing(tmp_path):
    cfg = sweep_config(num_seeds=2)
    summary = summarize_run(tmp_path, cfg)
    assert not summary["complete"] and summary["seeds"] == [] and summary["per_seed"] == {}
    assert all(
        p["aggregate"] == {} and p["curve"] == [] and p["seeds"] == [] for p in summary["sweep"]["points"]
    )
    assert len(format_table(summary).splitlines()) == 2 + 3 + 2  # title, header, points, footnote, tracks
    assert format_curve(summary).count("\n") == 1 + 3
    assert plot_sweep(summary, tmp_path / "sweep.png").read_bytes()[:8] == PNG
    assert plot_learning_curve(summary, tmp_path / "curves.png").read_bytes()[:8] == PNG


def _summary_before_sweeps(out, cfg):
    """summarize_run as it was before sweeps (commit 655a59d), the reference for plain runs."""
    from xrl_jax.runs.folder import read_rows as read_jsonl
    from xrl_jax.runs.summary import aggregate_metrics, curve_over_seeds

    evaluations = [
        {r["step"]: r for r in read_jsonl(out / "eval" / f"seed_{seed}.jsonl") if "step" in r}
        for seed in range(cfg.num_seeds)
    ]
    finals = {seed: rows[cfg.total_steps] for seed, rows in enumerate(evaluations) if cfg.total_steps in rows}
    used, reused = {}, {}
    for seed in range(cfg.num_seeds):
        rows = [r for r in read_jsonl(out / "metrics" / f"seed_{seed}.jsonl") if "rollout/tracks_used" in r]
        if rows:
            used[str(seed)] = int(rows[-1]["rollout/tracks_used"])
            reused[str(seed)] = int(rows[-1]["rollout/tracks_reused"])
    tracks = {"fresh": True, "distinct_per_seed": used, "reused_per_seed": reused}
    return {
        "env": cfg.env,
        "algo": cfg.algo,
        "preset": cfg.preset,
        "steps": cfg.total_steps,
        "seeds": sorted(finals),
        "complete": len(finals) == cfg.num_seeds,
        "per_seed": {
            str(s): {k: v for k, v in r.items() if k != "episode_returns"} for s, r in finals.items()
        },
        "aggregate": aggregate_metrics([finals[s] for s in sorted(finals)], cfg.env) if finals else {},
        "curve": curve_over_seeds(evaluations, cfg.env),
        "training_tracks": tracks if cfg.fresh_tracks else {"fresh": False, "bank": cfg.train_tracks},
    }


@pytest.mark.parametrize("train_tracks", [3, 0])  # a fixed bank, fresh tracks
def test_a_plain_run_summary_is_unchanged(tmp_path, train_tracks):
    cfg = resolve_config(
        "country_road", "xdsac", "smoke", num_seeds=4, overrides={"train_tracks": str(train_tracks)}
    )
    assert cfg.num_points == 1 and member_stem(cfg, 2) == "seed_2"
    write_run(tmp_path / "old", cfg, skip={1}, final_steps={3})
    # The same run as the new trainer writes it: every record also says point 0 and sweep {}.
    old_rows = (tmp_path / "old" / "eval" / "seed_0.jsonl").read_text()
    assert '"point": 0' in old_rows and '"sweep": {}' in old_rows
    for name in ("eval", "metrics"):
        (tmp_path / "bare" / name).mkdir(parents=True)
        for path in (tmp_path / "old" / name).iterdir():
            rows = [json.loads(line) for line in path.read_text().splitlines()]
            bare = [{k: v for k, v in r.items() if k not in ("point", "sweep")} for r in rows]
            (tmp_path / "bare" / name / path.name).write_text("".join(json.dumps(r) + "\n" for r in bare))
    reference = _summary_before_sweeps(tmp_path / "bare", cfg)
    assert reference["training_tracks"]["fresh"] == (train_tracks == 0)
    for folder in ("bare", "old"):
        summary = summarize_run(tmp_path / folder, cfg)
        assert json.dumps(summary, sort_keys=True) == json.dumps(reference, sort_keys=True)
        assert "sweep" not in summary
    assert format_table(summary).splitlines()[1].startswith("metric")


def test_fresh_track_counts_are_kept_per_member(tmp_path):
    cfg = sweep_config(num_seeds=2, overrides={"train_tracks": "0"})
    write_run(tmp_path, cfg)
    summary = summarize_run(tmp_path, cfg)
    tracks = summary["training_tracks"]
    assert tracks["fresh"] and tracks["distinct_per_seed"]["point_2_seed_1"] == 10 + 5
    assert len(tracks["reused_per_seed"]) == cfg.num_members
    assert "distinct per member (min 10, max 15); 15 resets" in format_training_tracks(summary)


def test_the_table_has_one_row_per_point_with_its_values(tmp_path):
    cfg = sweep_config()
    write_run(tmp_path, cfg)
    summary = summarize_run(tmp_path, cfg)
    lines = format_table(summary).splitlines()
    assert "kappa" in lines[1] and "final return" in lines[1] and "early-termination rate" in lines[1]
    rows = lines[2:5]
    for p, (kappa, row) in enumerate(zip(KAPPAS, rows, strict=True)):
        cells = row.split()
        assert float(cells[0]) == kappa and cells[-1] == "4"
        assert f"{100.0 * p + 5.0:.3f} [" in row
    assert "training tracks: a fixed bank of" in lines[-1]
    curve = format_curve(summary)
    assert curve.count("kappa=") == 3 and "summary.json" in curve


def test_the_intersection_table_uses_its_first_two_metrics(tmp_path):
    cfg = resolve_config("intersection", "xdsac", "smoke", num_seeds=2, sweep=parse_sweep(["kappa=0,0.1"]))
    (tmp_path / "eval").mkdir()
    for member in range(cfg.num_members):
        metrics = {"avg_trips_completed": 2.0, "avg_early_terminations": 0.0, "avg_mean_velocity": 3.0}
        row = {"step": cfg.total_steps, **member_fields(cfg, member), "avg_return": 1.0 + member, **metrics}
        (tmp_path / "eval" / f"{member_stem(cfg, member)}.jsonl").write_text(json.dumps(row) + "\n")
    summary = summarize_run(tmp_path, cfg)
    assert "training_tracks" not in summary and summary["complete"]
    header = format_table(summary).splitlines()[1]
    assert "final return (all agents)" in header and "completed trips" in header
    assert plot_sweep(summary, tmp_path / "sweep.png").stat().st_size > 0


def test_plot_sweep_with_and_without_a_baseline(tmp_path):
    cfg = sweep_config()
    write_run(tmp_path / "sweep", cfg)
    summary = summarize_run(tmp_path / "sweep", cfg)
    plain = resolve_config("country_road", "dsac", "smoke", num_seeds=4)
    write_run(tmp_path / "dsac", plain)
    baseline = summarize_run(tmp_path / "dsac", plain)
    without = plot_sweep(summary, tmp_path / "sweep.png")
    with_baseline = plot_sweep(summary, tmp_path / "sweep_baseline.png", baseline=baseline)
    for png in (without, with_baseline):
        assert png.read_bytes()[:8] == PNG and png.stat().st_size > 1000
    assert with_baseline.read_bytes() != without.read_bytes()
    curves = plot_learning_curve(summary, tmp_path / "curves.png")
    assert curves.read_bytes()[:8] == PNG
    with pytest.raises(ValueError, match="sweep"):
        plot_sweep(baseline, tmp_path / "no.png")


def test_a_two_field_sweep_plots_one_line_per_other_value(tmp_path):
    cfg = sweep_config(num_seeds=2, sweep=("kappa=-0.01,0,0.1", "gamma=0.9,0.99"))
    write_run(tmp_path, cfg)
    summary = summarize_run(tmp_path, cfg)
    assert summary["sweep"]["fields"] == ["kappa", "gamma"] and len(summary["sweep"]["points"]) == 6
    assert summary["sweep"]["points"][3]["values"] == {"kappa": 0.0, "gamma": 0.99}
    table = format_table(summary)
    assert len(table.splitlines()) == 2 + 6 + 1 + 1  # title, header, points, coverage, tracks
    # The interval's coverage at the points' 2 seeds: [lowest, highest], 1 - 2 * 0.5**2 = 50 %, by a
    # Monte Carlo of 2,000 trials (4 standard errors: 4.5 points; tests/test_stats.py).
    (held,) = re.findall(r"at 2 seeds (\d+) %", table)
    assert abs(int(held) - 50) <= 5
    assert plot_sweep(summary, tmp_path / "sweep.png").read_bytes()[:8] == PNG


@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ([-0.01, -0.001, 0.0, 0.001, 0.01, 0.1], ("symlog", 0.001)),
        ([0.0, 0.001, 0.1], ("symlog", 0.001)),
        ([-0.01, 0.0, 0.01], ("linear", None)),  # one order of magnitude: linear reads fine
        ([0.9, 0.95, 0.99], ("linear", None)),
        ([0.001, 0.01, 0.1], ("log", None)),  # positive, two orders of magnitude: learning rates
        ([0.01, 0.02, 0.05], ("linear", None)),
        ([-0.1, -0.01, -0.001], ("linear", None)),  # negative only: no log axis
        ([0.0], ("linear", None)),
    ],
)
def test_the_x_scale_is_logarithmic_only_across_orders_of_magnitude(values, expected):
    assert sweep_x_scale(values) == expected
