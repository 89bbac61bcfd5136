"""The campaign script: its plan, one run end to end with the report, skipping what is done, bad input.
The whole campaign at the smoke preset is a slow test (15 runs)."""

import json
import os
import shlex
import shutil

import pytest
from train_support import call, load_script, one_line_error, prepare_cache


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    return load_script("paper", "paper_cli")


def flop_dry_run(out, only: str) -> list[str]:
    """paper.py's arguments for a smoke-preset dry run of ``only`` costed by the FLOP model."""
    return ["--out", str(out), "--dry-run", "--no-calibrate", "--preset", "smoke", "--only", only]


def test_the_campaign_holds_every_figure_of_the_paper(paper):
    runs = {run.name: run for run in paper.campaign()}
    assert len(runs) == 12 + 1 + 2  # 3 envs x 4 agents, the kappa sweep, two Table I variants
    assert runs["country_road-xdsac-kappa"].sweep == ("kappa=-0.01,-0.001,0,0.001,0.01,0.1",)
    assert runs["country_road-xsac-weights1"].sets == ("weight_depth=1",)
    assert {run.figure for run in runs.values()} == {"Fig. 5", "Fig. 6", "Fig. 7", "Fig. 8", "Table I"}


def test_dry_run_prints_the_plan_and_writes_nothing(paper, capsys, tmp_path):
    out = tmp_path / "campaign"
    args = flop_dry_run(out, "tracking-d*")
    status, text, _ = call(paper, capsys, *args)
    assert status == 0 and not out.exists()
    (row,) = [line.split() for line in text.splitlines() if line.startswith("tracking-")]
    assert row[:6] == ["tracking-dsac", "Fig.", "6", "new", "0%", "20"]  # members: the default 20 seeds
    assert float(row[-5]) > 0 and "H100 hours at 25% of 67 TFLOP/s" in text  # GFLOP per update
    assert row[-2] == "FLOP" and "1 by FLOP model" in text  # --no-calibrate: the FLOP model, labelled
    # Patterns match whole names: the Country Road pair of Fig. 5 without the kappa sweep.
    args = flop_dry_run(out, "country_road-*dsac")
    status, text, _ = call(paper, capsys, *args)
    names = [line.split()[0] for line in text.splitlines() if line.startswith("country_road-")]
    assert status == 0 and names == ["country_road-dsac", "country_road-xdsac"]


FAKE_RATES = {"warmup_vector_step_s": 36.0, "vector_step_s": 360.0, "eval_s": 3600.0, "setup_s": 36000.0}


def test_dry_run_counts_cpu_hours_by_this_machines_calibrations(paper, capsys, tmp_path, monkeypatch):
    """A configuration without a calibration is measured first (here by a stand-in that trains
    nothing), then cached; --no-calibrate keeps the FLOP model; each row says where its hours come from."""
    from xrl_jax.benchmarks import calibration
    from xrl_jax.benchmarks.calibration import CalibrationError
    from xrl_jax.campaign import hours as shown_hours
    from xrl_jax.train.calibrations import cache_folder

    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))  # the dry run may add to it
    shutil.rmtree(cache_folder(), ignore_errors=True)
    asked = []

    def measure(cfg, members_per_device, devices):
        asked.append((cfg.env, cfg.algo, cfg.num_members, members_per_device, devices))
        return dict(FAKE_RATES, created="2026-01-02T03:04:05")

    monkeypatch.setattr(calibration, "calibrate_in_child", measure)
    dry = ["--dry-run", "--preset", "smoke", "--seeds", "2", "--only", "tracking-dsac"]
    args = ["--out", str(tmp_path / "c"), *dry]
    rows, errs = [], []
    for _ in range(2):
        status, text, err = call(paper, capsys, *args)
        assert status == 0, err
        rows += [line.split() for line in text.splitlines() if line.startswith("tracking-dsac")]
        errs.append(err)
    assert "1 configuration(s) have no calibration on this machine; measuring them takes ~" in errs[0]
    assert "calibrated tracking-dsac (" in errs[0] and "no calibration" not in errs[1]
    ((env, algo, members, per_device, devices),) = asked  # measured once, then cached
    assert (env, algo, members) == ("tracking", "dsac", 2) and per_device * devices >= 2
    assert [row[-2] for row in rows] == ["measured", "cached"]
    # The smoke preset's Tracking run, one group: 64 warm-up steps and 128 updating ones of 4 envs,
    # one evaluation at the end and the compilation.
    hours = (64 / 4 * 36.0 + 128 / 4 * 360.0 + 3600.0 + 36000.0) / 3600
    assert rows[0][-3] == rows[1][-3] == shown_hours(hours)  # as the table rounds them
    assert "1 by cached calibration" in text
    # --no-calibrate: the FLOP model, as plan() without a calibration gives it.
    status, text, _ = call(paper, capsys, *args, "--no-calibrate")
    (row,) = [line.split() for line in text.splitlines() if line.startswith("tracking-dsac")]
    runs = [run for run in paper.campaign() if run.name == "tracking-dsac"]
    (planned,) = paper.plan(runs, tmp_path / "c", "smoke", 2, 0.25)
    assert row[-2] == "FLOP" and row[-3] == shown_hours(planned["flop_cpu_hours"])
    assert planned["cpu_hours"] == planned["flop_cpu_hours"] and "FLOP model: the updates' FLOPs" in text

    # A calibration that fails leaves its run to the FLOP model, and says so; how long calibrating
    # takes is now told by the time the cached one took (4 seeds: another configuration).
    def fail(*_):
        raise CalibrationError("boom")

    monkeypatch.setattr(calibration, "calibrate_in_child", fail)
    status, text, err = call(paper, capsys, *[a if a != "2" else "4" for a in args])
    assert status == 0 and "calibrating tracking-dsac failed (boom)" in err
    assert "s each, the median of this machine's 1 calibration(s);" in err
    (row,) = [line.split() for line in text.splitlines() if line.startswith("tracking-dsac")]
    assert row[-2] == "FLOP"


