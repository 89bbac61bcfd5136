"""The report over result folders (hand-written folders: no training): tables with the paper's
values beside paper-protocol runs only, incomplete folders, improvement probabilities equal to
xrl_jax.stats by hand, figures, and the CLI's one-line error."""

import json
from pathlib import Path

import numpy as np
import pytest
from train_support import load_script

from xrl_jax import stats
from xrl_jax.config import parse_sweep, resolve_config
from xrl_jax.report import env_figure, improvements, read_run, read_runs, results_rows, write_report
from xrl_jax.runs import config_document
from xrl_jax.runs.folder import member_fields, member_stem

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


def fake_run(folder: Path, env, algo, preset, returns, sweep=(), missing=(), overrides=None):
    """A finished run whose member m ends with return ``returns[m]`` (ETR 0.1 each; on the
    Intersection, trips = return / 5 and 3 early terminations; halfway, half of it)."""
    sweep = parse_sweep(list(sweep))
    points = len(sweep[0][1]) if sweep else 1
    cfg = resolve_config(
        env, algo, preset, num_seeds=len(returns) // points, sweep=sweep, overrides=overrides
    )
    (folder / "eval").mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(config_document(cfg)))
    for member, value in enumerate(returns):
        if member in missing:
            continue
        fields = member_fields(cfg, member)
        rows = [
            {
                "step": cfg.total_steps // 2,
                **fields,
                "avg_return": value / 2,
                "avg_etr": 0.5,
                "avg_episode_length": 9.0,
                "episode_returns": [value / 2] * 3,
            },
            {
                "step": cfg.total_steps,
                **fields,
                "avg_return": value,
                "avg_etr": 0.1,
                "avg_episode_length": 9.0,
                "episode_returns": [value] * 3,
            },
        ]
        if env == "intersection":
            for row in rows:
                row.update(avg_trips_completed=row["avg_return"] / 5, avg_early_terminations=3.0,
                           avg_mean_velocity=6.0)  # fmt: skip
        (folder / "eval" / f"{member_stem(cfg, member)}.jsonl").write_text(
            "".join(json.dumps(r) + "\n" for r in rows)
        )
    return folder


