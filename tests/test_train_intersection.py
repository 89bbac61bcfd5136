"""Multi-agent training on the Intersection through the CLI: packed agent transitions, one update per
agent transition after warm-up, periodic re-initialisation, evaluation with 8 vehicles."""

import json
from pathlib import Path

import pytest
from train_support import load_script

from xrl_jax import train as train_mod

# 3 chunks of 64 env steps per seed (2 envs); warm-up = chunk 0; re-initialisation at env step 128.
# Every slot computed (dense_sets): packing, tested in test_sets, would compile both of its branches.
SMOKE = [
    "--env", "intersection", "--algo", "xdsac", "--preset", "smoke", "--seeds", "2", "--steps", "192",
    "--set", "reinit_steps=128", "--set", "buffer_size=4096", "--set", "dense_sets=true", "--quiet",
]  # fmt: skip


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    module = load_script("run", "run_cli_intersection")
    out = tmp_path_factory.mktemp("runs") / "intersection"
    assert module.main([*SMOKE, "--out", str(out)]) == 0
    return out


def lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_presets_follow_the_released_configs():
    cfg = train_mod.resolve_config("intersection", "xsac", "paper")
    assert cfg.scenario.kind == "multi_agent" and cfg.buffer_layout == "explicit"
    assert (cfg.total_steps, cfg.buffer_size, cfg.batch_size) == (5_000_000, 15_000_000, 512)
    assert (cfg.warmup_steps, cfg.reinit_steps, cfg.eval_episodes) == (2_000, 500_001, 20)
    assert cfg.env_name == "intersection"
    assert train_mod.resolve_config("intersection", "xdsac", "paper").env_name == "intersection_discrete"
    assert train_mod.resolve_config("tracking", "xsac", "paper").reinit_steps == 0


def test_every_agent_transition_is_stored_and_trained_on(smoke_run):
    for seed in (0, 1):
        rows = lines(smoke_run / "metrics" / f"seed_{seed}.jsonl")
        assert [r["step"] for r in rows] == [64, 128, 192]
        stored = [r["buffer/stored_rows"] for r in rows]
        updates = [r["train/updates"] for r in rows]  # the agent's own update counter
        # At least one agent acts in every env step (reset spawns >= 1 vehicle), so >= 64 per chunk.
        assert stored[0] >= 64 and stored[1] - stored[0] >= 64 and stored[2] - stored[1] >= 64
        assert updates[0] == 0  # chunk 0 is warm-up: random actions, no updates
        assert updates[1] == stored[1] - stored[0]  # one update per stored agent transition
        # The agent was re-initialised at env step 128: its counter restarted with chunk 2.
        assert updates[2] == stored[2] - stored[1]
        assert all(r["train/loss_critic"] is not None for r in rows[1:])


def test_evaluation_reports_trips_and_early_terminations_with_ci(smoke_run):
    summary = json.loads((smoke_run / "summary.json").read_text())
    assert summary["complete"] and summary["env"] == "intersection"
    for key in ("avg_return", "avg_trips_completed", "avg_early_terminations", "avg_mean_velocity"):
        agg = summary["aggregate"][key]
        assert agg["low"] <= agg["estimate"] <= agg["high"] and agg["n"] == 2
    final = lines(smoke_run / "eval" / "seed_0.jsonl")[-1]
    assert final["step"] == 192 and len(final["episode_returns"]) == 2
    # 8 vehicles drive for 60 s: something happens (spawned cars move at 5.5-8.3 m/s at least).
    assert final["avg_mean_velocity"] > 0.5
    assert final["avg_early_terminations"] == final["avg_come_off_vehicles"] + final["avg_collided_vehicles"]
    seeds = [lines(smoke_run / "metrics" / f"seed_{s}.jsonl")[-1] for s in (0, 1)]
    assert seeds[0]["buffer/stored_rows"] != seeds[1]["buffer/stored_rows"] or (
        seeds[0]["train/loss_critic"] != seeds[1]["train/loss_critic"]
    )


def test_cli_offers_every_trainable_env():
    parser = load_script("run", "run_cli_envs").build_parser()
    choices = next(action.choices for action in parser._actions if action.dest == "env")
    assert set(train_mod.ENVS) <= set(choices)  # and the envs registered in this process


