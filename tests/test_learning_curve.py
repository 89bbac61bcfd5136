"""The learning curve's figure: the evaluations' IQM and CI, the training episodes' lighter line, and
the scenario's yardstick (xrl_jax.runs.references) as a labelled line where it was measured on the
run's evaluation; none for another evaluation or a user's env."""

import json
from pathlib import Path

import pytest
from train_support import fast_env_registered

from xrl_jax.runs.plots import learning_curve_figure, plot_learning_curve
from xrl_jax.runs.references import MEASURED_YARDSTICKS, measured_yardstick
from xrl_jax.runs.summary import training_curve
from xrl_jax.train import resolve_config

CONTROLLER_FILE = Path(__file__).resolve().parents[1] / "docs" / "results_quick" / "controller.json"


def point(step: int, per_seed: dict[str, list[float]]) -> dict:
    """A curve point as summarize_run writes it (the IQM of two seeds is their mean)."""
    stats = {}
    for key, v in per_seed.items():
        stats[key] = {"estimate": sum(v) / 2, "low": min(v), "high": max(v), "mean": sum(v) / 2, "n": 2}
        stats[key]["per_seed"] = v
    return {"step": step} | stats


def quick_start_summary() -> dict:
    """The README's quick start (2 seeds, 80k steps): evaluations at 40k and 80k only."""
    curve = [
        point(
            40_000, {"avg_return": [20.0, 30.0], "avg_etr": [0.5, 0.3], "avg_episode_length": [300.0, 40.0]}
        ),
        point(
            80_000, {"avg_return": [40.0, 44.0], "avg_etr": [0.2, 0.1], "avg_episode_length": [500.0, 50.0]}
        ),
    ]
    return {"env": "tracking", "algo": "xdsac", "preset": "quick", "steps": 80_000, "curve": curve}


def labelled_lines(ax) -> dict[str, object]:
    return {line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")}


def test_the_curve_draws_the_hand_controller_and_the_training_episodes(tmp_path):
    cfg = resolve_config("tracking", "xdsac", "quick", num_seeds=2, total_steps=80_000)
    reference = measured_yardstick(cfg)
    assert reference is MEASURED_YARDSTICKS["tracking"]
    training = {"avg_return": ([1_000, 2_000, 40_000, 80_000], [1.0, 2.0, 25.0, 38.0])}
    figure = learning_curve_figure(quick_start_summary(), reference=reference, training=training)
    returns, etr = figure.axes
    lines = labelled_lines(returns)
    assert set(lines) == {"IQM", "hand controller 36.86", "training episodes (seeds' mean)"}
    assert list(lines["hand controller 36.86"].get_ydata()) == [36.86, 36.86]
    assert list(lines["training episodes (seeds' mean)"].get_xdata()) == [1_000, 2_000, 40_000, 80_000]
    assert {t.get_text() for t in returns.get_legend().get_texts()} == set(lines) | {"95 % CI"}
    assert set(labelled_lines(etr)) == {"IQM", "hand controller 0.06"}  # no training line given for it
    png = plot_learning_curve(quick_start_summary(), tmp_path / "curve.png", reference=reference)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_no_yardstick_line_without_one_measured_on_the_runs_evaluation():
    tracking = resolve_config("tracking", "xdsac", "quick")
    assert measured_yardstick(tracking.replace(eval_track_seed=7)) is None  # other tracks
    assert measured_yardstick(tracking.replace(eval_episodes=20)) is None
    assert measured_yardstick(resolve_config("intersection", "xdsac", "smoke")) is None  # 2 episodes
    driver = measured_yardstick(resolve_config("intersection", "xdsac", "quick"))  # its 10 episodes
    assert driver.label("avg_trips_completed") == "scripted driver 26.20"
    with fast_env_registered() as name:
        cfg = resolve_config(name, "xdsac", "smoke")
        assert measured_yardstick(cfg) is None  # a user's env has no yardstick
        summary = quick_start_summary() | {"env": name}
        for point_ in summary["curve"]:
            point_["avg_terminated"] = point_.pop("avg_etr")
        figure = learning_curve_figure(summary, reference=measured_yardstick(cfg))
    for ax in figure.axes:
        assert set(labelled_lines(ax)) == {"IQM"}
        assert all(line.get_linestyle() != "--" for line in ax.get_lines())


def test_the_measured_values_are_those_of_the_committed_measurement():
    """docs/results_quick/controller.json (report.py --controller) holds the measurement; the package
    keeps its values rounded to the 2 decimals the docs quote, so they agree within 0.005."""
    measured = {row["env"]: row for row in json.loads(CONTROLLER_FILE.read_text())}
    assert set(measured) == set(MEASURED_YARDSTICKS)
    for env, kept in MEASURED_YARDSTICKS.items():
        row = measured[env]
        assert (row["episodes"], row.get("eval_track_seed"), row["target_speed"]) == (
            kept.episodes, kept.eval_track_seed, kept.speed,
        )  # fmt: skip
        for key, value in kept.scores.items():
            assert value == pytest.approx(row[key], abs=0.005), (env, key)


def test_the_training_curve_is_the_seeds_mean_where_all_have_a_value(tmp_path):
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2)
    (tmp_path / "metrics").mkdir()
    rows = {
        0: [(64, 1.0, 0.5), (128, 2.0, 0.5), (192, 4.0, 0.0)],
        1: [(64, None, None), (128, 3.0, 1.0), (192, "nan", 0.5)],  # no episode yet; then not finite
    }
    for seed, lines in rows.items():
        text = "".join(
            json.dumps({"step": s, "rollout/avg_episode_return": ret, "rollout/early_termination_rate": e})
            + "\n"
            for s, ret, e in lines
        )
        (tmp_path / "metrics" / f"seed_{seed}.jsonl").write_text(text)
    curves = training_curve(tmp_path, cfg)
    assert curves == {"avg_return": ([128], [2.5]), "avg_etr": ([128, 192], [0.75, 0.25])}
    # The Intersection's training episodes are one car's, its evaluation scores the scene: not drawn.
    from xrl_jax.train.kinds import scenario_kind

    assert not scenario_kind(
        resolve_config("intersection", "xdsac", "smoke")
    ).training_episodes_like_evaluation
    assert scenario_kind(cfg).training_episodes_like_evaluation
