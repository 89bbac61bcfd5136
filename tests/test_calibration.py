"""Calibrations (xrl_jax.train.calibrations, xrl_jax.benchmarks.calibration): what their cache key
holds and what it leaves out, atomic writes and files that are not calibrations, the time a record
predicts, and one real calibration of the trivial env, which a run of that configuration then uses
for its estimate before its first chunk."""

import json
import os
import shutil
import time

import pytest
from train_support import fast_env_registered, prepare_cache

from xrl_jax.train import calibrations as C
from xrl_jax.train import resolve_config
from xrl_jax.train.cpu_devices import HOST_DEVICE_FLAG

RATES = {"warmup_vector_step_s": 0.01, "vector_step_s": 0.1, "eval_s": 5.0, "setup_s": 20.0}


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XRL_JAX_CACHE_DIR", str(tmp_path))
    return tmp_path / "calibrations"


def quick(**overrides):
    return resolve_config("country_road", "xdsac", "quick", num_seeds=4, overrides=overrides or None)


def test_the_key_changes_with_what_shapes_a_step_and_not_with_the_rest(monkeypatch):
    base = C.calibration_key(quick(), 4, 1)
    assert C.calibration_key(quick(), 4, 1) == base
    shaping = {  # each changes the compiled chunk or the evaluation
        "actor_width": "128", "critic_width": "128", "actor_depth": "4", "critic_depth": "4",
        "batch_size": "256", "num_envs": "8", "packed_rows": "none", "dense_sets": "true",
        "eval_episodes": "20", "n_critics": "3", "fourier_scale": "none", "train_tracks": "64",
    }  # fmt: skip
    for name, value in shaping.items():
        assert C.calibration_key(quick(**{name: value}), 4, 1) != base, name
    other_run = resolve_config("country_road", "dsac", "quick", num_seeds=4)
    assert C.calibration_key(other_run, 4, 1) != base
    assert C.calibration_key(resolve_config("tracking", "xdsac", "quick", num_seeds=4), 4, 1) != base
    assert C.calibration_key(quick(), 2, 1) != base and C.calibration_key(quick(), 4, 2) != base
    same = {  # host-only settings, the run's length and seeds, traced hyper-parameters
        "max_group_size": "1", "memory_budget_gb": "3", "checkpoint_minutes": "5", "num_devices": "2",
        "seed": "7", "total_steps": "160000", "warmup_steps": "2000", "buffer_size": "5000",
        "log_interval": "2000", "eval_interval": "80000", "checkpoint_interval": "20000",
        "actor_lr": "0.001", "gamma": "0.9", "kappa": "0.01", "track_seed": "5", "reinit_steps": "100000",
    }  # fmt: skip
    for name, value in same.items():
        assert C.calibration_key(quick(**{name: value}), 4, 1) == base, name
    assert C.calibration_key(quick().replace(num_seeds=8), 4, 1) == base
    swept = resolve_config("country_road", "xdsac", "quick", num_seeds=2, sweep=(("kappa", (0.0, 0.1)),))
    assert C.calibration_key(swept, 4, 1) == base  # its 4 members on one device, as 4 seeds
    # The machine: the code, the CPU, the compile settings, but not the host split or its collectives.
    monkeypatch.setenv("XLA_FLAGS", f"{os.environ.get('XLA_FLAGS', '')} --{HOST_DEVICE_FLAG}=2")
    assert C.calibration_key(quick(), 4, 1) == base
    monkeypatch.setenv("XLA_FLAGS", f"{os.environ['XLA_FLAGS']} --xla_cpu_enable_fast_math=true")
    assert C.calibration_key(quick(), 4, 1) != base
    monkeypatch.undo()
    monkeypatch.setattr(C, "cpu_model", lambda: "another CPU")
    assert C.calibration_key(quick(), 4, 1) != base
    monkeypatch.setattr(C, "code_digest", lambda: "other code")
    assert C.calibration_key(quick(), 4, 1)["machine"]["code"] == "other code"