def test_a_buffer_smaller_than_one_step_of_all_agents_is_refused():
    with pytest.raises(train_mod.ConfigError, match="one step of all agents"):
        train_mod.resolve_config(
            "intersection", "xdsac", "smoke", overrides={"buffer_size": "8", "batch_size": "8"}
        )


def test_members_in_one_program_pay_the_least_owed_until_one_falls_too_far_behind():
    """The owed-update counter (xrl_jax.train.kinds.multi_agent): members vmapped together pay one
    count per step, the least owed unless that leaves a member over MAX_OWED_UPDATES behind; all owed
    before a re-initialisation and at the run's last step; a member alone pays its own every step."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from xrl_jax.sets import MEMBERS_AXIS
    from xrl_jax.train.kinds.multi_agent import MAX_OWED_UPDATES, updates_to_pay

    cfg = train_mod.resolve_config("intersection", "xdsac", "smoke", overrides={"reinit_steps": "64"})
    last = cfg.total_vector_steps - 1  # 63: 128 env steps of 2 envs
    pay = jax.jit(jax.vmap(lambda owed, t: updates_to_pay(cfg, owed, t), (0, None), axis_name=MEMBERS_AXIS))
    assert np.all(pay(jnp.array([3, 10]), 5) == 3)  # the least owed
    most = MAX_OWED_UPDATES + 900
    assert np.all(pay(jnp.array([0, most]), 5) == 900)  # no member more than MAX_OWED_UPDATES behind
    assert np.all(pay(jnp.array([3, 10]), last) == 10)  # the last step pays everything
    # Vector step 32 (env steps 64 and 65) starts with a re-initialisation: step 31 pays everything.
    assert np.all(pay(jnp.array([3, 10]), 31) == 10) and np.all(pay(jnp.array([3, 10]), 30) == 3)
    alone = jax.jit(lambda owed, t: updates_to_pay(cfg, owed, t))
    assert int(alone(jnp.int32(7), 5)) == 7 and int(alone(jnp.int32(most), 5)) == most
    # Under a vmap of another name the members do not share a count: each pays its own.
    other = jax.jit(jax.vmap(lambda owed, t: updates_to_pay(cfg, owed, t), (0, None), axis_name="other"))
    assert np.all(other(jnp.array([3, 10]), 5) == jnp.array([3, 10]))


@pytest.mark.slow
def test_members_that_owe_updates_at_a_checkpoint_resume_exactly(tmp_path, monkeypatch):
    """Two seeds in one program, no re-initialisation: at the stop after chunk 2 the seed with more
    cars owes updates (fewer made than stored), and the stopped and resumed run still equals the
    uninterrupted one line for line, the owed count being part of the checkpoint."""
    import functools

    args = [*SMOKE, "--set", "reinit_steps=0", "--devices", "1"]
    args[args.index("reinit_steps=128")] = "checkpoint_interval=64"
    module = load_script("run", "run_cli_intersection_owed")
    assert module.main([*args, "--out", str(tmp_path / "whole")]) == 0
    original = train_mod.train
    monkeypatch.setattr(train_mod, "train", functools.partial(original, stop_after_chunks=2))
    assert module.main([*args, "--out", str(tmp_path / "split")]) == 1  # stopped early
    monkeypatch.setattr(train_mod, "train", original)
    assert module.main(["--resume", str(tmp_path / "split"), "--quiet"]) == 0
    behind = []
    for seed in (0, 1):
        for folder in ("metrics", "eval"):
            whole, split = (tmp_path / run / folder / f"seed_{seed}.jsonl" for run in ("whole", "split"))
            assert whole.read_text() == split.read_text()
        rows = lines(tmp_path / "whole" / "metrics" / f"seed_{seed}.jsonl")
        stored = [row["buffer/stored_rows"] - rows[0]["buffer/stored_rows"] for row in rows]  # after warm-up
        behind.append(rows[1]["train/updates"] < stored[1])
        assert rows[2]["train/updates"] == stored[2]
    assert any(behind)  # some member owed updates when the run stopped
