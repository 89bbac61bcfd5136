"""Sweeps and scale: every sweep point x seed in one program, spread over devices and processes.

What is compared exactly and what within a tolerance, and why:

* A member's numbers depend on its seed, its sweep point and on how many members share its device
  (XLA vectorises a vmapped batch of 2 and of 6 differently, so the last bits of the update's
  reductions differ). With the same per-device member count they are bit-identical: a sweep point
  equals a plain run of its values, and 4 devices equal 2 devices or 2 processes.
* A mesh of one device compiles without SPMD partitioning, and XLA's algebraic simplifier then
  reassociates some divisions (``a / (b / c)`` into ``(a * c) / b``), i.e. different rounding in
  the last bit. A one-device run therefore equals a multi-device run exactly only up to the first
  update; see :func:`test_one_device_agrees_within_float32_rounding` for the tolerance.
"""

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from train_support import FAST_ENV_ARGS, call, load_script, one_line_error, prepare_cache, xla_flags

ROOT = Path(__file__).resolve().parents[1]
# The sweeps train on the trivial env of the host-side tests (tests/fast_env.py, registered by --import):
# what is compared here, the members and their records across devices and processes, is the trainer's.
SWEEP = [*FAST_ENV_ARGS, "--algo", "xdsac", "--preset", "smoke", "--seeds", "2", "--quiet",
         "--sweep", "kappa=-0.01,0,0.1"]  # fmt: skip
POINTS, SEEDS = (-0.01, 0.0, 0.1), 2


def records(folder: Path, sub: str) -> dict[str, list[dict]]:
    return {
        p.stem: [json.loads(line) for line in p.read_text().splitlines()]
        for p in (folder / sub).glob("*.jsonl")
    }


def numbers(row: dict) -> dict:
    return {k: v for k, v in row.items() if isinstance(v, float)}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    return load_script("run", "run_cli_scaling")


@pytest.fixture(scope="module")
def one_device(run, tmp_path_factory):
    """The kappa sweep on one device in groups of two members (two per device, as below)."""
    out = tmp_path_factory.mktemp("sweeps") / "one_device"
    assert run.main([*SWEEP, "--set", "max_group_size=2", "--out", str(out)]) == 0
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(cache: Path, devices: int) -> dict:
    env = dict(os.environ, XRL_JAX_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    env["XLA_FLAGS"] = xla_flags(f"--xla_force_host_platform_device_count={devices}")
    env.pop("JAX_COORDINATOR_ADDRESS", None)
    return env


@pytest.fixture(scope="module")
def sharded(one_device, tmp_path_factory):
    """The same sweep on 4 forced CPU devices in one process: 6 members padded to 8, two per device."""
    folder = tmp_path_factory.mktemp("sharded")
    script = (
        "import sys; sys.path.insert(0, 'experiments'); import run\n"
        f"assert run.main([*{SWEEP!r}, '--devices', '4', '--out', {str(folder / 'four')!r}]) == 0\n"
    )
    cache = Path(os.environ["XRL_JAX_CACHE_DIR"])
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=_env(cache, 4), capture_output=True,
                          text=True, timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return folder


def test_sweep_errors_are_one_line_and_write_nothing(run, capsys, tmp_path):
    out = tmp_path / "never"
    cases = [
        (["--sweep", "kappa=a,b"], "not a list of numbers"),
        (["--sweep", "kappa="], "comma-separated list of numbers"),
        (["--sweep", "kappa=0.1", "--sweep", "kappa=0.2"], "given twice"),
        (["--sweep", "actor_width=64,128"], "sweepable: actor_lr, critic_lr"),
        (["--algo", "sac", "--sweep", "kappa=0,0.1"], "sac has no mixture"),
        (["--sweep", "kappa=0.1,0.1"], "repeats a value"),
        (["--sweep", "actor_lr=-1,0.1"], "actor_lr must be positive"),
        (["--devices", "3"], "sees only 1 cpu device"),
        (["--coordinator", "127.0.0.1:1", "--num-processes", "2", "--process-id", "5"], "not in 0..1"),
    ]
    for extra, fragment in cases:
        base = ["--env", "country_road", "--algo", "xdsac", "--preset", "smoke", "--out", str(out)]
        status, _, err = call(run, capsys, *base, *extra)
        one_line_error(status, err, fragment)
        assert not out.exists(), extra


def test_unreachable_coordinator_fails_in_one_line_within_its_timeout(tmp_path):
    """JAX's own client aborts with a page of C++ stack; the CLI checks the coordinator first."""
    address = f"127.0.0.1:{_free_port()}"
    args = ["--preset", "smoke", "--out", str(tmp_path / "never"), "--coordinator", address,
            "--num-processes", "2", "--process-id", "1", "--coordinator-timeout", "2"]  # fmt: skip
    done = subprocess.run([sys.executable, "experiments/run.py", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)))  # fmt: skip
    one_line_error(done.returncode, done.stderr, "cannot reach the coordinator", "within 2 s")
    assert not (tmp_path / "never").exists()