def test_a_calibration_is_stored_atomically_and_read_back(cache, monkeypatch):
    key = C.calibration_key(quick(), 4, 1)
    path = C.store_calibration(key, dict(RATES, created="2026-01-02"))
    assert path.parent == cache and C.load_calibration(key) == dict(RATES, created="2026-01-02")

    # A write that fails half-way leaves the old file whole, and no temporary file behind.
    def refuse(*_):
        raise OSError("disk gone")

    with monkeypatch.context() as patch, pytest.raises(OSError, match="disk gone"):
        patch.setattr(os, "replace", refuse)
        C.store_calibration(key, dict(RATES, eval_s=1.0))
    assert C.load_calibration(key)["eval_s"] == RATES["eval_s"]
    assert [p.name for p in cache.iterdir()] == [path.name]
    assert C.load_calibration(C.calibration_key(quick(), 2, 1)) is None  # none stored: no warning


@pytest.mark.parametrize(
    ("content", "why"),
    [
        ("{not json", "unreadable"),
        (b"\xff\xfe\x00", "unreadable"),
        ('["a list"]', "another calibration"),
        ("FOREIGN", "another calibration"),  # a whole calibration, but of another key
        ("NO RATES", "lacks the measured rates"),
    ],
)
def test_a_file_that_is_not_this_calibration_is_skipped_with_one_warning(cache, content, why):
    key = C.calibration_key(quick(), 4, 1)
    path = C.key_path(key)
    path.parent.mkdir(parents=True)
    if content == "FOREIGN":
        content = json.dumps({"key": C.calibration_key(quick(), 2, 1), "record": RATES})
    elif content == "NO RATES":
        content = json.dumps({"key": key, "record": {"vector_step_s": 0.1}})
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    warnings = []
    assert C.load_calibration(key, warn=warnings.append) is None
    assert len(warnings) == 1 and why in warnings[0] and str(path) in warnings[0]
    C.store_calibration(key, RATES)  # a new calibration replaces it
    assert C.load_calibration(key, warn=warnings.append) == RATES and len(warnings) == 1
    assert C.cached_calibrations() == [RATES]


def test_the_predicted_time_counts_steps_evaluations_and_one_compilation():
    cfg = resolve_config("tracking", "sac", "quick", num_seeds=2, total_steps=1000).replace(
        warmup_steps=200, log_interval=100, eval_interval=500, checkpoint_interval=500
    )
    # 50 warm-up vector steps (200 steps of 4 envs), 200 updating ones, evaluations at 500 and 1,000.
    whole = C.predicted_seconds(cfg, RATES, [0])
    assert whole["training_s"] == pytest.approx(50 * 0.01 + 200 * 0.1)
    assert whole["evaluation_s"] == pytest.approx(2 * 5.0) and whole["setup_s"] == 20.0
    assert whole["total_s"] == pytest.approx(20.5 + 10.0 + 20.0)
    # Two groups, the first done, the second at its checkpoint of step 300 (past the warm-up).
    rest = C.predicted_seconds(cfg, RATES, [1000, 300])
    assert rest["total_s"] == pytest.approx(700 / 4 * 0.1 + 2 * 5.0 + 20.0)
    assert C.predicted_seconds(cfg, RATES, [1000, 1000])["total_s"] == 0.0
    assert C.members_per_device([[0, 1, 2], [3, 4]], 2) == 2  # 3 members padded to 4 over 2 devices


