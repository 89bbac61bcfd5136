"""The results folder: metric encoding, the writer's lock, history checks, leftovers, resources."""

import errno
import json

import pytest

from xrl_jax import resources
from xrl_jax.runs.folder import (
    RunFolderError,
    RunLock,
    check_history,
    encode_metric,
    holds_results,
    is_disk_full,
    remove_leftovers,
    truncate_lines,
)
from xrl_jax.train import resolve_config
from xrl_jax.train.clock import CHECKPOINT_TIME_SHARE, RunClock


def test_no_data_and_not_finite_are_different_values():
    assert encode_metric(float("nan")) == "nan"
    assert encode_metric(float("inf")) == "inf" and encode_metric(float("-inf")) == "-inf"
    assert encode_metric(1.5) == 1.5 and encode_metric([1.0, float("nan")]) == [1.0, "nan"]
    assert json.loads(json.dumps({"x": encode_metric(float("nan"))})) == {"x": "nan"}  # strict JSON


def test_the_lock_is_exclusive_even_within_a_process(tmp_path):
    """The trainer takes the folder's lock once; a second taker, here or elsewhere, gets one line."""
    with RunLock(tmp_path):
        assert "process" in (tmp_path / ".lock").read_text()
        with pytest.raises(RunFolderError, match=r"^results folder .* is in use by process \d+ on "):
            RunLock(tmp_path).acquire()
    # released: another open file description can take it
    import fcntl

    with open(tmp_path / ".lock") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def test_history_checks_name_what_is_missing(tmp_path):
    path = tmp_path / "metrics" / "seed_0.jsonl"
    path.parent.mkdir()
    with pytest.raises(RunFolderError, match=r"metrics/seed_0\.jsonl is missing"):
        check_history(path, [64, 128], "metric")
    path.write_text('{"step": 64}\n{"step": 128, "cut')
    with pytest.raises(RunFolderError, match=r"lacks 1 of its 2 metric rows \(steps 128\)"):
        check_history(path, [64, 128], "metric")
    check_history(path, [64], "metric")
    truncate_lines(path, 64)
    assert path.read_text() == '{"step": 64}\n'


def test_a_failed_start_leaves_a_folder_that_holds_no_results(tmp_path):
    for name in ("metrics", "eval", "checkpoints"):
        (tmp_path / name).mkdir()
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "plan.json").write_text("{}")
    (tmp_path / ".config.json.tmp123").write_text("{")
    assert not holds_results(tmp_path)
    remove_leftovers(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoints", "config.json", "eval", "metrics",
                                                           "plan.json"]  # fmt: skip
    (tmp_path / "metrics" / "seed_0.jsonl").write_text('{"step": 64}\n')
    assert holds_results(tmp_path)


def test_disk_full_is_recognised_through_wrapping():
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as inner:
            raise RuntimeError("orbax: save failed") from inner
    except RuntimeError as outer:
        assert is_disk_full(outer)
    assert not is_disk_full(OSError(errno.EACCES, "Permission denied"))


@pytest.mark.parametrize("version", ["v1", "v2"])
def test_the_memory_budget_reads_the_container_limit(tmp_path, version):
    """Before: 90 % of the host's free RAM, and a run in an 8 GB container was OOM-killed silently."""
    if version == "v2":
        (tmp_path / "proc").write_text("0::/job/step\n")
        folder = tmp_path / "cg" / "job"
        limit, usage = "memory.max", "memory.current"
    else:
        (tmp_path / "proc").write_text("4:memory:/job/step\n3:cpu:/\n")
        folder = tmp_path / "cg" / "memory" / "job"
        limit, usage = "memory.limit_in_bytes", "memory.usage_in_bytes"
    (folder / "step").mkdir(parents=True)
    (folder / "step" / limit).write_text("max\n" if version == "v2" else "9223372036854771712\n")
    (folder / limit).write_text(str(8 * 10**9))  # the limit sits on the parent group
    (folder / usage).write_text(str(3 * 10**9))
    headroom, description = resources.cgroup_memory_headroom(tmp_path / "cg", tmp_path / "proc")
    assert headroom == 5 * 10**9 and "8.0 GB" in description
    assert resources.cgroup_memory_headroom(tmp_path / "cg", tmp_path / "absent") is None


