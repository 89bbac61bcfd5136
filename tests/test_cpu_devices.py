"""Every core by default: the rule that splits a CPU host into XLA devices, and a run that uses it and
whose resume splits the host as the run did, whatever the machine it resumes on."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
from train_support import DATA, FAST_ENV_ARGS, FAST_ENV_MODULE

from xrl_jax.config import resolve_config
from xrl_jax.train import cpu_devices


def config(seeds: int, **overrides):
    return resolve_config(
        "tracking", "xdsac", "quick", num_seeds=seeds, overrides={k: str(v) for k, v in overrides.items()}
    )


@pytest.mark.parametrize(
    ("seeds", "cores", "devices"),
    [
        (1, 2, 1),  # one member cannot be split
        (2, 2, 2),
        (4, 2, 2),
        (3, 2, 1),  # 3 members over 2 devices: a padded fourth would cost a core's time for nothing
        (6, 4, 3),  # the most devices that the members fill evenly
        (8, 16, 8),  # never more devices than members
        (20, 1, 1),
    ],
)
def test_one_device_per_core_that_the_members_fill_evenly(seeds, cores, devices):
    assert cpu_devices.auto_cpu_devices(config(seeds), cores) == devices


def test_intersection_members_get_a_device_each_up_to_two_per_core():
    """Members sharing a device wait for each other's vehicles: the Intersection splits finer."""
    intersection = resolve_config("intersection", "xdsac", "quick", num_seeds=4)
    assert cpu_devices.auto_cpu_devices(intersection, 2) == 4
    assert cpu_devices.auto_cpu_devices(intersection.replace(num_seeds=20), 2) == 4  # 4 of 5 members
    assert cpu_devices.devices_for_members(6, 2, per_core=2) == 3


def test_members_trained_one_group_at_a_time_are_what_is_split():
    assert cpu_devices.auto_cpu_devices(config(4, max_group_size=1), 2) == 1
    assert cpu_devices.auto_cpu_devices(config(8, max_group_size=2), 4) == 2


def test_the_users_xla_flag_stands(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_foo=1 --xla_force_host_platform_device_count=3")
    assert cpu_devices.flagged_host_devices() == 3
    assert not cpu_devices.split_cpu_host(2)  # nothing asked of JAX


def test_a_started_backend_is_left_alone(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    import jax

    jax.devices()  # the backend runs in this test process
    assert not cpu_devices.split_cpu_host(2)


# A fresh process (JAX's backend not started) that believes it has 2 cores: a new run of 2 seeds on
# the trivial env splits the host into 2 devices and records it; the resume in another fresh process,
# believing it has 1 core, splits the host as the run did.
CHILD = textwrap.dedent(
    """
    import json, sys
    sys.path.insert(0, {tests!r})
    from xrl_jax.train import cpu_devices
    cpu_devices.cpu_cores = lambda: int(sys.argv[1])
    import os
    if os.environ.get("PRESPLIT"):  # as paper.py: split for the campaign's most, start the backend
        import jax
        cpu_devices.split_cpu_host(int(os.environ["PRESPLIT"]))
        jax.devices()
    import importlib.util
    found = importlib.util.spec_from_file_location("run", {run!r})
    run = importlib.util.module_from_spec(found); sys.modules["run"] = run; found.loader.exec_module(run)
    status = run.main(sys.argv[2:])
    import jax
    print(json.dumps({{"status": status, "devices": len(jax.devices())}}))
    cpu_devices.end_process(0)  # as run.py's own end
    """
)


def run_child(cores: int, args: list[str], presplit: int = 0) -> dict:
    script = CHILD.format(tests=str(DATA.parent), run=str(DATA.parents[1] / "experiments" / "run.py"))
    env = {**os.environ, "PRESPLIT": str(presplit)} if presplit else None
    try:
        done = subprocess.run(
            [sys.executable, "-c", script, str(cores), *args],
            capture_output=True, text=True, timeout=300, env=env,
        )  # fmt: skip
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"the run did not end within 300 s: {(err.stderr or b'')[-3000:]!r}")
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # two fresh processes that each compile a run (~15 s each on 2 cores)
def test_a_new_run_uses_every_core_and_its_resume_splits_the_host_alike(tmp_path):
    out = tmp_path / "run"
    steps = ["--steps", "128", "--set", "log_interval=64", "--set", "checkpoint_interval=64"]
    args = [*FAST_ENV_ARGS, "--algo", "dsac", "--preset", "smoke", "--seeds", "2", *steps, "--quiet"]
    first = run_child(2, [*args, "--out", str(out)])
    assert first == {"status": 0, "devices": 2}
    assert json.loads((out / "config.json").read_text())["config"]["num_devices"] == 2
    # The run is complete; its resume finds nothing left to train but still splits the host as stored.
    again = run_child(1, ["--import", FAST_ENV_MODULE, "--resume", str(out), "--quiet"])
    assert again == {"status": 0, "devices": 2}


@pytest.mark.slow  # a fresh process that compiles a run (~15 s on 2 cores)
def test_a_run_in_a_host_split_for_a_campaign_takes_its_own_count(tmp_path):
    """paper.py splits its host once for the runs that want most devices (the Intersection's two per
    core); a racing run in it takes the devices its rule gives (4 seeds on 2 cores: 2), not all 4."""
    assert cpu_devices.most_cpu_devices(2) == 4
    out = tmp_path / "run"
    args = [*FAST_ENV_ARGS, "--algo", "dsac", "--preset", "smoke", "--seeds", "4", "--quiet"]
    child = run_child(2, [*args, "--steps", "64", "--set", "log_interval=64", "--out", str(out)], presplit=4)
    assert child == {"status": 0, "devices": 4}
    assert json.loads((out / "config.json").read_text())["config"]["num_devices"] == 2


@pytest.mark.slow  # a fresh process that compiles a run (14 s on 2 cores): the default tier's budget
def test_devices_given_split_the_host(tmp_path):
    args = [*FAST_ENV_ARGS, "--algo", "dsac", "--preset", "smoke", "--seeds", "1", "--quiet"]
    child = run_child(2, [*args, "--steps", "64", "--set", "log_interval=64", "--devices", "1"])
    assert child == {"status": 0, "devices": 1}


def test_a_split_host_waits_patiently_in_its_collectives(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_collective_call_warn_stuck_timeout_seconds=5")
    cpu_devices.split_cpu_host(2)  # the backend runs already: only the flags change
    flags = cpu_devices.os.environ["XLA_FLAGS"]
    assert "--xla_cpu_collective_call_terminate_timeout_seconds=1800" in flags
    assert flags.count("warn_stuck_timeout") == 1  # the user's own value stands
