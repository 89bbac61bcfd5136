"""The ``experiments/run.py`` CLI end to end: smoke runs, determinism, exact resume, bad input."""

import functools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from train_support import call, files_of, load_script, one_line_error, prepare_cache, run_stopped_after

from xrl_jax import train as train_mod

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ["--env", "tracking", "--algo", "xdsac", "--preset", "smoke", "--seeds", "2", "--quiet"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """``run.main`` loaded in-process, so runs of one configuration share their compilation."""
    prepare_cache(tmp_path_factory.mktemp("cache"))
    return load_script("run", "run_cli")


@pytest.fixture(scope="module")
def smoke_run(run, tmp_path_factory):
    """One 2-seed smoke run of Tracking / XDSAC (192 steps per seed)."""
    out = tmp_path_factory.mktemp("runs") / "first"
    status = run.main([*SMOKE, "--out", str(out)])
    assert status == 0
    return out


def test_help_documents_every_option(run, capsys):
    status, out, _ = call(run, capsys, "--help")
    assert status == 0
    for option in (
        "--env",
        "--algo",
        "--seeds",
        "--steps",
        "--preset",
        "--set",
        "--out",
        "--resume",
        "--quiet",
    ):
        assert option in out
    for word in ("country_road", "tracking", "xdsac", "paper", "quick", "smoke", "KEY=VALUE", "summary.json"):
        assert word in out


def test_smoke_run_leaves_a_complete_results_folder(smoke_run):
    config = json.loads((smoke_run / "config.json").read_text())
    assert config["config"]["algo"] == "xdsac" and config["config"]["num_seeds"] == 2
    assert config["resolved"]["env_name"] == "tracking_discrete"
    assert config["versions"]["jax"] and "commit" in config["git"]
    for seed in (0, 1):
        metrics = [
            json.loads(x) for x in (smoke_run / "metrics" / f"seed_{seed}.jsonl").read_text().splitlines()
        ]
        assert [m["step"] for m in metrics] == [64, 128, 192]
        assert metrics[-1]["train/updates"] == 192 - 64
        evals = [json.loads(x) for x in (smoke_run / "eval" / f"seed_{seed}.jsonl").read_text().splitlines()]
        assert [e["step"] for e in evals] == [192] and len(evals[0]["episode_returns"]) == 3
    summary = json.loads((smoke_run / "summary.json").read_text())
    assert summary["complete"] and summary["seeds"] == [0, 1]
    assert summary["training_tracks"] == {"fresh": False, "bank": 3}  # the smoke preset's fixed bank
    assert set(summary["aggregate"]) >= {"avg_return", "avg_etr"}
    assert [p["step"] for p in summary["curve"]] == [192]
    assert summary["curve"][-1]["avg_return"]["estimate"] == summary["aggregate"]["avg_return"]["estimate"]
    assert (smoke_run / "learning_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert any((smoke_run / "checkpoints" / "group_0").iterdir())


def test_same_seed_gives_identical_metrics_and_other_seeds_differ(run, smoke_run, tmp_path, capsys):
    again = tmp_path / "again"
    status, out, _ = call(run, capsys, *SMOKE, "--out", str(again))
    assert status == 0 and "final return" in out and "IQM" in out and "learning curve" in out
    assert files_of(again, "metrics") == files_of(smoke_run, "metrics")
    assert files_of(again, "eval") == files_of(smoke_run, "eval")
    first = files_of(smoke_run, "metrics")
    assert first["seed_0.jsonl"] != first["seed_1.jsonl"].replace('"seed": 1', '"seed": 0')
    other = tmp_path / "other"
    assert call(run, capsys, *SMOKE, "--set", "seed=5", "--out", str(other))[0] == 0
    assert files_of(other, "metrics")["seed_0.jsonl"] != first["seed_0.jsonl"]


FRESH_TRACKS = ["--set", "train_tracks=0", "--set", "track_feed_size=8"]


# The fresh-track variant compiles the track generator into the run (~40 s more); the default suite
# checks instead that a checkpoint restores the feed exactly (tests/test_train.py).
@pytest.mark.parametrize(
    "tracks",
    [["--set", "train_tracks=3"], pytest.param(FRESH_TRACKS, marks=pytest.mark.slow)],
    ids=["bank", "fresh"],
)
def test_stopped_and_resumed_run_equals_an_uninterrupted_one(run, tmp_path, capsys, monkeypatch, tracks):
    """For a fixed bank and for fresh tracks (the feed is part of the checkpointed run state)."""
    args = [*SMOKE, "--steps", "256", "--set", "checkpoint_interval=128", *tracks]
    full, split = tmp_path / "full", tmp_path / "split"
    assert call(run, capsys, *args, "--out", str(full))[0] == 0
    # Stop after 3 of 4 chunks: the checkpoint is at step 128, metrics exist up to 192.
    status, _, err = run_stopped_after(run, capsys, monkeypatch, 3, *args, "--out", str(split))
    assert status == 1 and "--resume" in err
    metrics0 = split / "metrics" / "seed_0.jsonl"
    assert [json.loads(x)["step"] for x in metrics0.read_text().splitlines()] == [64, 128, 192]
    with open(metrics0, "a") as f:
        f.write('{"step": 256, "trunc')  # a line cut by a crash
    status, out, _ = call(run, capsys, "--resume", str(split), "--quiet")
    assert status == 0 and "final return" in out
    assert files_of(split, "metrics") == files_of(full, "metrics")
    assert files_of(split, "eval") == files_of(full, "eval")
    summary_full = json.loads((full / "summary.json").read_text())
    summary_split = json.loads((split / "summary.json").read_text())
    assert summary_full["aggregate"] == summary_split["aggregate"]
    assert summary_full["training_tracks"] == summary_split["training_tracks"]
    # Resuming a finished run trains nothing and reprints the table.
    status, out, _ = call(run, capsys, "--resume", str(split), "--quiet")
    assert status == 0 and "final return" in out


@pytest.fixture(scope="module")
def evaluate_cli(run):
    return load_script("evaluate", "evaluate_cli")


@pytest.mark.slow  # ~16 s; the next test drives the same CLI on the held-out tracks by default
def test_evaluate_cli_drives_a_bank_runs_agents_on_its_training_and_held_out_tracks(
    evaluate_cli, smoke_run, capsys
):
    status, out, err = call(evaluate_cli, capsys, str(smoke_run), "--tracks", "eval")
    assert status == 0, err
    held_out = json.loads((smoke_run / "evaluation_eval.json").read_text())
    assert held_out["episodes"] == 3 and [row["seed"] for row in held_out["per_seed"]] == [0, 1]
    assert [row["checkpoint_step"] for row in held_out["per_seed"]] == [192, 192]
    # XDSAC evaluates greedily and each track's start is fixed, so this repeats the run's own final
    # evaluation; only the rounding of another batch shape (2 seeds vmapped there, 1 here) may differ.
    final = json.loads((smoke_run / "summary.json").read_text())["per_seed"]
    for row in held_out["per_seed"]:
        assert abs(row["avg_return"] - final[str(row["seed"])]["avg_return"]) < 1e-3
    # --mode deterministic is greedy for every agent; XDSAC already evaluates greedily: the same drive.
    status, out, err = call(
        evaluate_cli, capsys, str(smoke_run), "--tracks", "eval", "--mode", "deterministic"
    )
    assert status == 0, err
    greedy = json.loads((smoke_run / "evaluation_eval_deterministic.json").read_text())
    assert greedy["mode"] == "deterministic" and greedy["per_seed"] == held_out["per_seed"]
    status, out, err = call(evaluate_cli, capsys, str(smoke_run), "--tracks", "train", "--episodes", "2")
    assert status == 0, err
    assert "final return on 2 train tracks: IQM" in out
    assert json.loads((smoke_run / "evaluation_train.json").read_text())["episodes"] == 2


def test_evaluate_cli_says_which_checkpoint_of_a_finished_run_it_used(
    evaluate_cli, smoke_run, capsys, tmp_path
):
    """Issue 48: with a finished run's last checkpoint damaged, evaluate.py used the one before and said
    "the run has not finished", and evaluation_eval.json did not say which step it evaluated."""
    finished = tmp_path / "finished"
    shutil.copytree(smoke_run, finished)
    data = max((p for p in (finished / "checkpoints" / "group_0" / "192").rglob("*") if p.is_file()),
               key=lambda p: p.stat().st_size)  # fmt: skip
    damaged = bytearray(data.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    data.write_bytes(bytes(damaged))
    status, _, err = call(evaluate_cli, capsys, str(finished), "--tracks", "eval")
    assert status == 0, err
    assert "using the checkpoint at step 128 of 192 (the run finished, but its last checkpoint" in err, err
    assert "has not finished" not in err
    rows = json.loads((finished / "evaluation_eval.json").read_text())["per_seed"]
    assert [row["checkpoint_step"] for row in rows] == [128, 128]


def test_evaluate_cli_offers_every_evaluation_mode(evaluate_cli):
    # The CLI lists the modes itself (no xrl_jax import for --help); they must be the agents' own.
    from xrl_jax.agents import EVAL_MODES

    mode = next(action for action in evaluate_cli.build_parser()._actions if action.dest == "mode")
    assert tuple(mode.choices) == EVAL_MODES and mode.default == "eval"


def test_evaluate_cli_refuses_what_it_cannot_measure(evaluate_cli, smoke_run, capsys, tmp_path):
    status, _, err = call(evaluate_cli, capsys, str(smoke_run), "--tracks", "train", "--episodes", "4")
    one_line_error(status, err, "--episodes 4", "only 3")
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    config = json.loads((smoke_run / "config.json").read_text())
    config["config"]["train_tracks"] = 0
    (fresh / "config.json").write_text(json.dumps(config))
    status, _, err = call(evaluate_cli, capsys, str(fresh), "--tracks", "train")
    one_line_error(status, err, "fresh tracks", "--tracks eval")
    status, _, err = call(evaluate_cli, capsys, str(tmp_path / "none"))
    one_line_error(status, err, "does not exist")


@pytest.mark.parametrize(
    "args, fragments",
    [
        (["--env", "moon"], ["invalid choice: 'moon'", "tracking", "country_road"]),
        (["--algo", "a2c"], ["invalid choice: 'a2c'", "xdsac", "xdppo"]),
        (["--preset", "huge"], ["invalid choice: 'huge'", "quick"]),
        (["--steps", "-5"], ["positive integer"]),
        (["--steps", "many"], ["positive integer"]),
        (["--seeds", "0"], ["positive integer"]),
        (["--preset", "smoke", "--steps", "130"], ["multiple of num_envs"]),
        (["--set", "gamma"], ["KEY=VALUE", "'gamma'"]),
        (["--set", "=0.9"], ["KEY=VALUE"]),
        (["--set", "learning_rate=1"], ["unknown setting 'learning_rate'", "actor_lr"]),
        (["--set", "gamma=abc"], ["cannot parse 'abc'"]),
        (["--set", "tau=0"], ["tau must lie in (0, 1]"]),
        (["--set", "gamma=0.9", "--set", "agent.gamma=0.8"], ["--set gamma is given twice"]),
    ],
)
def test_bad_input_fails_at_once_with_one_line(run, capsys, tmp_path, args, fragments):
    status, _, err = call(run, capsys, *args, "--out", str(tmp_path / "never"))
    one_line_error(status, err, *fragments)
    assert not (tmp_path / "never").exists()


def test_unwritable_out_is_refused(run, capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    status, _, err = call(run, capsys, "--preset", "smoke", "--out", str(blocker / "sub"))
    one_line_error(status, err, "cannot write the results folder")


def test_existing_results_are_never_overwritten(run, smoke_run, capsys):
    before = files_of(smoke_run, "metrics")
    status, _, err = call(run, capsys, *SMOKE, "--out", str(smoke_run))
    one_line_error(status, err, "already exists", "--resume")
    assert files_of(smoke_run, "metrics") == before


def test_resume_checks_the_folder_and_its_config(run, smoke_run, capsys, tmp_path):
    status, _, err = call(run, capsys, "--resume", str(tmp_path))
    one_line_error(status, err, "not a results folder")
    status, _, err = call(run, capsys, "--resume", str(smoke_run), "--algo", "xsac")
    one_line_error(status, err, "another configuration", "algo")
    status, _, err = call(run, capsys, "--resume", str(smoke_run), "--seeds", "3")
    one_line_error(status, err, "another configuration", "num_seeds: stored 2, given 3")
    status, _, err = call(run, capsys, "--resume", str(smoke_run), "--out", str(tmp_path / "x"))
    one_line_error(status, err, "exclude each other")
    (tmp_path / "config.json").write_text('{"config": {"env": "mars"}}')
    status, _, err = call(run, capsys, "--resume", str(tmp_path))
    one_line_error(status, err, "trained on 'mars'", "--import")
    (tmp_path / "config.json").write_text('{"config": {"env": "tracking", "algo": 3}}')
    status, _, err = call(run, capsys, "--resume", str(tmp_path))
    one_line_error(status, err, "config.json is unreadable")


def test_resume_refuses_checkpoints_of_another_configuration(run, smoke_run, capsys, tmp_path):
    """config.json edited after the run (here γ): the checkpoints no longer match it, so resuming
    fails at once, before anything is restored or any result file is touched."""
    copy = tmp_path / "edited"
    shutil.copytree(smoke_run, copy)
    document = json.loads((copy / "config.json").read_text())
    document["config"]["agent"]["gamma"] = 0.9
    (copy / "config.json").write_text(json.dumps(document))
    before = files_of(copy, "metrics")
    status, _, err = call(run, capsys, "--resume", str(copy), "--quiet")
    one_line_error(status, err, "another configuration", "--out")
    assert files_of(copy, "metrics") == before


def test_resume_with_the_same_options_is_accepted(run, smoke_run, capsys):
    status, out, _ = call(run, capsys, "--resume", str(smoke_run), *SMOKE)
    assert status == 0 and "final return" in out


OTHER_COMBOS = [
    ("tracking", "sac"),
    ("tracking", "dsac"),
    ("tracking", "xsac"),
    ("country_road", "sac"),
    ("country_road", "dsac"),
    ("country_road", "xsac"),
    ("country_road", "xdsac"),
]


@pytest.mark.slow
@pytest.mark.parametrize("env, algo", OTHER_COMBOS)
def test_smoke_run_of_every_env_and_algo(run, capsys, tmp_path, env, algo):
    out = tmp_path / "run"
    status, stdout, err = call(run, capsys, "--env", env, "--algo", algo, "--preset", "smoke", "--quiet",
                               "--out", str(out))  # fmt: skip
    assert status == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and "final return" in stdout
    last = json.loads((out / "metrics" / "seed_0.jsonl").read_text().splitlines()[-1])
    assert last["train/updates"] == 128 and last["train/loss_critic"] is not None


# ---------------------------------------------------------------------------------------------
# Runs that cannot hang, lie or lose work
# ---------------------------------------------------------------------------------------------


def read_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def checkpoint_steps(out: Path) -> list[int]:
    return sorted(int(p.name) for p in (out / "checkpoints" / "group_0").iterdir() if p.name.isdigit())


def test_a_diverging_run_stops_naming_seed_step_and_quantity(run, capsys, tmp_path):
    """Before: exit 0, "final return 0.000", every loss written as null. Now: exit 3 at the first
    non-finite value, one line, the last good checkpoint kept and nothing after it."""
    out = tmp_path / "diverged"
    status, _, err = call(run, capsys, *SMOKE, "--set", "actor_lr=1e4", "--set", "critic_lr=1e4",
                          "--out", str(out))  # fmt: skip
    assert status == 3, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "diverged at step" in lines[0] and "became non-finite" in lines[0]
    assert "seed 0" in lines[0] or "seed 1" in lines[0]
    assert "checkpoint at step 64 of 192 per seed is kept" in lines[0]
    assert checkpoint_steps(out) == [64]
    assert not (out / "summary.json").exists()
    first, second = read_lines(out / "metrics" / "seed_0.jsonl")
    assert first["train/loss_critic"] is None  # warm-up: no update yet, so no data
    written = {value for value in second.values() if isinstance(value, str)}  # non-finite, as text
    assert "nan" in written or "inf" in written


def test_a_second_writer_is_refused_and_a_dead_ones_lock_is_not_in_the_way(run, smoke_run, capsys, tmp_path):
    copy = tmp_path / "locked"
    shutil.copytree(smoke_run, copy)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from xrl_jax.runs.folder import RunLock; "
         "lock = RunLock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(120)", str(copy)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        before = files_of(copy, "metrics")
        status, _, err = call(run, capsys, "--resume", str(copy), "--quiet")
        one_line_error(status, err, "is in use by process", str(holder.pid))
        assert files_of(copy, "metrics") == before
    finally:
        holder.kill()
        holder.wait()
    status, out, _ = call(run, capsys, "--resume", str(copy), "--quiet")  # the holder died: no stale lock
    assert status == 0 and "final return" in out


@pytest.mark.parametrize("damage", ["delete metrics", "truncate eval"])
def test_resume_refuses_a_run_whose_history_is_gone(run, capsys, tmp_path, monkeypatch, damage):
    args = [*SMOKE, "--steps", "256", "--set", "checkpoint_interval=128", "--set", "eval_interval=128"]
    out = tmp_path / "run"
    assert run_stopped_after(run, capsys, monkeypatch, 3, *args, "--out", str(out))[0] == 1
    if damage == "delete metrics":
        (out / "metrics" / "seed_1.jsonl").unlink()
        fragments = ["metrics/seed_1.jsonl is missing"]
    else:
        (out / "eval" / "seed_0.jsonl").write_text("")
        fragments = ["eval/seed_0.jsonl lacks 1 of its 1 evaluation rows (steps 128)"]
    status, _, err = call(run, capsys, "--resume", str(out), "--quiet")
    one_line_error(status, err, "cannot resume", *fragments)


def test_leftovers_of_a_failed_start_do_not_block_a_retry(run, capsys, tmp_path):
    out = tmp_path / "retry"
    status, _, err = call(run, capsys, *SMOKE, "--set", "memory_budget_gb=0.000001", "--out", str(out))
    one_line_error(status, err, "one member needs about")  # the failed memory check left a folder...
    (out / ".config.json.tmp4242").write_text("{half")  # ...and a killed atomic write a temporary file
    status, stdout, err = call(run, capsys, *SMOKE, "--out", str(out))
    assert status == 0 and "final return" in stdout, err
    assert not (out / ".config.json.tmp4242").exists()


def test_a_full_disk_ends_in_one_line_with_the_checkpoint_intact(run, capsys, tmp_path, monkeypatch):
    import errno

    from xrl_jax.checkpoint import Checkpointer

    out = tmp_path / "full"
    original = Checkpointer.save

    def save(self, step, state, metadata):
        if step > 64:
            raise OSError(errno.ENOSPC, "No space left on device")
        original(self, step, state, metadata)

    monkeypatch.setattr(Checkpointer, "save", save)
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out))
    assert status == 1 and len(err.strip().splitlines()) == 1, err
    assert "is full" in err and f"--resume {out}" in err
    assert checkpoint_steps(out) == [64]


@pytest.mark.parametrize("write", ["results folder", "config.json", "plan.json"])
def test_a_disk_full_at_the_start_ends_in_one_line(run, capsys, tmp_path, monkeypatch, write):
    """Before: a 13-line OSError 28 traceback when the disk was full before the first result. Now
    every write of the start (the folder, config.json, plan.json) ends in one line, status 1, that
    says the disk is full and that the same command starts the run once there is space."""
    import errno
    import pathlib

    from xrl_jax.train import loop, memory

    out = tmp_path / "full"
    full = OSError(errno.ENOSPC, "No space left on device")
    if write == "results folder":
        original_mkdir = pathlib.Path.mkdir

        def mkdir(self, *args, **kwargs):
            if self == out:
                raise full
            original_mkdir(self, *args, **kwargs)

        monkeypatch.setattr(pathlib.Path, "mkdir", mkdir)
    else:
        original_write = loop.write_atomic

        def write_atomic(path, text):
            if path.name == write:
                raise full
            original_write(path, text)

        monkeypatch.setattr(loop, "write_atomic", write_atomic)
        monkeypatch.setattr(memory, "write_atomic", write_atomic)  # the plan's writer
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out))
    assert status == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"run.py: error: the disk of {out} is full (No space left on device)")
    assert "before the run wrote any results" in err and "start it again" in err


