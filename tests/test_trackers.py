"""``run.py --log tensorboard|wandb``: the trackers receive every record of the run folder, read back
(TensorBoard's EventAccumulator, W&B's transaction logs as wandb's protocol buffers); a
resumed run continues the same tracker runs and sends each step once; a failing tracker is dropped and
the run finishes; a missing extra fails in one line before anything runs."""

import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import fast_env
import pytest
from train_support import (
    FAST_ENV_MODULE,
    call,
    fast_env_registered,
    load_script,
    one_line_error,
    prepare_cache,
)

from xrl_jax import train as train_mod
from xrl_jax.runs import trackers as trackers_mod
from xrl_jax.runs import wandb_log

pytest.importorskip(
    "tensorboard", reason="the tensorboard extra is not installed (pip install -e '.[tensorboard]')"
)
wandb = pytest.importorskip("wandb", reason="the wandb extra is not installed (pip install -e '.[wandb]')")

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# 192 steps in three chunks of 64, each evaluated and checkpointed, on the trivial env of the host-side
# tests (tests/fast_env.py): what the trackers receive does not depend on the env.
SMOKE = ["--env", fast_env.NAME, "--algo", "xdsac", "--preset", "smoke", "--seeds", "2", "--quiet",
         "--set", "checkpoint_interval=64", "--set", "eval_interval=64"]  # fmt: skip


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    with fast_env_registered():
        yield load_script("run", "run_trackers_cli")


@pytest.fixture(autouse=True)
def offline_wandb(monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_PROJECT", "xrl-jax-tests")


def jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def expected_scalars(out: Path, stem: str) -> dict[str, dict[int, float]]:
    """What the run folder holds for member ``stem``, as tracker scalars by tag and step."""
    expected: dict[str, dict[int, float]] = {}
    for sub, prefix in (("metrics", ""), ("eval", "eval/")):
        for row in jsonl(out / sub / f"{stem}.jsonl"):
            for tag, value in trackers_mod.scalar_values(row, prefix).items():
                expected.setdefault(tag, {})[row["step"]] = value
    return expected


def tensorboard_scalars(folder: Path) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def wandb_records(out: Path, run_id: str) -> tuple[list[dict], dict, int]:
    """The history rows, config and number of transaction logs of W&B run ``run_id`` under ``out``,
    read with wandb's own protocol buffers (the log's framing: :mod:`xrl_jax.runs.wandb_log`, since
    wandb 0.30 has no reader of its own)."""
    from wandb.proto import wandb_internal_pb2

    history, config, logs = [], {}, 0
    for log in wandb_log.run_logs(out, run_id):
        logs += 1
        for data in wandb_log.read_records(log):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(data)
            kind = record.WhichOneof("record_type")
            if kind == "history":
                items = record.history.item
                history.append(
                    {item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in items}
                )
            elif kind == "run":
                config |= {item.key: json.loads(item.value_json) for item in record.run.config.update}
    return history, config, logs


def assert_close(actual: float, expected: float) -> None:
    """TensorBoard keeps float32 (a relative 2**-24); W&B keeps the JSON double; nan equals nan."""
    assert actual == pytest.approx(expected, rel=2**-23, nan_ok=True)


def assert_tensorboard_holds_the_folder(out: Path) -> None:
    for stem in ("seed_0", "seed_1"):
        got = tensorboard_scalars(out / "tensorboard" / stem)
        expected = expected_scalars(out, stem)
        assert set(got) == set(expected)
        for tag, by_step in expected.items():
            assert [step for step, _ in got[tag]] == sorted(by_step), tag  # every step once
            for step, value in got[tag]:
                assert_close(value, by_step[step])
    summary = json.loads((out / "summary.json").read_text())
    curve = tensorboard_scalars(out / "tensorboard" / "iqm")
    for point in summary["curve"]:
        for key, stats in point.items():
            if key != "step":
                assert_close(dict(curve[f"iqm/{key}"])[point["step"]], stats["estimate"])
                assert_close(dict(curve[f"iqm/{key}_ci_low"])[point["step"]], stats["low"])
    events = EventAccumulator(str(out / "tensorboard" / "seed_0"))
    events.Reload()
    assert "_hparams_/session_start_info" in events.Tags()["tensors"]


def assert_wandb_holds_the_folder(out: Path, sessions: int) -> None:
    ids = json.loads((out / "trackers.json").read_text())["wandb"]["ids"]
    assert set(ids) == {"seed_0", "seed_1", "iqm"}
    for stem in ("seed_0", "seed_1"):
        history, config, logs = wandb_records(out, ids[stem])
        assert logs == sessions  # one transaction log per session, all under the member's one run id
        assert config["agent.actor_lr"] > 0 and config["seed"] == int(stem[-1])
        expected = expected_scalars(out, stem)
        steps = [row["_step"] for row in history]
        assert steps == sorted(set(steps))  # every step once, in order
        for tag, by_step in expected.items():
            got = {row["_step"]: row[tag] for row in history if tag in row}
            assert set(got) == set(by_step), tag
            for step, value in got.items():
                assert_close(float(value), by_step[step])
    history, _, _ = wandb_records(out, ids["iqm"])
    assert any("iqm/avg_return" in row for row in history)


def test_both_trackers_hold_every_record_of_the_folder(run, capsys, tmp_path):
    out = tmp_path / "run"
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out), "--log", "tensorboard", "--log", "wandb")
    assert status == 0, err
    assert_tensorboard_holds_the_folder(out)
    assert_wandb_holds_the_folder(out, sessions=1)


