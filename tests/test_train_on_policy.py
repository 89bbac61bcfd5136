"""The on-policy family through the trainer (run.py --algo ppo|dppo|xppo|xdppo): a smoke run leaves a
complete results folder with the family's metrics, a stopped run resumed equals an uninterrupted one
(also after kill -9, and on the Intersection), a resume with changed settings is refused, the
explanation figure reads a trained XDPPO agent, and what it cannot train is refused in one line."""

import json

import pytest
from train_support import call, files_of, load_script, run_stopped_after

from xrl_jax.config import ConfigError, resolve_config

SMOKE = ["--env", "tracking", "--algo", "xdppo", "--preset", "smoke", "--seeds", "2", "--quiet"]


@pytest.fixture(scope="module")
def run():
    return load_script("run", "run_cli_on_policy")


def test_a_stopped_and_resumed_run_equals_an_uninterrupted_one(run, tmp_path, capsys, monkeypatch):
    """Rollouts of 16 vector steps x 4 envs are the smoke chunk of 64 transitions; the checkpoint at
    128 holds the agent, its optimiser states and the envs mid-episode."""
    args = [*SMOKE, "--steps", "256", "--set", "checkpoint_interval=128"]
    full, split = tmp_path / "full", tmp_path / "split"
    assert call(run, capsys, *args, "--out", str(full))[0] == 0
    status, _, err = run_stopped_after(run, capsys, monkeypatch, 3, *args, "--out", str(split))
    assert status == 1 and "--resume" in err
    status, out, _ = call(run, capsys, "--resume", str(split), "--quiet")
    assert status == 0 and "final return" in out
    assert files_of(split, "metrics") == files_of(full, "metrics")
    assert files_of(split, "eval") == files_of(full, "eval")
    rows = [json.loads(line) for line in (full / "metrics" / "seed_0.jsonl").read_text().splitlines()]
    # A rollout per chunk, each 2 epochs x 4 minibatches.
    assert [row["train/updates"] for row in rows] == [8, 16, 24, 32]
    expected = {"train/loss_policy", "train/loss_value", "train/approx_kl", "train/mixture_entropy"}
    assert expected <= set(rows[-1])
    assert "train/ent_coef" not in rows[-1] and "buffer/stored_rows" not in rows[-1]
    # Resumes with changed settings are refused in one line, nothing touched: on the command line, and
    # in config.json edited after the run (clip_eps, a setting hashed only where set: the checkpoints'
    # fingerprint tells it from the default all the same).
    before = files_of(full, "metrics")
    status, _, err = call(run, capsys, "--resume", str(full), *SMOKE, "--set", "ppo_epochs=3")
    assert status == 2 and "another configuration" in err and "ppo_epochs" in err
    document = json.loads((full / "config.json").read_text())
    document["config"]["agent"]["clip_eps"] = 0.3
    (full / "config.json").write_text(json.dumps(document))
    status, _, err = call(run, capsys, "--resume", str(full), "--quiet")
    assert status == 2 and "another configuration" in err and len(err.strip().splitlines()) == 1
    assert files_of(full, "metrics") == before


@pytest.mark.slow  # two Intersection smoke runs (~40 s); the masked rollout's pieces are tested by default
def test_the_intersection_trains_every_agent_slot_and_resumes_exactly(run, tmp_path, capsys, monkeypatch):
    """Parameter sharing over the vehicles, as the SAC agents do: every slot's steps in one rollout
    (16 vector steps x 2 envs x 8 slots), the empty slots masked out; stopped after its first chunk
    and resumed, it equals the uninterrupted run."""
    args = ["--env", "intersection", "--algo", "xdppo", "--preset", "smoke", "--seeds", "1", "--quiet"]
    full, split = tmp_path / "full", tmp_path / "split"
    assert call(run, capsys, *args, "--out", str(full))[0] == 0
    assert run_stopped_after(run, capsys, monkeypatch, 1, *args, "--out", str(split))[0] == 1
    assert call(run, capsys, "--resume", str(split), "--quiet")[0] == 0
    assert files_of(split, "metrics") == files_of(full, "metrics")
    assert files_of(split, "eval") == files_of(full, "eval")
    rows = [json.loads(line) for line in (full / "metrics" / "seed_0.jsonl").read_text().splitlines()]
    # Two rollouts per chunk of 64 transitions (32 vector steps), each 2 epochs x 4 minibatches.
    assert [row["train/updates"] for row in rows] == [16, 32]
    assert rows[-1]["rollout/episodes"] > 0 and "rollout/trips_per_episode" in rows[-1]
    summary = json.loads((full / "summary.json").read_text())  # the Intersection's evaluation
    assert summary["complete"]
    assert {"avg_trips_completed", "avg_early_terminations"} <= set(summary["aggregate"])


@pytest.mark.slow  # a smoke run and the figure (~20 s); the explain CLI of the SAC family runs by default
def test_the_explanation_figure_reads_a_trained_xdppo_agent(run, tmp_path, capsys):
    out = tmp_path / "run"
    assert call(run, capsys, *SMOKE, "--out", str(out))[0] == 0
    explain = load_script("explain", "explain_cli_on_policy")
    assert call(explain, capsys, "--run", str(out), "--step", "5")[0] == 0
    assert list((out / "explain").glob("*.png"))


