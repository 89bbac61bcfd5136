"""SIGINT/SIGTERM: the stop controller's decisions, a real signal in-process, and the CLI end to end."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from train_support import FAST_ENV_ARGS, prepare_cache

from xrl_jax.interrupts import StopController, exit_status

ROOT = Path(__file__).resolve().parents[1]


class Exited(Exception):
    pass


def controller(grace_s=30.0):
    """A controller whose hard exit raises instead of ending the test process."""
    messages = []

    def hard_exit(status):
        raise Exited(status)

    return StopController(grace_s, "resume-command", messages.append, hard_exit), messages


def test_start_up_ends_at_once_saying_what_is_kept():
    stop, messages = controller()
    stop.keep("the checkpoint at step 64 of 192 per seed is kept")
    with pytest.raises(Exited) as info:
        stop.handle(signal.SIGINT)
    assert info.value.args == (130,)
    assert "SIGINT: stopping now; the checkpoint at step 64" in messages[0]
    assert "continue with: resume-command" in messages[0]


def test_a_chunk_that_ends_within_the_grace_is_finished_and_a_second_signal_stops_at_once():
    stop, messages = controller(grace_s=30.0)
    stop.training(5.0)
    stop.handle(signal.SIGTERM)  # no exit: the host loop stops at the boundary
    assert stop.requested == signal.SIGTERM and "stopping after the current chunk" in messages[0]
    with pytest.raises(Exited) as info:
        stop.handle(signal.SIGINT)
    assert info.value.args == (exit_status(signal.SIGINT),) and "(again)" in messages[1]


def test_a_long_chunk_or_an_unknown_one_is_not_waited_for():
    for expected in (3600.0, None):
        stop, messages = controller(grace_s=30.0)
        stop.training(expected)
        with pytest.raises(Exited) as info:
            stop.handle(signal.SIGTERM)
        assert info.value.args == (143,) and "stopping now" in messages[0]


def test_a_real_signal_reaches_the_watcher_and_never_raises_in_the_main_thread():
    """Before: Ctrl-C became a KeyboardInterrupt wherever the main thread was (swallowed in a gc
    callback, or a crash during XLA's teardown). Now the main thread is never interrupted."""
    # What was there before is restored: Python's default handler, or SIG_IGN when the tests run
    # in the background of a non-interactive shell (which starts them with SIGINT ignored).
    before = signal.getsignal(signal.SIGINT)
    stop, messages = controller(grace_s=30.0)
    with stop:
        stop.training(1.0)
        os.kill(os.getpid(), signal.SIGINT)
        deadline = time.monotonic() + 10
        while stop.requested is None and time.monotonic() < deadline:
            time.sleep(0.01)
    assert stop.requested == signal.SIGINT and "stopping after the current chunk" in messages[0]
    assert signal.getsignal(signal.SIGINT) is before  # restored on exit


# ---------------------------------------------------------------------------------------------
# The CLI in a subprocess, as a user or a cluster scheduler signals it
# ---------------------------------------------------------------------------------------------


def start_run(tmp_path, out, *extra, grace="30"):
    prepare_cache(tmp_path / "cache")
    env = {**os.environ, "XRL_JAX_CACHE_DIR": str(tmp_path / "cache"), "XRL_JAX_STOP_GRACE_S": grace}
    # The trivial env of the host-side tests (tests/fast_env.py): signals reach the host loop, not the env.
    args = [sys.executable, str(ROOT / "experiments" / "run.py"), *FAST_ENV_ARGS, "--algo", "xdsac",
            "--preset", "smoke", "--out", str(out), *extra]  # fmt: skip
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def assert_clean_end(process, status, timeout=60):
    _, err = process.communicate(timeout=timeout)
    assert process.returncode == status, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    return err


def test_sigint_during_start_up_ends_the_run_at_once(tmp_path):
    process = start_run(tmp_path, tmp_path / "run", "--quiet")
    time.sleep(1.5)  # importing jax and building the trainer: the place where Ctrl-C used to be lost
    process.send_signal(signal.SIGINT)
    tic = time.monotonic()
    err = assert_clean_end(process, 130, timeout=30)
    assert time.monotonic() - tic < 10
    assert "SIGINT" in err and "nothing has been trained yet" in err


def test_sigterm_during_training_checkpoints_at_the_chunk_boundary(tmp_path):
    out = tmp_path / "run"
    process = start_run(tmp_path, out, "--quiet", "--steps", "64000", "--set", "checkpoint_interval=64000")
    metrics = out / "metrics" / "seed_0.jsonl"
    deadline = time.monotonic() + 240
    while not (metrics.exists() and len(metrics.read_text().splitlines()) >= 3):
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.1)
    process.send_signal(signal.SIGTERM)
    err = assert_clean_end(process, 143)
    assert "stopped by SIGTERM" in err and f"--resume {out}" in err
    steps = sorted(int(p.name) for p in (out / "checkpoints" / "group_0").iterdir() if p.name.isdigit())
    last_line_step = int(metrics.read_text().splitlines()[-1].split('"step": ')[1].split(",")[0])
    assert steps[-1] == last_line_step  # the checkpoint was written at the boundary the run stopped at
    assert f"checkpoint at step {last_line_step:,} of 64,000" in err