def test_a_resumed_run_continues_its_tracker_runs(run, capsys, tmp_path, monkeypatch):
    """Three sessions of one chunk each: both trackers, then TensorBoard only, then both. TensorBoard
    holds every step once over its three event files; W&B continues each member's run in the third
    session (a second transaction log under the same id) and receives there, from the files, the
    chunk that the second session trained without it."""
    out = tmp_path / "run"
    original = train_mod.train
    monkeypatch.setattr(train_mod, "train", functools.partial(original, stop_after_chunks=1))
    both, tensorboard = ["--log", "tensorboard", "--log", "wandb"], ["--log", "tensorboard"]
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out), *both)
    assert status == 1 and f"--resume {out} --log tensorboard --log wandb" in err  # the --log kept
    status, _, err = call(run, capsys, "--resume", str(out), "--quiet", *tensorboard)
    assert status == 1 and f"--resume {out} --log tensorboard\n" in err
    monkeypatch.setattr(train_mod, "train", original)
    status, _, err = call(run, capsys, "--resume", str(out), "--quiet", *both)
    assert status == 0, err
    assert len(list((out / "tensorboard" / "seed_0").glob("events.out.tfevents.*"))) == 3
    assert_tensorboard_holds_the_folder(out)
    assert_wandb_holds_the_folder(out, sessions=2)


def test_a_failing_tracker_is_dropped_and_the_run_finishes(run, capsys, tmp_path, monkeypatch):
    def broken(self, run_name, step, values):
        raise OSError("No space left on device")

    monkeypatch.setattr(trackers_mod.TensorBoardTracker, "log", broken)
    out = tmp_path / "run"
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out), "--log", "tensorboard")
    assert status == 0
    warnings = [line for line in err.splitlines() if "tensorboard tracker failed" in line]
    assert len(warnings) == 1 and "No space left on device" in warnings[0]
    assert json.loads((out / "summary.json").read_text())["complete"]


def test_a_missing_extra_fails_in_one_line_before_anything_runs(run, capsys, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "wandb", None)  # as if the extra were not installed
    out = tmp_path / "run"
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out), "--log", "wandb")
    one_line_error(status, err, "--log wandb", "pip install 'xrl-jax[wandb]'")
    assert not out.exists()
    status, _, err = call(run, capsys, *SMOKE, "--out", str(out), "--log", "mlflow")
    assert status == 2 and "invalid choice" in err


def test_an_offline_wandb_run_reports_to_no_error_service(monkeypatch):
    """Issue 48: W&B printed three retry warnings of its error service (sentry) in offline runs."""
    monkeypatch.setenv("WANDB_ERROR_REPORTING", "unset")  # undone after the test, like the lines below
    monkeypatch.delenv("WANDB_ERROR_REPORTING")
    monkeypatch.setenv("WANDB_MODE", "online")
    trackers_mod.check_trackers(["wandb"])
    assert "WANDB_ERROR_REPORTING" not in os.environ
    monkeypatch.setenv("WANDB_MODE", "offline")
    trackers_mod.check_trackers(["wandb"])
    assert not wandb.env.error_reporting_enabled()  # wandb's own switch, read as its service starts