@pytest.mark.slow  # ~20 s: a whole campaign run; the dry-run's tests stay in the default tier
def test_one_run_end_to_end_then_skipped_when_done(paper, capsys, tmp_path):
    out = tmp_path / "campaign"
    args = [
        "--out",
        str(out),
        "--preset",
        "smoke",
        "--seeds",
        "2",
        "--only",
        "tracking-dsac",
        "--no-controller",
        "--set",
        "checkpoint_minutes=10",
    ]
    status, text, err = call(paper, capsys, *args)
    assert status == 0, err
    config = json.loads((out / "tracking-dsac" / "config.json").read_text())
    assert config["config"]["checkpoint_minutes"] == 10.0  # --set reaches the runs it starts
    assert (out / "tracking-dsac" / "summary.json").is_file() and (out / "report" / "report.md").is_file()
    assert "tracking-dsac: starting" in err and "report:" in text
    status, _, err = call(paper, capsys, *args)
    assert status == 0 and "tracking-dsac: done, skipped" in err
    # The plan costs what would run: the finished run as it ran (2 seeds, smoke widths), a new one with
    # the command's --seeds and --set.
    plans = {}
    for sets in ((), ("--set", "actor_width=64")):
        dry = [*flop_dry_run(out, "tracking-*dsac"), *sets]
        status, text, _ = call(paper, capsys, *dry)
        assert status == 0
        rows = [line.split() for line in text.splitlines() if line.startswith("tracking-")]
        plans[sets] = {row[0]: row for row in rows}
    plain, wide = plans.values()
    assert plain["tracking-dsac"][3:6] == ["done", "100%", "2"]
    assert plain["tracking-xdsac"][3:6] == ["new", "0%", "20"]
    assert wide["tracking-dsac"] == plain["tracking-dsac"]
    assert float(wide["tracking-xdsac"][-5]) > float(plain["tracking-xdsac"][-5])  # GFLOP per update
    # A report that cannot be written fails in one line and keeps the finished runs.
    shutil.rmtree(out / "report")
    (out / "report").write_text("not a folder")
    status, _, err = call(paper, capsys, *args)
    assert status == 1 and "the runs are kept, but the report failed" in err and "is a file" in err
    assert "Traceback" not in err and (out / "tracking-dsac" / "summary.json").is_file()
    # A started run costs what its checkpoints leave to run, not its whole budget: stopped at the
    # checkpoint of step 128 of 192, each seed has done 128 steps and half of its 128 updates (they
    # start after the 64 warm-up steps).
    (out / "tracking-dsac" / "summary.json").unlink()
    shutil.rmtree(out / "tracking-dsac" / "checkpoints" / "group_0" / "192")
    runs = [run for run in paper.campaign() if run.name == "tracking-dsac"]
    (row,) = paper.plan(runs, out, "smoke", 2, 0.25)
    assert row["status"] == "started" and row["progress"] == pytest.approx(128 / 192)
    assert row["cpu_hours_left"] == pytest.approx(row["cpu_hours"] / 2)
    status, text, _ = call(
        paper,
        capsys,
        *flop_dry_run(out, "tracking-dsac"),
    )
    assert status == 0 and "started    67%" in text