def test_a_job_whose_other_processes_never_join_fails_in_one_line_within_its_timeout(tmp_path):
    """Process 0 started alone: JAX waits for the others and then aborts with ~15 lines of C++ stack
    (status 134). The CLI gives JAX a longer deadline than --coordinator-timeout and ends first, in
    one line naming the coordinator, before anything is written."""
    address = f"127.0.0.1:{_free_port()}"
    args = ["--preset", "smoke", "--out", str(tmp_path / "never"), "--coordinator", address,
            "--num-processes", "2", "--process-id", "0", "--coordinator-timeout", "3"]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("JAX_COORDINATOR_ADDRESS", None)
    started = time.monotonic()
    done = subprocess.run([sys.executable, "experiments/run.py", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, env=env)  # fmt: skip
    elapsed = time.monotonic() - started
    one_line_error(done.returncode, done.stderr, "did not assemble within 3 s", f"the coordinator {address}",
                   "--process-id 0..1", "nothing was written")  # fmt: skip
    assert not (tmp_path / "never").exists()
    from xrl_jax.train.hosts import JOIN_GRACE_S

    assert elapsed < 3 + JOIN_GRACE_S, elapsed  # JAX's own deadline (and abort) comes later


def _two_process_smoke_job(script: str, out: Path, cache: Path) -> list[tuple[int, str]]:
    """Run ``script`` (which ends in ``run.main``) as processes 0 and 1 of a smoke job writing to
    ``out``, one CPU device each; ``(exit status, stderr)`` per process."""
    job = ["--preset", "smoke", "--quiet", "--out", str(out), "--coordinator", f"127.0.0.1:{_free_port()}",
           "--num-processes", "2"]  # fmt: skip
    pipes = {"cwd": ROOT, "env": _env(cache, 1), "stdout": subprocess.PIPE, "stderr": subprocess.PIPE,
             "text": True}  # fmt: skip
    procs = [
        subprocess.Popen([sys.executable, "-c", script, str(i), *job, "--process-id", str(i)], **pipes)
        for i in range(2)
    ]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    return [(p.returncode, err) for p, err in zip(procs, errs, strict=True)]


LOSE_A_PROCESS = """
import os, sys, time
sys.path.insert(0, "experiments")
import run
from xrl_jax import train
from xrl_jax.train import hosts

def vanish(*args, **kwargs):  # after the job's first collective, process 1 dies without a word
    hosts.gathered(0)
    os._exit(9)

def collect(*args, **kwargs):  # process 0 meets the loss in the job's next collective
    hosts.gathered(0)
    time.sleep(1)
    hosts.gathered(1)

train.train = vanish if sys.argv[1] == "1" else collect
sys.exit(run.main(sys.argv[2:]))
"""


@pytest.mark.distributed
def test_a_process_that_dies_mid_run_ends_the_others_in_one_line(tmp_path):
    """Before: a traceback, then ~70 lines of C++ stack as JAX's shutdown waits for the lost process
    and aborts. Now the collective's error (Gloo on CPU) ends process 0 at once, in one line, status 1,
    saying how to resume. (A loss that only JAX's missed heartbeats reveal, e.g. before the job's
    first collective has connected the processes, still ends in XLA's abort; see run.py --help.)"""
    out = tmp_path / "job"
    (status, err), (status_1, err_1) = _two_process_smoke_job(LOSE_A_PROCESS, out, tmp_path / "cache")
    assert status_1 == 9, err_1
    lines = [line for line in err.strip().splitlines() if not line.startswith("[Gloo]")]  # Gloo's own note
    assert status == 1 and len(lines) == 1, err
    assert lines[0].startswith("run.py: error: process 0 of 2 lost another process of the job (")
    assert f"start every process again with --resume {out}" in lines[0]


LATE_PROCESS = """
import os, sys, time
sys.path.insert(0, "experiments")
import run
from xrl_jax import train
from xrl_jax.train import hosts, start

checked = start.prepare_run

def late(*args, **kwargs):  # process 1 looks at the folder 3 s after process 0
    time.sleep(3)
    return checked(*args, **kwargs)

def first_file(*args, **kwargs):  # process 0 writes into the folder as soon as it has it
    prepared = checked(*args, **kwargs)
    (prepared.out / "first_file").write_text("written by process 0")  # a file that counts as results
    return prepared

def meet(*args, **kwargs):
    hosts.gathered(0)
    os._exit(0)

start.prepare_run = late if sys.argv[1] == "1" else first_file
train.train = meet
sys.exit(run.main(sys.argv[2:]))
"""


@pytest.mark.distributed
def test_a_process_that_checks_the_new_folder_late_still_joins_the_run(tmp_path):
    """Every process refuses a --out that holds results, but only as the folder was before the job
    wrote anything: a process slower to look (here by 3 s) must not find the first files of a faster
    one and refuse the job's own folder (it did, now and then, on a loaded machine)."""
    out = tmp_path / "job"
    (status_0, err_0), (status_1, err_1) = _two_process_smoke_job(LATE_PROCESS, out, tmp_path / "cache")
    assert status_1 == 0, err_1
    assert status_0 == 0, err_0
    assert (out / "first_file").read_text() == "written by process 0"


def test_a_sweep_point_equals_a_plain_run_of_its_values(run, one_device, tmp_path):
    """Same seeds, same values, same member count per device: bit-identical records, also in
    the sweep's per-point summary (a member's stream depends on its seed and point alone)."""
    out = tmp_path / "plain"
    args = [*FAST_ENV_ARGS, "--algo", "xdsac", "--preset", "smoke", "--seeds", "2", "--quiet"]
    assert run.main([*args, "--set", "kappa=0.1", "--out", str(out)]) == 0
    sweep_metrics, plain_metrics = records(one_device, "metrics"), records(out, "metrics")
    for seed in range(SEEDS):
        swept = sweep_metrics[f"point_2_seed_{seed}"]
        assert all(r["point"] == 2 and r["sweep"] == {"kappa": 0.1} and r["seed"] == seed for r in swept)
        assert [numbers(r) for r in swept] == [numbers(r) for r in plain_metrics[f"seed_{seed}"]]
    summary, plain = (json.loads((f / "summary.json").read_text()) for f in (one_device, out))
    point = summary["sweep"]["points"][2]
    assert point["values"] == {"kappa": 0.1} and point["aggregate"] == plain["aggregate"]
    config = json.loads((one_device / "config.json").read_text())["config"]
    assert config["sweep"] == [["kappa", list(POINTS)]] and config["num_seeds"] == SEEDS
    members = json.loads((one_device / "config.json").read_text())["members"]
    expected = {"member": 5, "file": "point_2_seed_1", "seed": 1, "point": 2, "sweep": {"kappa": 0.1}}
    assert members[5] == expected
    assert (one_device / "sweep.png").stat().st_size > 0


@pytest.mark.distributed
def test_four_devices_train_every_member_of_the_sweep(sharded):
    four = sharded / "four"
    plan = json.loads((four / "plan.json").read_text())
    assert plan["devices"] == 4 and plan["groups"] == [[0, 1, 2, 3, 4, 5]]
    for sub in ("metrics", "eval"):
        got = records(four, sub)
        assert sorted(got) == [f"point_{p}_seed_{s}" for p in range(3) for s in range(SEEDS)]
        for name, rows in got.items():
            point, seed = int(name.split("_")[1]), int(name.split("_")[3])
            assert all(r["point"] == point and r["seed"] == seed for r in rows)
            assert all(r["sweep"] == {"kappa": POINTS[point]} for r in rows)
    summary = json.loads((four / "summary.json").read_text())
    assert summary["complete"] and [p["values"]["kappa"] for p in summary["sweep"]["points"]] == list(POINTS)
    assert (four / "sweep.png").stat().st_size > 0


@pytest.mark.distributed
def test_one_device_agrees_within_float32_rounding(one_device, sharded):
    """Exact through the warm-up: no update has run yet, so nothing the two programs round
    differently. At the first chunk with updates (U = 64 of them) the bound follows from Adam: its
    step is lr * m / sqrt(v), at most lr per parameter whatever the gradient's size, so a rounding
    difference that flips a near-zero gradient component reverses at most one step of size lr.
    After U steps every parameter of the two runs agrees within 2 * lr * U (= 0.0128 at lr 1e-4),
    and the chunk's metrics (smooth functions of the parameters, of order one or compared at their
    own scale when larger) within that much. On the development CPU the largest gap was ~1e-4 (the
    mixture logits' mean, over 120 members), the losses' ~1e-5 relative."""
    config = json.loads((one_device / "config.json").read_text())["config"]["agent"]
    lr = max(config["actor_lr"], config["critic_lr"], config["alpha_lr"] or config["critic_lr"])
    got, want = records(sharded / "four", "metrics"), records(one_device, "metrics")
    assert sorted(got) == sorted(want)
    for name in want:
        warmup, first_updates = want[name][0], want[name][1]
        assert numbers(got[name][0]) == numbers(warmup), name
        updates = first_updates["step"] - warmup["step"]
        a, b = numbers(got[name][1]), numbers(first_updates)
        assert a.keys() == b.keys() and updates == 64
        for key in a:
            bound = 2 * lr * updates * max(abs(a[key]), abs(b[key]), 1.0)
            assert abs(a[key] - b[key]) <= bound, (name, key, a[key], b[key])


@pytest.mark.distributed
def test_two_processes_equal_one_process_and_resume_per_process(sharded, tmp_path):
    """Two processes on 127.0.0.1 (one CPU device each) train the sweep as one job in groups of
    3 members (padded to 4: two per device): each writes the records of its members; process 0
    writes the summary, and each one's progress callbacks receive every member's records. Each
    stops after two chunks and resumes from the job's checkpoints, as a preempted SLURM job would.
    With two members per device, as in the one-process run on 4 devices, the records are equal bit
    for bit."""
    out = tmp_path / "job"
    port = _free_port()
    driver = (
        "import sys\n"
        "from xrl_jax.train import hosts\n"
        f"hosts.initialize('127.0.0.1:{port}', 2, int(sys.argv[1]), 60)\n"
        "from xrl_jax.config import parse_sweep, resolve_config\n"
        "from xrl_jax.train import train\n"
        "sys.path.insert(0, 'tests'); import fast_env\n"
        "cfg = resolve_config('fast', 'xdsac', 'smoke', num_seeds=2,\n"
        "                     overrides={'max_group_size': '4'}, sweep=parse_sweep(['kappa=-0.01,0,0.1']))\n"
        "seen = set()\n"  # every process's progress callbacks get every member's records
        "def tell(progress):\n"
        "    seen.update(member for member, _ in progress.metrics)\n"
        "quiet = dict(progress=False, log=lambda m: None, progress_fns=[tell])\n"
        f"assert train(cfg, {str(out)!r}, stop_after_chunks=2, **quiet) is None\n"
        f"summary = train(cfg, {str(out)!r}, resume=True, **quiet)\n"
        "assert summary['complete'] and seen == set(range(6)), seen\n"
    )
    cache = Path(os.environ["XRL_JAX_CACHE_DIR"])
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", driver, str(i)],
            cwd=ROOT,
            env=_env(cache, 1),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=900) for p in procs]
    for p, (_, err) in zip(procs, outputs, strict=True):
        assert p.returncode == 0, err[-3000:]
    want = sharded / "four"
    assert json.loads((out / "plan.json").read_text())["groups"] == [[0, 1, 2], [3, 4, 5]]
    for sub in ("metrics", "eval"):
        assert records(out, sub) == records(want, sub), sub
    summary = json.loads((out / "summary.json").read_text())
    assert summary["memory_plan"]["processes"] == 2 and summary["complete"]
    expected = json.loads((want / "summary.json").read_text())["sweep"]["points"]
    assert [p["aggregate"] for p in summary["sweep"]["points"]] == [p["aggregate"] for p in expected]
    assert (out / ".lock.process_1").exists() and (out / "sweep.png").stat().st_size > 0
    assert np.all([len(rows) == 3 for rows in records(out, "metrics").values()])