def test_host_memory_takes_the_smaller_of_ram_and_the_container(monkeypatch):
    monkeypatch.setattr(resources, "cgroup_memory_headroom", lambda: (1000, "container memory limit"))
    assert resources.host_memory_available() == (1000, "container memory limit")


def test_time_based_checkpoints_cost_at_most_two_percent():
    cfg = resolve_config("tracking", "xdsac", "smoke", overrides={"checkpoint_minutes": "1"})
    clock = RunClock(cfg, num_groups=1)
    clock.saved(seconds=10.0)  # a slow save: the next may come only after 10 s / 2 % = 500 s
    clock.last_save -= 499.0
    assert not clock.checkpoint_due_by_time()
    clock.last_save -= 2.0
    assert clock.checkpoint_due_by_time() and CHECKPOINT_TIME_SHARE == 0.02
    clock.saved(seconds=0.1)  # a fast save: the 1-minute interval rules
    clock.last_save -= 59.0
    assert not clock.checkpoint_due_by_time()
    clock.last_save -= 2.0
    assert clock.checkpoint_due_by_time()
    assert not RunClock(cfg.replace(checkpoint_minutes=0.0), 1).checkpoint_due_by_time()


def test_sizes_read_at_any_scale():
    assert [resources.format_bytes(n) for n in (512, 40_000, 1.234e7, 4.56e9, 1.2e12)] == [
        "512 B", "40 kB", "12.3 MB", "4.56 GB", "1200 GB",
    ]  # fmt: skip
    assert [resources.format_duration(s) for s in (42, 780, 5.2 * 3600, 23 * 86400)] == [
        "42 s", "13 min", "5.2 h", "23 days",
    ]  # fmt: skip


def test_the_folders_documents_are_read_with_one_line_errors(tmp_path):
    """A garbage plan.json or config.json (a papercut: 34-line JSONDecodeError tracebacks) is one
    RunFolderError line naming the file; a folder without a plan is one group on one device."""
    from xrl_jax.runs.folder import read_checkpoint_plan, read_run_config

    assert read_checkpoint_plan(tmp_path, 3) == ([[0, 1, 2]], 1)
    (tmp_path / "plan.json").write_text("{not json")
    with pytest.raises(RunFolderError, match=r"plan\.json is unreadable \(the run's seed groups\)") as err:
        read_checkpoint_plan(tmp_path, 3)
    assert "\n" not in str(err.value)
    (tmp_path / "plan.json").write_text('{"groups": 3}')
    with pytest.raises(RunFolderError, match=r"plan\.json does not describe the seed groups"):
        read_checkpoint_plan(tmp_path, 3)
    (tmp_path / "plan.json").write_text('{"groups": [[0, 1], [2]], "devices": 2}')
    assert read_checkpoint_plan(tmp_path, 3) == ([[0, 1], [2]], 2)
    with pytest.raises(RunFolderError, match=r"is not a results folder \(no config\.json\)"):
        read_run_config(tmp_path)
    (tmp_path / "config.json").write_text("[1, 2]")
    with pytest.raises(RunFolderError, match=r"config\.json is not a JSON object"):
        read_run_config(tmp_path)
    (tmp_path / "config.json").write_text('{"config": {"env": "nowhere"}}')
    with pytest.raises(RunFolderError, match=r"trained on 'nowhere', an env this process has not registered"):
        read_run_config(tmp_path)
    (tmp_path / "config.json").write_text('{"config": {"env": "tracking"}}')
    with pytest.raises(RunFolderError, match=r"config\.json is unreadable or from another version"):
        read_run_config(tmp_path)