def test_a_stopped_campaign_is_continued_by_its_own_command(paper):
    """The command printed on a stop repeats every option: a bare --out would continue with the
    whole paper at the paper preset instead of, say, four quick Tracking runs."""
    argv = ["--out", "results/my runs", "--preset", "quick", "--seeds", "4", "--only", "tracking-*"]
    again = paper.continue_command(argv)
    assert again.startswith("python experiments/paper.py ") and shlex.split(again)[2:] == argv


def test_bad_input_fails_in_one_line(paper, capsys, tmp_path):
    status, _, err = call(paper, capsys, "--out", str(tmp_path), "--only", "nothing-like-this")
    one_line_error(status, err, "matches no run")
    status, _, err = call(paper, capsys, "--out", str(tmp_path), "--utilisation", "0")
    one_line_error(status, err, "--utilisation must be in (0, 1]")
    # A --set repeated, or one that a run of the campaign sets itself, is refused before anything runs.
    out = tmp_path / "campaign"
    status, _, err = call(paper, capsys, "--out", str(out), "--set", "gamma=0.9", "--set", "agent.gamma=0.8")
    one_line_error(status, err, "--set gamma is given twice", "'gamma=0.9'", "'agent.gamma=0.8'")
    status, _, err = call(paper, capsys, "--out", str(out), "--set", "weight_depth=2")
    one_line_error(status, err, "country_road-xsac-weights1 sets this itself", "'weight_depth=1'")
    # A value a run's config refuses, too, and in the plan as well as in a campaign.
    for dry in ([], ["--dry-run"]):
        status, _, err = call(paper, capsys, "--out", str(out), "--set", "actor_width=0", *dry)
        one_line_error(status, err, "country_road-sac: AgentConfig: actor_width must be a positive integer")
    assert not out.exists()


@pytest.mark.slow
# 15 training runs, compiled as a user's are: the unoptimised build of the default tier runs
# Intersection's SAC into a non-finite actor gradient at step 70 of seed 1 (the optimised one does not).
@pytest.mark.optimised
def test_the_whole_campaign_at_the_smoke_preset(paper, capsys, tmp_path):
    out = tmp_path / "campaign"
    status, _, err = call(paper, capsys, "--out", str(out), "--preset", "smoke", "--seeds", "2")
    assert status == 0, err[-2000:]
    assert all((out / run.name / "summary.json").is_file() for run in paper.campaign())
    report = (out / "report" / "report.md").read_text()
    assert all(f"## {env}" in report for env in ("country_road", "tracking", "intersection"))
    assert (out / "report" / "sweep_country_road-xdsac-kappa.png").is_file()
    assert report.count("| hand controller (8 m/s) |") == 2  # the two racing envs
    assert report.count("| scripted driver (10 m/s) |") == 1


def test_the_cpu_rate_of_the_estimate_is_a_measured_table_shipped_with_the_package():
    """The campaign's CPU FLOP/s is a measurement: it lives in a data file beside the benchmarks that
    measure it (not a constant in code), which the package installs (pyproject's package data)."""
    import fnmatch
    from pathlib import Path

    tomllib = pytest.importorskip("tomllib")
    from xrl_jax import campaign

    root = Path(campaign.__file__).resolve().parent
    assert campaign.MEASURED_RATES.parent == root / "benchmarks" and campaign.MEASURED_RATES.is_file()
    setuptools = tomllib.loads((root.parent / "pyproject.toml").read_text())["tool"]["setuptools"]
    declared = setuptools["package-data"]
    assert any(fnmatch.fnmatch(campaign.MEASURED_RATES.name, p) for p in declared["xrl_jax.benchmarks"])
    rate = json.loads(campaign.MEASURED_RATES.read_text())["cpu_update_flop_per_s"]
    assert campaign.cpu_flops() == rate["value"] > 0 and "bench.py update" in rate["measured"]
    assert not hasattr(campaign, "CPU_FLOPS")