def test_grid_members_and_their_hyper_parameters():
    """The grid is the product (first field slowest), members are point-major, every member gets
    its point's resolved values (alpha_lr follows a swept critic_lr when unset), and the config
    round-trips through config.json."""
    import math

    from xrl_jax.config import TrainConfig, parse_sweep, resolve_config
    from xrl_jax.train.chunk import member_hparams
    from xrl_jax.train.memory import padded_members

    sweep = parse_sweep(["critic_lr=1e-4,3e-4", "agent.init_alpha=0.1,0.2,0.05"])
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2, sweep=sweep)
    assert cfg.num_points == 6 and cfg.num_members == 12
    assert cfg.sweep_points[1] == {"critic_lr": 1e-4, "init_alpha": 0.2}
    assert cfg.member_point_seed(7) == (3, 1) and TrainConfig.from_dict(cfg.to_dict()) == cfg

    class Agent:  # member_hparams reads the action count only
        action_size = 12

    hp = member_hparams(cfg, Agent(), [0, 7, 11])
    np.testing.assert_allclose(hp.critic_lr, [1e-4, 3e-4, 3e-4], rtol=1e-6)
    np.testing.assert_allclose(hp.alpha_lr, hp.critic_lr)  # unset alpha_lr follows each point's critic_lr
    np.testing.assert_allclose(hp.init_log_alpha, np.log([0.1, 0.1, 0.05]), rtol=1e-6)
    np.testing.assert_allclose(hp.target_entropy, [1.24] * 3, rtol=1e-6)
    assert math.isclose(float(hp.kappa[0]), cfg.agent.kappa, rel_tol=1e-6)
    assert padded_members([4, 5, 6], 4) == [4, 5, 6, 6] and padded_members([1, 2], 2) == [1, 2]