def test_a_cached_calibration_is_told_before_the_chunks_and_its_long_run_warning_once(cache):
    from xrl_jax.train.clock import RunClock
    from xrl_jax.train.console import Console

    cfg = quick()  # 4 seeds, 320k steps: 80k vector steps at 2 s, evaluations and setup: 44.3 h, beyond a day
    C.store_calibration(C.calibration_key(cfg, 4, 1), dict(RATES, vector_step_s=2.0, created="2026-01-02T03"))
    lines, warnings = [], []
    console = Console(
        cfg, lines.append, warnings.append, enabled=False, backend="cpu", start_time=time.perf_counter()
    )
    console.estimate_calibrated([[0, 1, 2, 3]], 1, 0, 0)
    console.estimate_calibrated([[0, 1, 2, 3]], 1, 0, 0)  # once a session
    assert len(lines) == 1 and "(by this machine's calibration of 2026-01-02;" in lines[0]
    assert "takes ~44.3 h on cpu" in lines[0] and len(warnings) == 1 and "--preset quick" in warnings[0]
    clock = RunClock(cfg, num_groups=1)
    clock.start_group()
    for chunk in range(1, 4):
        clock.observe_chunk(chunk, 200.0)
        console.estimate_once(clock, 0, chunk)
    assert len(lines) == 2 and "calibration" not in lines[1] and len(warnings) == 1  # warned already
    # Another configuration (2 members per device) has no calibration: nothing is told.
    other = Console(
        cfg, lines.append, warnings.append, enabled=False, backend="cpu", start_time=time.perf_counter()
    )
    other.estimate_calibrated([[0, 1], [2, 3]], 1, 0, 0)
    assert len(lines) == 2


@pytest.mark.slow  # a real calibration and a run (~20 s each on 2 cores): the default tier's budget
def test_a_real_calibration_is_cached_and_a_run_tells_its_cost_before_its_first_chunk(tmp_path):
    """The trivial env at the smoke preset: a calibration in this process (its devices as they are),
    then a run of the same configuration, which finds it and tells the estimate before compiling."""
    from xrl_jax.benchmarks.calibration import calibrate_and_store
    from xrl_jax.train import train

    prepare_cache(tmp_path / "cache")
    with fast_env_registered() as env:
        cfg = resolve_config(env, "xdsac", "smoke", num_seeds=2, overrides={"max_group_size": "1"})
        record = calibrate_and_store(cfg, 1, 1)
        assert 0 < record["warmup_vector_step_s"] <= record["measured"]["updating_vector_step_s"]
        assert (
            record["updates_per_vector_step"] == cfg.num_envs == record["measured"]["updates_per_vector_step"]
        )
        assert record["vector_step_s"] == pytest.approx(record["measured"]["updating_vector_step_s"])
        assert record["eval_s"] > 0 and record["setup_s"] > 0 and record["devices"] == 1
        assert record["others_cpu_share"] is None or 0.0 <= record["others_cpu_share"] <= 1.0
        assert C.load_calibration(C.calibration_key(cfg, 1, 1)) == record
        lines = []
        train(cfg, tmp_path / "run", progress=False, log=lines.append, stop_after_chunks=1)
        (told,) = [i for i, line in enumerate(lines) if "by this machine's calibration of" in line]
        assert lines[told].startswith("estimate: the whole run (2 seed(s) x 192 steps) takes ~")
        assert "compiling the training chunk ..." in lines[told + 1 :]
        # Without a calibration of the run's configuration, nothing is told before the chunks.
        shutil.rmtree(C.cache_folder())
        lines.clear()
        train(cfg, tmp_path / "other", progress=False, log=lines.append, stop_after_chunks=1)
        assert not any("calibration" in line for line in lines)


def test_a_calibration_in_a_child_process_that_fails_says_why_in_one_line():
    """The child knows only the built-in scenarios: a user's env registered here is unknown there."""
    from xrl_jax.benchmarks.calibration import CalibrationError, calibrate_in_child

    with fast_env_registered() as env:
        cfg = resolve_config(env, "dsac", "smoke")
    with pytest.raises(CalibrationError, match="fast"):
        calibrate_in_child(cfg, 1, 1)


@pytest.mark.slow  # a child process compiles the Intersection's smoke chunk (~30 s)
def test_a_calibration_in_a_child_process_splits_its_host_as_asked(tmp_path, monkeypatch):
    from xrl_jax.benchmarks.calibration import calibrate_in_child

    monkeypatch.setenv("XRL_JAX_CACHE_DIR", str(tmp_path))
    cfg = resolve_config("intersection", "dsac", "smoke", num_seeds=2)
    record = calibrate_in_child(cfg, 1, 2)
    assert record["devices"] == record["devices_in_process"] == 2 and record["note"] == ""
    assert record["vector_step_s"] > record["warmup_vector_step_s"] > 0
    assert not (tmp_path / "calibrations").exists()  # the caller stores it, under its own key