@pytest.mark.parametrize("folder", ["metrics", "checkpoints"])
def test_a_folder_made_read_only_mid_run_ends_in_one_line(run, capsys, tmp_path, monkeypatch, folder):
    """Issue 48: ``chmod -w`` of checkpoints/ or metrics/ mid-run gave a traceback of 15-79 lines (orbax
    wraps the error of its temporary folder). Now one line, status 1, saying what is kept and how to go
    on; the resume then finishes the run. (Root ignores chmod, so the refusal is raised here.)"""
    import errno

    from xrl_jax.checkpoint import Checkpointer
    from xrl_jax.train import records

    out = tmp_path / "read_only"
    if folder == "metrics":
        original_append = records.append_lines

        def append_lines(path, rows):
            if rows[0]["step"] > 64:
                raise PermissionError(errno.EACCES, "Permission denied", str(path))
            original_append(path, rows)

        monkeypatch.setattr(records, "append_lines", append_lines)
    else:
        original_save = Checkpointer.save

        def save(self, step, state, metadata):
            if step > 64:
                try:
                    os.makedirs(self.directory / f"{step}.orbax-checkpoint-tmp", exist_ok=True)
                    raise PermissionError(errno.EACCES, "Permission denied", str(self.directory))
                except PermissionError as err:
                    raise ValueError("the checkpoint could not be written") from err  # as orbax wraps it
            original_save(self, step, state, metadata)

        monkeypatch.setattr(Checkpointer, "save", save)
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out))
    assert status == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"run.py: error: cannot write {out / folder}") and "(Permission denied)" in err, err
    assert "the checkpoint at step 64 of 192 per seed is kept" in err and f"--resume {out}" in err
    monkeypatch.undo()
    status, stdout, err = call(run, capsys, "--resume", str(out), "--quiet")
    assert status == 0 and "final return" in stdout, err


