"""Evaluation protocol (docs/algorithms.md §6.1) with scripted drivers of known outcome, and the run
summary."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from train_support import prepare_cache

from xrl_jax import stats
from xrl_jax.evaluation import make_evaluate, summarize_episodes
from xrl_jax.evaluation.protocol import empty_record, record_step
from xrl_jax.runs.plots import format_step_axis, plot_learning_curve
from xrl_jax.runs.summary import learning_curve, summarize_run
from xrl_jax.runs.tables import format_curve, format_table
from xrl_jax.train import make_envs, resolve_config


class ScriptedAgent:
    """Stands in for an agent: the 'agent state' is the one action every env takes."""

    def act(self, key, state, obs, mode="train"):
        assert mode == "eval"
        return jnp.broadcast_to(state, (obs["state"].shape[0], 3))


@pytest.fixture(scope="module")
def scripted_evaluate(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    cfg = resolve_config("tracking", "sac", "smoke")
    env, _, eval_params = make_envs(cfg)
    return jax.jit(make_evaluate(env, eval_params, ScriptedAgent(), cfg.eval_episodes))


def test_a_car_that_never_moves_idles_out_after_51_steps(scripted_evaluate):
    # No throttle, full brake: truncated at step 51 (Idling), return 0 (docs/carenv-single-agent.md §3.3).
    episodes = jax.device_get(scripted_evaluate(jax.random.PRNGKey(0), jnp.array([0.0, -1.0, 1.0])))
    np.testing.assert_array_equal(episodes["length"], [51, 51, 51])
    np.testing.assert_array_equal(episodes["return"], [0.0, 0.0, 0.0])
    assert episodes["truncated"].all() and not episodes["terminated"].any()
    summary = summarize_episodes(episodes)
    assert summary["avg_etr"] == 0.0 and summary["avg_sr"] == 0.0 and summary["avg_episode_length"] == 51
    assert summary["avg_end_idling"] == 1.0 and summary["avg_end_left_track"] == 0.0  # why it ended


def test_full_throttle_straight_ahead_leaves_the_track(scripted_evaluate):
    # docs/carenv-single-agent.md §8.3: straight at full throttle leaves the track after a few dozen steps.
    episodes = jax.device_get(scripted_evaluate(jax.random.PRNGKey(0), jnp.array([0.0, 1.0, -1.0])))
    assert episodes["terminated"].all() and not episodes["truncated"].any()
    assert (episodes["length"] > 10).all() and (episodes["length"] < 200).all()
    np.testing.assert_array_equal(episodes["last_reward"], [-1.0, -1.0, -1.0])  # off-track overwrite
    # The return is the progress reward before leaving, then -1.
    assert (episodes["return"] > -1.0).all()
    summary = summarize_episodes(episodes)
    assert summary["avg_etr"] == 1.0 and summary["avg_sr"] == 0.0
    # Why and where: every episode left the track, after driving some way along it.
    assert summary["avg_end_left_track"] == 1.0 and summary["avg_end_time_limit"] == 0.0
    assert (episodes["progress"] > 0).all() and summary["avg_end_progress_m"] == pytest.approx(
        float(np.mean(episodes["progress"]))
    )


def test_an_ended_episode_keeps_its_record_while_the_others_step_on():
    # Two steps of three episodes: the first terminates at step 1, the third is truncated at step 2.
    no, yes = False, True
    a = jnp.array
    record = empty_record(3, floats=("progress",), ints=("cones_hit",))
    first = {"progress": a([5.0, 6.0, 7.0]), "cones_hit": a([1, 1, 1])}
    rewards, terminated, truncated = a([1.0, 2.0, 3.0]), a([yes, no, no]), a([no, no, no])
    record = record_step(record, a([no, no, no]), rewards, terminated, truncated, **first)
    second = {"progress": a([8.0, 9.0, 10.0]), "cones_hit": a([4, 5, 6])}
    rewards, terminated, truncated = a([10.0, 20.0, 30.0]), a([no, no, no]), a([no, no, yes])
    record = record_step(record, a([yes, no, no]), rewards, terminated, truncated, **second)
    np.testing.assert_array_equal(record["return"], [1.0, 22.0, 33.0])
    np.testing.assert_array_equal(record["length"], [1, 2, 2])
    np.testing.assert_array_equal(record["terminated"], [yes, no, no])
    np.testing.assert_array_equal(record["truncated"], [no, no, yes])
    np.testing.assert_array_equal(record["last_reward"], [1.0, 20.0, 30.0])
    np.testing.assert_array_equal(record["progress"], [5.0, 9.0, 10.0])
    np.testing.assert_array_equal(record["cones_hit"], [1, 5, 6])
    assert record["length"].dtype == jnp.int32 and record["cones_hit"].dtype == jnp.int32


def test_episode_classification_closed_form():
    episodes = {
        "return": np.array([1.0, 2.0, 3.0, 4.0]),
        "length": np.array([10, 20, 30, 40]),
        "terminated": np.array([True, True, False, False]),
        "truncated": np.array([False, False, True, True]),
        "last_reward": np.array([-1.0, 0.2, -1.0, 0.1]),  # only a terminated ending can be early
        "track_velocity": np.array([1.0, 2.0, 3.0, 4.0]),
        "cones_hit": np.array([0, 1, 2, 3]),
        "done_reason": np.array([1, 4, 2, 2]),  # left the track, an invalid action, two time limits
        "progress": np.array([10.0, 20.0, 30.0, 60.0]),
    }
    summary = summarize_episodes(episodes)
    assert (summary["avg_end_left_track"], summary["avg_end_invalid_action"]) == (0.25, 0.25)
    assert (summary["avg_end_time_limit"], summary["avg_end_idling"]) == (0.5, 0.0)
    assert summary["avg_end_progress_m"] == 30.0
    assert summary["avg_return"] == 2.5
    assert summary["avg_episode_length"] == 25.0
    assert summary["avg_etr"] == 0.25 and summary["avg_sr"] == 0.25
    assert summary["avg_cones_hit"] == 1.5
    assert summary["episode_returns"] == [1.0, 2.0, 3.0, 4.0]


def test_summary_reports_iqm_and_bootstrap_ci_over_seeds(tmp_path):
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=5)
    finals = [10.0, 0.0, 30.0, 20.0, 100.0]
    (tmp_path / "eval").mkdir()
    for seed, score in enumerate(finals):
        rows = [
            {"step": 64, "avg_return": -5.0, "avg_etr": 1.0, "avg_episode_length": 1.0},
            {"step": cfg.total_steps, "avg_return": score, "avg_etr": seed / 10, "avg_episode_length": 100.0},
        ]
        text = "".join(json.dumps(r) + "\n" for r in rows) + '{"step": 1'  # a line cut by a crash
        (tmp_path / "eval" / f"seed_{seed}.jsonl").write_text(text)
    summary = summarize_run(tmp_path, cfg)
    assert summary["complete"] and summary["seeds"] == [0, 1, 2, 3, 4]
    agg = summary["aggregate"]["avg_return"]
    # IQM of 5 values trims floor(5/4) = 1 each side: mean(10, 20, 30) = 20.
    assert agg["estimate"] == pytest.approx(20.0)
    assert agg["mean"] == pytest.approx(32.0) and agg["n"] == 5
    expected = stats.stratified_bootstrap_ci(np.array(finals), stats.iqm, confidence=0.95)
    assert (agg["low"], agg["high"]) == (expected.low, expected.high)
    assert agg["low"] <= 20.0 <= agg["high"]
    assert summary["aggregate"]["avg_etr"]["estimate"] == pytest.approx(0.2)
    table = format_table(summary)
    assert "final return" in table and "20.000" in table and "early-termination rate" in table


def test_learning_curve_aggregates_every_step_all_seeds_reached(tmp_path):
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=4)
    (tmp_path / "eval").mkdir()
    returns = {64: [1.0, 2.0, 3.0, 40.0], 128: [5.0, 6.0, 7.0, 8.0], 192: [9.0, 10.0, 11.0, 12.0]}
    for seed in range(4):
        steps = (64, 128, 128, 192) if seed < 3 else (64, 128)  # seed 3 stopped early; 128 rewritten once
        rows = []
        for i, step in enumerate(steps):
            stale = seed < 3 and step == 128 and i == 1  # rewritten after a resume: the last row wins
            value = -100.0 if stale else returns[step][seed]
            rows.append({"step": step, "avg_return": value, "avg_etr": 0.5, "avg_episode_length": 10.0})
        (tmp_path / "eval" / f"seed_{seed}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    curve = learning_curve(tmp_path, cfg)
    assert [p["step"] for p in curve] == [64, 128]  # 192 is missing for seed 3
    # IQM of 4 values drops one at each end: mean(2, 3) = 2.5, mean(6, 7) = 6.5.
    assert [p["avg_return"]["estimate"] for p in curve] == [pytest.approx(2.5), pytest.approx(6.5)]
    assert curve[1]["avg_return"]["per_seed"] == [5.0, 6.0, 7.0, 8.0]
    assert curve[0]["avg_return"]["mean"] == pytest.approx(11.5)
    assert curve[0]["avg_return"]["low"] <= 2.5 <= curve[0]["avg_return"]["high"]
    summary = summarize_run(tmp_path, cfg)
    assert summary["curve"] == curve and not summary["complete"]
    text = format_curve(summary)
    assert "2.500 [" in text and "6.500 [" in text and "early-termination rate" in text
    png = plot_learning_curve(summary, tmp_path / "curve.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("last_step", "expected"),
    [(80_000, ["0", "20k", "40k", "60k", "80k"]), (1_000_000, ["0", "200k", "400k", "600k", "800k", "1M"])],
)
def test_learning_curve_step_ticks_are_short(last_step, expected):
    from matplotlib.figure import Figure

    ax = Figure().subplots()
    ax.plot([0, last_step], [0.0, 1.0])
    ax.set_xlim(0, last_step)
    format_step_axis(ax)
    ax.figure.canvas.draw()
    labels = [t.get_text() for t in ax.get_xticklabels() if 0 <= t.get_position()[0] <= last_step]
    assert labels == expected


def test_summary_of_an_unfinished_run_is_marked_incomplete(tmp_path):
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2)
    summary = summarize_run(tmp_path, cfg)
    assert not summary["complete"] and summary["aggregate"] == {} and summary["curve"] == []
    assert "no final evaluation" in format_table(summary)