@pytest.fixture
def folders(tmp_path):
    return {
        "sac": fake_run(tmp_path / "sac", "tracking", "sac", "quick", [10.0, 12.0, 14.0, 16.0]),
        "xsac": fake_run(tmp_path / "xsac", "tracking", "xsac", "quick", [13.0, 15.0, 17.0, 9.0]),
        "dsac": fake_run(tmp_path / "dsac", "country_road", "dsac", "paper", [80.0, 81.0, 82.0, 83.0]),
        "xdsac": fake_run(
            tmp_path / "xdsac", "country_road", "xdsac", "paper", [84.0, 85.0, 86.0, 87.0], missing=(3,)
        ),
        "sweep": fake_run(
            tmp_path / "kappa",
            "country_road",
            "xdsac",
            "smoke",
            [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            sweep=["kappa=0,0.001,0.01"],
        ),
    }


def test_tables_put_the_papers_values_beside_paper_protocol_runs_only(folders):
    runs = [read_run(f) for f in folders.values()]
    road = results_rows(runs, "country_road")
    assert [r["agent"] for r in road] == ["dsac", "xdsac"]  # the sweep has its own figure
    assert road[0]["paper: final return"] == "82.24" and road[1]["paper: final return"] == "85.22"
    assert road[1]["seeds"] == "3/4" and road[1]["status"].startswith("incomplete: 3 of 4")
    tracking = results_rows(runs, "tracking")
    assert all(r["paper: final return"] == "-" for r in tracking)  # quick runs are not the paper's protocol
    iqm = stats.iqm(np.array([10.0, 12.0, 14.0, 16.0]))
    assert tracking[0]["agent"] == "sac" and tracking[0]["final return"].startswith(f"{iqm:.2f} [")


def test_improvement_probability_is_computed_as_by_hand(folders):
    runs = [read_run(f) for f in folders.values()]
    (found,) = improvements(runs, "tracking")
    xs, ys = np.array([13.0, 15.0, 17.0, 9.0]), np.array([10.0, 12.0, 14.0, 16.0])
    # By hand: 13 beats 10, 12 (2); 15 beats 3; 17 beats 4; 9 beats none: 9 of 16 pairs.
    assert (
        found["estimate"] == pytest.approx(9 / 16) == pytest.approx(stats.probability_of_improvement(xs, ys))
    )
    assert found["low"] <= found["estimate"] <= found["high"] and found["seeds"] == [4, 4]
    # The test beside it: U = 9 is near its centre 8; of the 70 splits of the 8 seeds into two groups
    # of 4, 31 have U >= 9, so p = 2 * 31 / 70 (the enumeration: tests/test_stats.py).
    assert found["p_value"] == pytest.approx(62 / 70)
    assert found["coverage_without_difference"] == stats.improvement_interval_coverage(4, 4)
    (road,) = improvements(runs, "country_road")
    assert road["estimate"] == 1.0 and road["seeds"] == [3, 4]  # the incomplete run's 3 final seeds


def test_report_cli_writes_tables_figures_and_report(folders, tmp_path, capsys):
    cli = load_script("report", "report_cli")
    out = tmp_path / "report"
    assert cli.main([*map(str, folders.values()), "--out", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "## country_road" in text and "## tracking" in text and "P(xsac" in text and "incomplete" in text
    for name in ("results_tracking.csv", "results_country_road.md", "tracking.png", "country_road.png",
                 "sweep_kappa.png"):  # fmt: skip
        assert (out / name).exists(), name
    assert (out / "tracking.png").read_bytes().startswith(PNG)
    found = json.loads((out / "improvement.json").read_text())
    # Each pair at the end and at the shared evaluation nearest a quarter of the run (the only other
    # one, halfway); xdsac's run lost a seed, so it has no curve and no early comparison.
    halfway = str(resolve_config("tracking", "xsac", "quick").total_steps // 2)
    assert sorted((r["x"].split()[0], str(r["step"])) for r in found) == [
        ("xdsac", "final"),
        ("xsac", halfway),
        ("xsac", "final"),
    ]
    capsys.readouterr()
    assert cli.main([str(tmp_path / "nothing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]


def test_env_figure_gives_each_agent_one_colour_and_shows_a_one_point_curve(tmp_path):
    """An unfinished run (one evaluation, halfway; no final) listed first: the finished run's bar
    takes its own curve's colour, not the first one, and the one-point curve is drawn (a marker: a
    line through one point draws nothing)."""
    from matplotlib.colors import to_hex

    unfinished = fake_run(tmp_path / "dsac", "country_road", "dsac", "quick", [1.0, 2.0])
    for path in (unfinished / "eval").iterdir():
        path.write_text(path.read_text().splitlines(keepends=True)[0])
    finished = fake_run(tmp_path / "xdsac", "country_road", "xdsac", "quick", [3.0, 4.0])
    figure = env_figure(read_runs([unfinished, finished]), "country_road")
    bars, curves = figure.axes[0], figure.axes[2]  # final return; its learning curves
    colours = {line.get_label(): to_hex(line.get_color()) for line in curves.get_lines()}
    [bar] = bars.containers
    assert [tick.get_text() for tick in bars.get_yticklabels()] == ["xdsac"]
    assert to_hex(bar.lines[0].get_color()) == colours["xdsac"] != colours["dsac"]
    [one_point] = [line for line in curves.get_lines() if line.get_label() == "dsac"]
    assert len(one_point.get_xdata()) == 1 and one_point.get_marker() not in ("None", "", None)


def test_an_agent_has_one_colour_in_every_figure_and_legends_sit_outside_the_axes(tmp_path):
    """Issue 50: an agent's colour changed from figure to figure (the n-th run drawn took the n-th
    colour), and legends inside the axes hid curve segments. Now the colour is the agent's, whatever
    else is drawn, a second run of one agent keeps it with another line style, and the one legend is
    the figure's."""
    from matplotlib.colors import to_hex

    from xrl_jax.report_figures import AGENT_COLOURS

    xdsac = fake_run(tmp_path / "xdsac", "country_road", "xdsac", "quick", [3.0, 4.0])
    dsac = fake_run(tmp_path / "dsac", "country_road", "dsac", "quick", [1.0, 2.0])
    again = fake_run(tmp_path / "xdsac-2", "country_road", "xdsac", "smoke", [5.0, 6.0])
    for runs in ([xdsac], [dsac, xdsac], [dsac, xdsac, again]):
        figure = env_figure(read_runs(runs), "country_road")
        lines = figure.axes[2].get_lines()
        assert all(ax.get_legend() is None for ax in figure.axes) and len(figure.legends) == 1
        by_algo = {}
        for line in lines:
            by_algo.setdefault(line.get_label().split()[0], set()).add(to_hex(line.get_color()))
        assert by_algo == {algo: {to_hex(AGENT_COLOURS[algo])} for algo in by_algo}
    styles = sorted(line.get_linestyle() for line in lines if line.get_label().startswith("xdsac"))
    assert styles == ["-", "--"]


def test_sweep_points_are_compared_with_the_baseline_and_the_best_point(folders):
    """Fig. 8's reading: each κ against the DSAC baseline, and the best point against the others,
    each by the Mann-Whitney U test. The fixture's points (2 seeds each: 1-2, 3-4, 5-6) all lie below
    the baseline's 4 seeds (80-83): P = 0, p = 2 / C(6, 2) = 2/15; the best point (κ = 0.01) beats
    each other one in every pair: p = 2 / C(4, 2) = 1/3, not a difference at 2 vs 2 seeds."""
    from xrl_jax.comparisons import sweep_comparisons

    runs = read_runs(list(folders.values()))
    sweep = next(r for r in runs if r.is_sweep)
    baseline = next(r for r in runs if r.cfg.algo == "dsac")
    lines = sweep_comparisons(sweep, baseline)
    assert len(lines) == 4
    assert lines[0] == "kappa=0: P(> dsac) = 0.00 [0.00, 0.00] (2 vs 4 seeds; Mann-Whitney p = 0.13)"
    assert lines[3] == ("best IQM: kappa=0.01; against every other point (Mann-Whitney): kappa=0 p = 0.33, "
                        "kappa=0.001 p = 0.33")  # fmt: skip
    assert sweep_comparisons(sweep, None) == lines[3:]


def test_the_report_says_how_episodes_end_where_the_evaluations_record_it(tmp_path):
    """Issue 50 (safety, looked at): the share of each way the final evaluation's episodes end and
    the distance driven, a mean over seeds; a run whose records predate the fields has no row."""
    from xrl_jax.report import ending_rows

    recorded = fake_run(tmp_path / "xdsac", "country_road", "xdsac", "quick", [3.0, 4.0])
    old = fake_run(tmp_path / "dsac", "country_road", "dsac", "quick", [1.0, 2.0])
    for seed, path in enumerate(sorted((recorded / "eval").iterdir())):
        rows = [json.loads(line) for line in path.read_text().splitlines()]
        rows[-1] |= {"avg_end_left_track": 0.5 + 0.1 * seed, "avg_end_time_limit": 0.5 - 0.1 * seed,
                     "avg_end_idling": 0.0, "avg_end_invalid_action": 0.0,
                     "avg_end_progress_m": 100.0 * (seed + 1)}  # fmt: skip
        path.write_text("".join(json.dumps(row) + "\n" for row in rows))
    (row,) = ending_rows(read_runs([old, recorded]), "country_road")
    assert row["agent"].startswith("xdsac") and row["seeds"] == "2"
    ended = (row["left the track"], row["time limit"], row["distance at the end (m)"])
    assert ended == ("0.55", "0.45", "150.0")
    out = tmp_path / "report"
    write_report([old, recorded], out)
    assert "How the final evaluation's episodes end" in (out / "report.md").read_text()


def test_table_one_puts_each_weight_depth_beside_sac_with_its_costs(tmp_path):
    """Issue 50: Table I at the runs' scale. XSAC runs with weights from layers 1 and 2 and the main
    XSAC run (layer = actor depth) beside SAC, each with its return and the costs that
    ``policy_costs`` gives for its own agent config; the paper's numbers only beside its protocol.
    Without a weight-depth variant there is no table."""
    from xrl_jax.report import table_one_rows

    folders = [
        fake_run(tmp_path / "sac", "country_road", "sac", "quick", [1.0, 2.0, 3.0, 4.0]),
        fake_run(tmp_path / "xsac", "country_road", "xsac", "quick", [5.0, 6.0, 7.0, 8.0]),
        *[
            fake_run(
                tmp_path / f"w{d}",
                "country_road",
                "xsac",
                "quick",
                [9.0, 10.0, 11.0, 12.0],
                overrides={"weight_depth": str(d)},
            )
            for d in (1, 2)
        ],
        fake_run(tmp_path / "tracking", "tracking", "xsac", "quick", [1.0, 2.0]),
    ]
    runs = read_runs(folders)
    assert table_one_rows([r for r in runs if r.cfg.agent.weight_depth is None]) == []

    def costs(config):  # a stand-in: the depth decides the FLOPs, as in the real count
        depth = config.weight_depth or config.actor_depth
        return {"params": 100, "flops_as_run": 1000.0 * depth if config.algo == "xsac" else 7.0,
                "flops_xla": 5000.0}  # fmt: skip

    rows = table_one_rows(runs, costs)
    depth = resolve_config("country_road", "xsac", "quick").agent.actor_depth
    assert [r["model"] for r in rows] == ["SAC (baseline)", "XSAC, weights from hidden layer 1",
                                          "XSAC, weights from hidden layer 2",
                                          f"XSAC, weights from hidden layer {depth}"]  # fmt: skip
    assert [r["FLOPs per action (as run)"] for r in rows] == ["7", "1,000", "2,000", f"{1000 * depth:,}"]
    assert rows[1]["final return"] == _cell_of([9.0, 10.0, 11.0, 12.0])
    assert all(r["paper: final return"] == "-" for r in rows)  # quick runs: not the paper's protocol
    out = tmp_path / "report"
    write_report(folders, out, policy_costs=costs)
    assert "## Table I" in (out / "report.md").read_text() and (out / "table_one.md").exists()


def _cell_of(scores) -> str:
    interval = stats.stratified_bootstrap_ci(np.array(scores), stats.iqm)
    return f"{interval.estimate:.2f} [{interval.low:.2f}, {interval.high:.2f}]"


@pytest.mark.parametrize("where", ["an existing file", "below a file"])
def test_report_cli_refuses_an_out_it_cannot_write_in_one_line(folders, tmp_path, capsys, where):
    """Before: a 12-21-line traceback (FileExistsError, NotADirectoryError). Now one line, status 2,
    before any folder is read."""
    cli = load_script("report", "report_cli")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    out, fragment = (
        (blocker, "is a file") if where == "an existing file" else (blocker / "sub", "cannot create")
    )
    assert cli.main([str(folders["sac"]), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("report.py: error: ") and fragment in err[0], err
    assert blocker.read_text() == "not a folder"


def test_report_cli_reports_a_folder_given_twice_once_and_says_so(folders, tmp_path, capsys):
    """The same folder twice (also under another name) is one run, not two rows of the same seeds;
    a note on standard error says which was left out, and the report is written."""
    cli = load_script("report", "report_cli")
    sac, out = folders["sac"], tmp_path / "report"
    again = tmp_path / "link"
    again.symlink_to(sac)
    assert cli.main([str(sac), str(folders["xsac"]), str(sac), str(again), "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"report.py: note: {sac} is given twice; reported once",
                   f"report.py: note: {again} is the same folder as {sac}; reported once"]  # fmt: skip
    rows = (out / "results_tracking.md").read_text().splitlines()[2:]
    assert [row.split(" | ")[0] for row in rows] == ["| sac", "| xsac"]


@pytest.mark.parametrize("copy_first", [True, False])
def test_report_reads_a_run_given_also_as_a_copy_of_its_records_once(folders, tmp_path, capsys, copy_first):
    """A run folder and a report's copy of its records (``runs/<name>``) are one run, not two rows of
    the same seeds (docs/results_quick's Intersection table once listed DSAC twice so). The copy made
    before the run's last evaluation has fewer lines, so the run folder is read, in either order."""
    cli = load_script("report", "report_cli")
    sac = folders["sac"]
    early = tmp_path / "early"
    write_report([sac], early)
    copy = early / "runs" / sac.name
    last_seed = sorted((copy / "eval").glob("*.jsonl"))[-1]
    last_seed.write_text(last_seed.read_text().splitlines(keepends=True)[0])  # before its final evaluation
    sources = [copy, sac] if copy_first else [sac, copy]
    out = tmp_path / "report"
    assert cli.main([*map(str, sources), str(folders["xsac"]), "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    same = f"{copy} holds the same run as {sac} (its records); reported once"
    assert err == [f"report.py: note: {same}"]
    rows = (out / "results_tracking.md").read_text().splitlines()[2:]
    assert [row.split(" | ")[0] for row in rows] == ["| sac", "| xsac"]
    assert "| complete |" in rows[0]  # read from the run folder, which has every evaluation


def test_write_report_reads_a_folder_without_any_evaluation(tmp_path):
    """A run that has only just started: no eval file yet. It is listed, incomplete, nothing fails."""
    folder = fake_run(tmp_path / "fresh", "tracking", "xdsac", "quick", [1.0, 2.0], missing=(0, 1))
    report = write_report([folder], tmp_path / "out").read_text()
    assert "incomplete: 0 of 2" in report


def test_controller_rows_use_each_envs_evaluation_tracks(folders, tmp_path, monkeypatch):
    """--controller: one hand-controller row per racing env, driven on the tracks its runs evaluate
    on (the driving itself is tested in test_hand_controller.py; here a stand-in records the calls)."""
    import xrl_jax.report as report_mod

    calls = []

    def fake_controller(scenario, eval_track_seed, episodes, target_speed):
        calls.append((scenario, eval_track_seed, episodes, target_speed))
        return {"target_speed": target_speed, "avg_return": 36.5, "avg_etr": 0.06, "episode_returns": []}

    monkeypatch.setattr(report_mod, "evaluate_yardstick", fake_controller)
    out = tmp_path / "with_controller"
    write_report(list(folders.values()), out, controller_speed=9.0)
    cfg = read_run(folders["sac"]).cfg
    assert sorted(calls) == [
        ("country_road", cfg.eval_track_seed, cfg.eval_episodes, 9.0),
        ("tracking", cfg.eval_track_seed, cfg.eval_episodes, 9.0),
    ]
    table = (out / "results_tracking.md").read_text()
    assert "| hand controller (9 m/s) |" in table and "36.50 (mean)" in table and "0.06 (mean)" in table
    assert [r["env"] for r in json.loads((out / "controller.json").read_text())] == [
        "country_road",
        "tracking",
    ]


def test_intersection_report_shows_trips_and_early_terminations_with_the_scripted_driver(
    tmp_path, monkeypatch
):
    """Fig. 7's quantities on the Intersection: the table and figure show completed trips and early
    terminations, the scripted driver is the yardstick row, and P(explainable > baseline) is taken on
    trips at the end and early in the run (the driving itself is tested in test_intersection_driver.py)."""
    import xrl_jax.report as report_mod

    calls = []

    def fake_driver(scenario, eval_track_seed, episodes, target_speed):
        calls.append((scenario, eval_track_seed, episodes, target_speed))
        return {"target_speed": 10.0, "avg_return": 160.0, "avg_trips_completed": 26.2,
                "avg_early_terminations": 2.4, "episode_returns": []}  # fmt: skip

    monkeypatch.setattr(report_mod, "evaluate_yardstick", fake_driver)
    runs = [
        fake_run(tmp_path / "dsac", "intersection", "dsac", "quick", [100.0, 110.0, 120.0, 130.0]),
        fake_run(tmp_path / "xdsac", "intersection", "xdsac", "quick", [140.0, 150.0, 160.0, 170.0]),
    ]
    out = tmp_path / "report"
    write_report(runs, out, controller=True)
    cfg = read_run(runs[0]).cfg
    assert calls == [("intersection", None, cfg.eval_episodes, None)]  # the driver's own cruise speed
    table = (out / "results_intersection.md").read_text().splitlines()
    assert table[0].startswith("| agent | preset | steps | seeds | folder | completed trips |")
    assert "early terminations" in table[0]
    assert table[-1].startswith(
        f"| scripted driver (10 m/s) | - | - | {cfg.eval_episodes} episodes | - | 26.20 (mean) |"
    )
    assert (out / "intersection_pairs.png").read_bytes().startswith(PNG)
    found = json.loads((out / "improvement.json").read_text())
    # At the only earlier evaluation of the fakes and at the end; equal early terminations tie at 0.5.
    assert [(r["metric"], r["step"], r["estimate"]) for r in found] == [
        ("avg_trips_completed", cfg.total_steps // 2, 1.0),
        ("avg_trips_completed", "final", 1.0),
        ("avg_early_terminations", cfg.total_steps // 2, 0.5),
        ("avg_early_terminations", "final", 0.5),
    ]
    assert (
        "P(xdsac (quick, xdsac) > dsac (quick, dsac)) on completed trips, evaluation at step"
        in (out / "report.md").read_text()
    )


def test_a_report_is_written_again_from_its_kept_records_with_a_run_added(folders, tmp_path):
    """The report keeps each run's config and evaluations (runs/<folder>), without the per-episode
    values; after the run folders are gone, those copies and one new run write the same tables again
    with the new run's row added, and the kept copies are then exactly this report's runs."""
    import shutil

    out = tmp_path / "report"
    write_report([folders["sac"], folders["dsac"], folders["xdsac"]], out)
    first = {env: (out / f"results_{env}.csv").read_text() for env in ("tracking", "country_road")}
    kept = sorted(p.name for p in (out / "runs").iterdir())
    assert kept == ["dsac", "sac", "xdsac"]
    original = (folders["sac"] / "eval" / "seed_0.jsonl").read_text().splitlines()
    lines = (out / "runs" / "sac" / "eval" / "seed_0.jsonl").read_text().splitlines()
    assert [json.loads(line) for line in lines] == [
        {k: v for k, v in json.loads(line).items() if k != "episode_returns"} for line in original
    ]
    for name in ("sac", "dsac", "xdsac"):
        shutil.rmtree(folders[name])

    write_report([*sorted((out / "runs").iterdir()), folders["xsac"]], out)
    assert (out / "results_country_road.csv").read_text() == first["country_road"]  # 3/4 seeds as before
    tracking = (out / "results_tracking.csv").read_text().splitlines()
    assert tracking[:2] == first["tracking"].splitlines() and tracking[2].startswith("xsac,quick,")
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["dsac", "sac", "xdsac", "xsac"]
    assert not list(out.glob(".runs.*"))  # no staging or former copies left behind
    found = json.loads((out / "improvement.json").read_text())
    (xsac,) = [item for item in found if item["x"].startswith("xsac") and item["step"] == "final"]
    assert xsac["estimate"] == pytest.approx(9 / 16)  # as test_improvement_probability_is_computed_as_by_hand


def test_kept_records_of_two_runs_with_one_folder_name_are_both_kept(tmp_path):
    """Two machines' folders of one name (a/tracking-sac, b/tracking-sac) are both reported; their
    copies are kept side by side, the second with a suffix. (One command at one commit: the same
    config.json; the runs tell apart by their evaluations.)"""
    runs = [fake_run(tmp_path / where / "tracking-sac", "tracking", "sac", "quick", returns)
            for where, returns in (("a", [1.0, 2.0]), ("b", [1.5, 2.5]))]  # fmt: skip
    out = tmp_path / "report"
    write_report(runs, out)
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["tracking-sac", "tracking-sac-2"]


def test_runs_of_one_protocol_from_different_base_seeds_are_pooled_into_one_row(folders, tmp_path):
    """A protocol's seeds trained two at a time (--set seed=S, another machine, another session) are
    one row over all of them: the IQM, curve and P(XSAC > SAC) equal those of one 4-seed run. Runs
    that differ in what they measure, or that trained the same seeds, stay apart, and say why."""
    pool = [fake_run(tmp_path / "first", "tracking", "sac", "quick", [10.0, 12.0],
                     overrides={"seed": "0", "max_group_size": "1"}),
            fake_run(tmp_path / "second", "tracking", "sac", "quick", [14.0, 16.0],
                     overrides={"seed": "7", "checkpoint_minutes": "10"})]  # fmt: skip
    notes = []
    out = tmp_path / "report"
    write_report([pool[1], pool[0], folders["xsac"]], out, note=notes.append)
    whole = read_run(folders["sac"])  # the same four returns as one run
    (row, _) = results_rows([read_run(folders["xsac"]), *read_runs(pool)], "tracking")
    assert row["folder"] == "first + second" and row["seeds"] == "4/4" and row["status"] == "complete"
    assert row["final return"] == results_rows([whole], "tracking")[0]["final return"]
    assert notes == ["one protocol's seeds pooled into one row (first: 2 from base seed 0, second: 2 "
                     "from base seed 7)"]  # fmt: skip
    found = json.loads((out / "improvement.json").read_text())
    final = next(item for item in found if item["step"] == "final")
    assert final["estimate"] == pytest.approx(9 / 16) and final["seeds"] == [4, 4]
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["first", "second", "xsac"]

    (pooled,) = read_runs(sorted((out / "runs").iterdir())[:2])  # the kept records pool again
    assert pooled.summary["curve"] == whole.summary["curve"]

    longer = fake_run(tmp_path / "longer", "tracking", "sac", "quick", [1.0, 2.0],
                      overrides={"seed": "3", "total_steps": "160000"})  # fmt: skip
    twin = fake_run(tmp_path / "twin", "tracking", "sac", "quick", [1.0, 2.0])  # base seed 0, as "first"
    notes.clear()
    runs = read_runs([pool[0], twin, longer], note=notes.append)
    assert sorted(r.name for r in runs) == ["first", "longer", "twin"]
    assert notes == [
        "first, twin trained the same seeds of one protocol (one base seed); reported separately"
    ]


def test_pieces_of_one_sweep_are_pooled_into_the_sweep_of_them_all(folders, tmp_path):
    """Fig. 8 is longer than a session on a small machine, so it is trained in pieces (some κ values,
    some seeds each): the report reads them as the one sweep. The fixture's sweep (κ = 0, 0.001, 0.01,
    2 seeds each, returns 1-6 point-major) split by values, and split by seeds, gives its summary and
    its Fig. 8 reading exactly; a point fewer pieces trained is incomplete; pieces that trained one seed
    of one point stay apart, and say why."""
    from xrl_jax.comparisons import sweep_comparisons

    def piece(name, kappas, returns, seed):
        return fake_run(tmp_path / name, "country_road", "xdsac", "smoke", returns, sweep=[f"kappa={kappas}"],
                        overrides={"seed": str(seed)})  # fmt: skip

    whole, baseline = read_run(folders["sweep"]), read_run(folders["dsac"])
    by_values = [piece("low", "0,0.001", [1.0, 2.0, 3.0, 4.0], 0), piece("high", "0.01", [5.0, 6.0], 0)]
    by_seeds = [piece("even", "0,0.001,0.01", [1.0, 3.0, 5.0], 0),
                piece("odd", "0,0.001,0.01", [2.0, 4.0, 6.0], 5)]  # fmt: skip
    for pieces in (by_values, by_seeds):
        notes = []
        (pooled,) = read_runs(pieces, note=notes.append)
        assert pooled.is_sweep and pooled.cfg.num_points == 3 and pooled.cfg.num_seeds == 2
        assert pooled.summary["sweep"] == whole.summary["sweep"]
        assert pooled.summary["per_seed"] == whole.summary["per_seed"] and pooled.summary["complete"]
        assert sweep_comparisons(pooled, baseline) == sweep_comparisons(whole, baseline)
        assert notes and notes[0].startswith("one protocol's seeds pooled")

    short = piece("short", "0.01", [5.0], 3)  # κ = 0.01 with one seed: that point lacks one
    (pooled,) = read_runs([by_values[0], short])
    assert [p["seeds"] for p in pooled.summary["sweep"]["points"]] == [[0, 1], [0, 1], [0]]
    assert pooled.status() == "incomplete: 5 of 6 seeds have their final evaluation"

    again = piece("again", "0.001,0.01", [7.0, 8.0, 9.0, 10.0], 0)  # κ = 0.001 from base seed 0 twice
    notes = []
    runs = read_runs([by_values[0], again], note=notes.append)
    assert sorted(r.name for r in runs) == ["again", "low"]
    assert notes == [
        "low, again trained the same seeds of a sweep point both swept (one base seed); reported separately"
    ]
    other_field = fake_run(tmp_path / "alpha", "country_road", "xdsac", "smoke", [1.0, 2.0],
                           sweep=["init_alpha=0.01,0.1"])  # fmt: skip
    assert len(read_runs([by_values[0], other_field])) == 2  # what they sweep differs: two sweeps

    out = tmp_path / "report"
    write_report([*by_values, folders["dsac"]], out)
    assert (out / "sweep_low+high.png").read_bytes().startswith(PNG)
    assert "![sweep](sweep_low+high.png)" in (out / "report.md").read_text()


def test_a_run_that_diverged_is_reported_as_diverged_naming_seed_and_step(tmp_path):
    """The trainer stops a diverged run after writing the chunk's metrics (non-finite values as "nan");
    the report said only "incomplete" of it."""
    folder = fake_run(tmp_path / "nan", "tracking", "sac", "quick", [10.0, 12.0], missing=(1,))
    (folder / "metrics").mkdir()
    healthy = {"train/loss_critic": 0.5, "train/loss_actor": -1.0}
    for stem, broken_at in (("seed_0", None), ("seed_1", 4096)):
        rows = [{"step": step, "seed": int(stem[-1]), **healthy} for step in (2048, 4096)]
        rows = [r | ({"train/loss_actor": "nan"} if r["step"] == broken_at else {}) for r in rows]
        (folder / "metrics" / f"{stem}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (row,) = results_rows(read_runs([folder]), "tracking")
    assert row["status"] == (
        "diverged: seed 1 by step 4,096 (train/loss_actor not finite); "
        "1 of 2 seeds have their final evaluation"
    )
    assert read_run(folder).status() == row["status"]


def test_every_trained_agent_has_a_colour_of_its_own():
    """The on-policy agents drew grey before they had entries; each agent now keeps one colour."""
    from xrl_jax.config import TRAINED_ALGOS
    from xrl_jax.report_figures import AGENT_COLOURS

    assert set(AGENT_COLOURS) == set(TRAINED_ALGOS)
    assert len(set(AGENT_COLOURS.values())) == len(AGENT_COLOURS)


def test_the_report_orders_and_pairs_the_on_policy_agents_as_the_sac_family(tmp_path):
    """Reporting a PPO run raised (its algo had no row order); XDPPO is compared with DPPO as XDSAC
    with DSAC, and the report is written with every trained agent in it."""
    from xrl_jax.config import TRAINED_ALGOS
    from xrl_jax.report_figures import ALGO_ORDER

    assert sorted(ALGO_ORDER) == sorted(TRAINED_ALGOS)
    folders = [
        fake_run(tmp_path / "xdppo", "tracking", "xdppo", "quick", [13.0, 15.0, 17.0, 9.0]),
        fake_run(tmp_path / "dppo", "tracking", "dppo", "quick", [10.0, 12.0, 14.0, 16.0]),
        fake_run(tmp_path / "xdsac", "tracking", "xdsac", "quick", [1.0, 2.0, 3.0, 4.0]),
    ]
    runs = [read_run(folder) for folder in folders]
    assert [row["agent"] for row in results_rows(runs, "tracking")] == ["xdsac", "dppo", "xdppo"]
    (found,) = improvements(runs, "tracking")
    assert (found["x"], found["y"]) == (runs[0].label, runs[1].label)
    assert found["estimate"] == pytest.approx(9 / 16)
    write_report(folders, tmp_path / "report")
    assert "P(xdppo" in (tmp_path / "report" / "report.md").read_text()


def test_the_report_tabulates_explanation_statistics_and_keeps_them(tmp_path):
    """Issue 52: a run folder with ``explain.py --stats`` output gets a row (its numbers as written);
    the kept records carry the statistics, so a report written again from them has the row too."""
    from xrl_jax.report import explanation_rows

    xdsac = fake_run(tmp_path / "xdsac", "country_road", "xdsac", "quick", [3.0, 4.0])
    dsac = fake_run(tmp_path / "dsac", "country_road", "dsac", "quick", [1.0, 2.0])
    interval = lambda e, lo, hi: {"estimate": e, "low": lo, "high": hi}
    against = {"tv": interval(0.1, 0.05, 0.15), "return": interval(-8.0, -11.0, -5.0)}
    deletion = lambda ranker: {"against_random": {ranker: against}}
    explained = {
        "seeds": 2,
        "kinds": ["blue cone", "yellow cone"],
        "kind": {"share": [interval(0.3, 0.2, 0.4), interval(0.7, 0.6, 0.8)]},
        "size": {"mean": interval(4.5, 4.0, 5.0)},
        "stability": {"mean_change": interval(0.092, 0.07, 0.11)},
        "agreement": {"mean_similarity_between_seeds": 0.75},
        "deletion": deletion("weight"),
    }
    for folder, written in ((xdsac, explained), (dsac, {"seeds": 2, "deletion": deletion("occlusion")})):
        (folder / "explain" / "stats").mkdir(parents=True)
        (folder / "explain" / "stats" / "stats.json").write_text(json.dumps(written))
    rows = explanation_rows(read_runs([xdsac, dsac]))
    assert [row["agent"] for row in rows] == ["dsac (dsac)", "xdsac (xdsac)"]  # as the results tables
    assert explanation_rows(read_runs([dsac, xdsac])) == rows  # whatever the folders' order
    by_agent = {row["agent"]: row for row in rows}
    row = by_agent["xdsac (xdsac)"]
    assert row["objects for 90 %"] == "4.50 [4.00, 5.00]" and row["step-to-step TV"] == "0.092 [0.070, 0.110]"
    assert row["weight by kind"] == "yellow cone 0.70, blue cone 0.30"  # heaviest first
    deleted = "deleting the top-ranked objects, against random"
    assert row[deleted] == "by weight: tv +0.100 [+0.050, +0.150], return -8.00 [-11.00, -5.00]"
    baseline = by_agent["dsac (dsac)"]
    assert baseline["objects for 90 %"] == "-" and baseline[deleted].startswith("by occlusion: tv +0.100")
    out = tmp_path / "report"
    write_report([dsac, xdsac], out)
    assert "## Explanations over the evaluation" in (out / "report.md").read_text()
    again = tmp_path / "again"
    write_report(sorted((out / "runs").iterdir()), again)
    assert (again / "report.md").read_text().count("vs random") == (out / "report.md").read_text().count(
        "vs random"
    )


def test_the_report_says_how_intersection_cars_end(tmp_path):
    """Issue 50 (safety, looked at): on the Intersection the cars per episode that completed their
    trip, left the road or collided, a mean over seeds (fake_run: trips = return / 5)."""
    from xrl_jax.report import ending_rows

    run = fake_run(tmp_path / "xsac", "intersection", "xsac", "quick", [10.0, 20.0])
    for seed, path in enumerate(sorted((run / "eval").iterdir())):
        rows = [json.loads(line) for line in path.read_text().splitlines()]
        rows[-1] |= {"avg_come_off_vehicles": 1.0 + seed, "avg_collided_vehicles": 4.0 + 2 * seed}
        path.write_text("".join(json.dumps(row) + "\n" for row in rows))
    (row,) = ending_rows(read_runs([run]), "intersection")
    ended = (row["completed trips"], row["left the road"], row["collided"])
    assert row["seeds"] == "2" and ended == ("3.0", "1.5", "5.0")
    out = tmp_path / "report"
    write_report([run], out)
    assert "episodes end (cars per episode" in (out / "report.md").read_text()