def test_checkpoints_also_follow_wall_time(run, capsys, tmp_path, monkeypatch):
    """A run interrupted between step checkpoints keeps the time-based one. With a tiny
    checkpoint_minutes the first chunk's end is due; the next is not, because a time-based checkpoint
    may cost at most 2 % of the wall time (the save's duration x 50 must have passed)."""
    args = [*SMOKE, "--set", "checkpoint_interval=192"]
    original = train_mod.train
    monkeypatch.setattr(train_mod, "train", functools.partial(original, stop_after_chunks=2))
    timed, untimed = tmp_path / "timed", tmp_path / "untimed"
    assert call(run, capsys, *args, "--set", "checkpoint_minutes=1e-9", "--out", str(timed))[0] == 1
    assert call(run, capsys, *args, "--set", "checkpoint_minutes=0", "--out", str(untimed))[0] == 1
    assert checkpoint_steps(timed) == [64]
    assert checkpoint_steps(untimed) == []


def test_the_run_says_where_it_runs_and_what_it_will_cost(run, capsys, tmp_path):
    status, _, err = call(run, capsys, *SMOKE[:-1], "--out", str(tmp_path / "talk"))
    assert status == 0
    assert "backend: cpu" in err or "backend: gpu" in err
    assert "estimate: the whole run (2 seed(s) x 192 steps) takes ~" in err