@pytest.mark.slow  # two runs (~35 s); the SAC family's sweep point test above runs by default
def test_an_on_policy_sweep_point_equals_a_plain_run_of_its_values(run, tmp_path):
    """The PPO family's traced settings (here the entropy bonus) sweep as the SAC family's do: every
    point x seed a member of one program, each bit-identical to a plain run of its values."""
    args = [*FAST_ENV_ARGS, "--algo", "xdppo", "--preset", "smoke", "--seeds", "2", "--quiet",
            "--set", "max_group_size=2"]  # fmt: skip
    swept, plain = tmp_path / "swept", tmp_path / "plain"
    assert run.main([*args, "--sweep", "ent_coef=0,0.1", "--out", str(swept)]) == 0
    assert run.main([*args, "--set", "ent_coef=0.1", "--out", str(plain)]) == 0
    swept_metrics, plain_metrics = records(swept, "metrics"), records(plain, "metrics")
    for seed in range(2):
        rows = swept_metrics[f"point_1_seed_{seed}"]
        assert all(r["sweep"] == {"ent_coef": 0.1} for r in rows)
        assert [numbers(r) for r in rows] == [numbers(r) for r in plain_metrics[f"seed_{seed}"]]
    other = [numbers(r) for r in swept_metrics["point_0_seed_0"]]
    assert other != [numbers(r) for r in plain_metrics["seed_0"]]  # the bonus did matter