def test_tracker_scalars_keep_non_finite_values_and_skip_the_rest():
    row = {"step": 5, "seed": 0, "point": 0, "sweep": {}, "a/x": 1, "a/nan": "nan", "a/none": None,
           "episode_returns": [1.0, 2.0], "a/inf": "-inf"}  # fmt: skip
    values = trackers_mod.scalar_values(row, "eval/")
    assert set(values) == {"eval/a/x", "eval/a/nan", "eval/a/inf"}
    assert values["eval/a/inf"] == float("-inf") and values["eval/a/nan"] != values["eval/a/nan"]


@pytest.mark.slow  # a killed subprocess (~21 s); test_what_a_tracker_holds_is_not_sent_again runs by default
def test_a_killed_session_loses_no_wandb_row(run, capsys, tmp_path):
    """Issue 48 (b): W&B's service writes its transaction log in 32 KiB blocks and completes it when a
    run finishes, so a ``kill -9`` lost the rows of the last seconds; trackers.json had marked them
    sent and the resume never sent them again. Now the resume reads W&B's logs back and sends what
    they lack: W&B holds every row of the folder, each step once."""
    out = tmp_path / "run"
    args = [*SMOKE, "--steps", "640", "--out", str(out), "--log", "wandb",  # 10 chunks
            "--import", FAST_ENV_MODULE]  # fmt: skip
    # A process of its own, as a user's killed run: not attached to this one's W&B service.
    env = {k: v for k, v in os.environ.items() if k != "WANDB_SERVICE"} | {
        "PYTHONPATH": os.pathsep.join(sys.path)
    }
    child = subprocess.Popen([sys.executable, str(ROOT / "experiments" / "run.py"), *args], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline, metrics = time.monotonic() + 300, out / "metrics" / "seed_0.jsonl"
        while child.poll() is None and time.monotonic() < deadline:
            if metrics.exists() and len(metrics.read_text().splitlines()) >= 3:
                break
            time.sleep(0.1)
        assert child.poll() is None, child.communicate()[1]
    finally:
        child.kill()  # SIGKILL: W&B's service loses what it had not written
        child.wait()
    ids = json.loads((out / "trackers.json").read_text())["wandb"]["ids"]
    assert len(wandb_records(out, ids["seed_0"])[0]) < len(jsonl(metrics))  # rows W&B's disk lacks
    status, _, err = call(run, capsys, "--resume", str(out), "--quiet", "--log", "wandb")
    assert status == 0, err
    assert_wandb_holds_the_folder(out, sessions=2)


class _Recording:
    """A tracker that records what it receives; it holds ``held`` of every run from an earlier session."""

    held = -1
    received: dict[str, list[int]]

    def __init__(self, out, group, state):
        self.received = _Recording.received = {}

    def held_step(self, run):
        return self.held

    def start(self, run, hparams):
        self.received[run] = []

    def log(self, run, step, values):
        self.received[run].append(step)

    def flush(self):
        return True

    def close(self):
        pass


def test_what_a_tracker_holds_is_not_sent_again(tmp_path, monkeypatch):
    """The other half of (b): rows that reached the tracker's disk before the kill are not sent twice,
    whatever trackers.json says; and trackers.json marks what a flush put on disk."""
    from xrl_jax.config import resolve_config
    from xrl_jax.train.records import Progress

    monkeypatch.setitem(trackers_mod._BACKENDS, "recording", _Recording)
    monkeypatch.setattr(_Recording, "held", 128)
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2)
    for stem in ("seed_0", "seed_1"):
        (tmp_path / "metrics").mkdir(exist_ok=True)
        rows = [{"step": s, "seed": int(stem[-1]), "point": 0, "sweep": {}, "x": s} for s in (64, 128, 192)]
        (tmp_path / "metrics" / f"{stem}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    mirror = trackers_mod.TrackerMirror(tmp_path, cfg, ["recording"])
    line = {"step": 256, "seed": 0, "point": 0, "sweep": {}, "x": 1.0}
    mirror(Progress(step=256, group=0, metrics=((0, line), (1, line | {"seed": 1}))))
    mirror.close()
    assert _Recording.received == {"seed_0": [192, 256], "seed_1": [192, 256]}
    sent = json.loads((tmp_path / "trackers.json").read_text())["recording"]["sent"]
    assert sent == {"seed_0": {"metrics": 256}, "seed_1": {"metrics": 256}}