def test_resume_falls_back_past_a_damaged_checkpoint_and_says_so(run, capsys, tmp_path, monkeypatch):
    """Before: 4 KB of random bytes in a data file restored silently (and the run then hung). Now the
    file digests catch it; the run says so in one line (also with --quiet) and uses the one before."""
    args = [*SMOKE, "--steps", "256", "--set", "checkpoint_interval=64"]
    out, full = tmp_path / "run", tmp_path / "full"
    assert call(run, capsys, *args, "--out", str(full))[0] == 0
    assert run_stopped_after(run, capsys, monkeypatch, 3, *args, "--out", str(out))[0] == 1
    assert checkpoint_steps(out) == [128, 192]
    data = max((p for p in (out / "checkpoints" / "group_0" / "192").rglob("*") if p.is_file()),
               key=lambda p: p.stat().st_size)  # fmt: skip
    damaged = bytearray(data.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    data.write_bytes(bytes(damaged))
    status, stdout, err = call(run, capsys, "--resume", str(out), "--quiet")
    assert status == 0 and "final return" in stdout
    assert (
        err.strip().splitlines()
        == [
            line
            for line in err.strip().splitlines()
            if "group_0/192 is damaged" in line and "step 128" in line
        ]
        and err.strip()
    )
    assert files_of(out, "metrics") == files_of(full, "metrics")  # recomputed from step 128, exactly


def test_a_disk_too_full_for_the_next_checkpoint_stops_before_orbax(run, capsys, tmp_path, monkeypatch):
    """Orbax reports a disk that fills during a save from several threads (hundreds of lines); the
    trainer checks the free space against the state's size first and stops in one line."""
    out = tmp_path / "tight"
    from xrl_jax.train import loop

    monkeypatch.setattr(loop, "disk_free_bytes", lambda folder: 40_000)
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out))
    assert status == 1, err
    assert err.strip().splitlines()[-1].startswith("run.py: error: the disk of")
    assert "40 kB free, but the checkpoint at step 64 needs up to" in err and "--resume" in err
    assert checkpoint_steps(out) == []