@pytest.mark.parametrize(
    "env, algo, overrides, message",
    [
        ("intersection", "xdppo", {"reinit_steps": "1000"}, "reinit_steps .* is not for xdppo"),
        ("tracking", "xdppo", {"warmup_steps": "64"}, "warmup_steps must be 0"),
        ("tracking", "xdppo", {"rollout_steps": "10"}, "must be a multiple of one rollout"),
        ("tracking", "xdppo", {"ppo_minibatches": "5"}, "cannot be split into ppo_minibatches=5"),
        ("tracking", "xppo", {}, None),  # continuous Tracking: accepted
        ("country_road", "dppo", {}, None),
        ("intersection", "xdppo", {}, None),  # its agent slots: rollouts of every slot
        ("intersection", "ppo", {}, None),
        ("tracking", "xppo", "sweep", ("ent_coef=0,0.01", None)),  # its own traced settings sweep
        ("tracking", "ppo", "sweep", ("kappa=0,0.01", "ppo has no mixture")),
        ("tracking", "xppo", "sweep", ("tau=0.01,0.1", "cannot sweep tau for xppo: .*sweepable: actor_lr")),
    ],
)
def test_what_the_on_policy_trainer_cannot_train_is_refused_in_one_line(env, algo, overrides, message):
    from xrl_jax.config import parse_sweep

    if overrides == "sweep":
        sweep = parse_sweep([message[0]])
        if message[1] is None:
            assert resolve_config(env, algo, "smoke", sweep=sweep).num_points == 2
            return
        with pytest.raises(ConfigError, match=message[1]):
            resolve_config(env, algo, "smoke", sweep=sweep)
        return
    if message is None:
        assert resolve_config(env, algo, "smoke", overrides=overrides).agent.is_on_policy
        return
    with pytest.raises(ConfigError, match=message):
        resolve_config(env, algo, "smoke", overrides=overrides)


@pytest.mark.slow  # two runs in subprocesses (~60 s); the in-process stop and resume runs by default
def test_a_run_killed_with_sigkill_resumes_to_the_uninterrupted_runs_results(tmp_path):
    """kill -9 once the first checkpoint is written (no handler runs): the resume restores the newest
    verified checkpoint and ends with the same metrics and evaluations as a run never killed."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    script = str(Path(__file__).resolve().parents[1] / "experiments" / "run.py")
    args = [*SMOKE, "--steps", "512", "--set", "checkpoint_interval=64"]
    full, killed = tmp_path / "full", tmp_path / "killed"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    subprocess.run([sys.executable, script, *args, "--out", str(full)], check=True, env=env,
                   capture_output=True)  # fmt: skip
    child = subprocess.Popen([sys.executable, script, *args, "--out", str(killed)], env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        group = killed / "checkpoints" / "group_0"
        while not (group.is_dir() and any(p.name.isdigit() for p in group.iterdir())):
            assert child.poll() is None and time.monotonic() < deadline, "no checkpoint was written"
            time.sleep(0.05)
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
    finally:
        if child.poll() is None:
            child.kill()
    assert not (killed / "summary.json").exists()  # killed before the end
    resumed = subprocess.run([sys.executable, script, "--resume", str(killed), "--quiet"], env=env,
                             capture_output=True, text=True)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr
    assert files_of(killed, "metrics") == files_of(full, "metrics")
    assert files_of(killed, "eval") == files_of(full, "eval")


@pytest.mark.slow  # a smoke run (~15 s); the SAC family's divergence test runs by default, same host loop
def test_a_diverging_on_policy_run_stops_naming_seed_step_and_loss(run, capsys, tmp_path):
    out = tmp_path / "diverged"
    status, _, err = call(run, capsys, *SMOKE, "--set", "actor_lr=1e4", "--set", "critic_lr=1e4",
                          "--out", str(out))  # fmt: skip
    lines = err.strip().splitlines()
    assert status == 3 and len(lines) == 1, err
    assert "diverged at step" in lines[0] and "became non-finite" in lines[0] and "actor_lr" in lines[0]
    assert not (out / "summary.json").exists()
    kept = sorted(int(p.name) for p in (out / "checkpoints" / "group_0").iterdir() if p.name.isdigit())
    assert kept and f"checkpoint at step {kept[-1]} of 192 per seed is kept" in lines[0]


def test_the_quick_on_policy_protocol_is_the_tuned_one():
    """docs/quick_preset_tuning.md, "PPO on Tracking": 16 envs, rollouts of 125 vector steps in 8
    minibatches, 2,048,000 steps with the learning rates decaying to zero at the last minibatch; the
    Intersection keeps its kind's rows, its rollout counted over every agent slot (250 x 8 rows)."""
    for env in ("tracking", "country_road"):
        for algo in ("ppo", "dppo", "xppo", "xdppo"):
            cfg = resolve_config(env, algo, "quick", num_seeds=8)
            assert (cfg.num_envs, cfg.total_steps, cfg.eval_interval) == (16, 2_048_000, 256_000)
            assert (cfg.agent.rollout_steps, cfg.agent.ppo_minibatches, cfg.agent.ppo_epochs) == (125, 8, 4)
            assert cfg.agent.lr_decay_updates == 2_048_000 // (125 * 16) * 4 * 8
            assert cfg.warmup_steps == 0
    sac = resolve_config("tracking", "xdsac", "quick")
    assert (sac.num_envs, sac.total_steps) == (4, 240_000)  # the SAC family's rows are untouched
    cfg = resolve_config("intersection", "xdppo", "quick")
    assert (cfg.num_envs, cfg.agent.ppo_minibatches, cfg.reinit_steps) == (2, 4, 0)
