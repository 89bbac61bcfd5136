"""Trainer: config validation, episode window, memory planning, and the compiled loop's bookkeeping."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from train_support import fast_env_registered, prepare_cache

from xrl_jax import train as T
from xrl_jax.config import AgentConfig
from xrl_jax.train import ConfigError, MemoryPlanError, TrainConfig, parse_overrides, resolve_config
from xrl_jax.train.episodes import window_add, window_init, window_means
from xrl_jax.train.kinds import scenario_kind
from xrl_jax.train.memory import tree_bytes

# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------


def test_presets_resolve_with_the_spec_values():
    paper = resolve_config("tracking", "xsac", "paper")
    assert (paper.total_steps, paper.buffer_size, paper.batch_size, paper.warmup_steps) == (
        1_000_000, 1_000_000, 256, 256,
    )  # fmt: skip
    assert (paper.eval_interval, paper.eval_episodes, paper.log_interval) == (100_000, 100, 2_000)
    assert paper.agent.actor_lr == 3e-4 and paper.agent.gamma == 0.95
    assert resolve_config("country_road", "xdsac", "paper").agent.target_entropy == 1.24
    assert resolve_config("tracking", "xdsac", "paper").env_name == "tracking_discrete"
    quick = resolve_config("tracking", "xdsac", "quick", num_seeds=4)
    assert quick.total_steps < paper.total_steps and quick.agent.actor_width == 64 and quick.num_seeds == 4
    assert (quick.agent.init_alpha, quick.agent.alpha_lr, quick.agent.gamma) == (0.005, 1e-3, 0.98)
    assert quick.buffer_size == quick.total_steps  # the quick buffer keeps every transition...
    assert resolve_config("tracking", "xsac", "quick", total_steps=100_000).buffer_size == 100_000
    longer = resolve_config("country_road", "sac", "quick", overrides={"total_steps": "70000"})
    assert longer.buffer_size == 70_000
    assert resolve_config("tracking", "xsac", "quick", total_steps=100).buffer_size == 128  # >= batch
    chosen = resolve_config("tracking", "xsac", "quick", overrides={"buffer_size": "20000"})
    assert chosen.buffer_size == 20_000  # ...unless the user sets its size
    # the quick learning rates decay to zero at the last update (one per transition after warm-up)
    assert (quick.agent.actor_lr, quick.agent.critic_lr) == (6e-4, 6e-4)
    assert quick.agent.lr_decay_updates == quick.total_steps - quick.warmup_steps == 239_000  # Tracking: 240k
    assert longer.agent.lr_decay_updates == 70_000 - longer.warmup_steps
    constant = resolve_config("tracking", "xsac", "quick", overrides={"lr_decay_updates": "0"})
    assert constant.agent.lr_decay_updates == 0
    assert paper.agent.lr_decay_updates == 0
    ix = resolve_config("intersection", "xdsac", "quick").agent  # a fixed α, lower than the paper's 0.015
    assert (ix.init_alpha, ix.auto_alpha, ix.gamma) == (0.005, False, 0.95)
    assert (ix.actor_lr, ix.critic_lr, ix.lr_decay_updates) == (6e-4, 6e-4, 0)
    assert resolve_config("intersection", "dsac", "quick").agent.actor_lr == 6e-4  # one rate for all four
    smoke = resolve_config("country_road", "sac", "smoke", total_steps=128)
    assert smoke.total_steps == 128 and smoke.agent.actor_width == 16


def test_overrides_reach_train_and_agent_fields():
    cfg = resolve_config(
        "tracking", "xsac", "smoke",
        overrides=parse_overrides(["gamma=0.9", "agent.kappa=-0.01", "num_envs=8", "log_interval=64",
                                   "memory_budget_gb=1.5", "truncation=bootstrap"]),
    )  # fmt: skip
    assert cfg.agent.gamma == 0.9 and cfg.agent.kappa == -0.01
    assert cfg.num_envs == 8 and cfg.memory_budget_gb == 1.5
    assert cfg.buffer_layout == "explicit"
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    "kwargs, overrides, message",
    [
        ({"env": "moon"}, [], "unknown scenario 'moon'; known: country_road, tracking"),
        ({"algo": "a2c"}, [], "allowed: sac, dsac, xsac, xdsac, ppo, dppo, xppo, xdppo"),
        ({"preset": "fast"}, [], "allowed: paper, quick, smoke"),
        ({"total_steps": -4}, [], "total_steps must be a positive integer"),
        ({"total_steps": 130}, [], "multiple of num_envs"),
        ({"num_seeds": 0}, [], "num_seeds must be a positive integer"),
        ({}, ["lr=1e-3"], "unknown setting 'lr'; allowed:"),
        ({}, ["gamma=fast"], "cannot parse 'fast'"),
        ({}, ["gamma=2"], "gamma must lie in [0, 1]"),
        ({}, ["eval_interval=100"], "multiple of log_interval"),
        ({}, ["warmup_steps=2"], "at least num_envs"),
        ({}, ["seed=-1"], "seed must be a non-negative integer"),
        ({}, ["batch_size=4096"], "at least batch_size"),
        ({}, ["env=country_road"], "use --env"),
        ({}, ["algo=sac"], "use --algo"),
        ({}, ["truncation=maybe"], "unknown truncation"),
        ({}, ["train_tracks=-1"], "train_tracks must be a non-negative integer"),
        ({}, ["track_feed_size=6"], "track_feed_size (6) must be at least 2 x num_envs (8)"),
        ({}, ["track_seed=1"], "the evaluation tracks would be training tracks"),
    ],
)
def test_invalid_settings_fail_with_one_line(kwargs, overrides, message):
    args = {"env": "tracking", "algo": "xdsac", "preset": "smoke", **kwargs}
    with pytest.raises(ConfigError) as info:
        resolve_config(**args, overrides=parse_overrides(overrides))
    assert message in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("item", ["gamma", "=3", "gamma=", "  =x"])
def test_malformed_set_items_are_rejected(item):
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_overrides([item])


def test_train_config_checks_the_agent_matches():
    with pytest.raises(ConfigError, match="differs"):
        TrainConfig(algo="xsac", agent=AgentConfig(algo="sac"))


def test_chunk_bookkeeping():
    cfg = resolve_config("tracking", "xdsac", "smoke", total_steps=200, overrides={"log_interval": "64"})
    assert (cfg.chunk_vector_steps, cfg.total_vector_steps, cfg.num_chunks) == (16, 50, 4)
    assert [cfg.chunk_end_step(c) for c in range(4)] == [64, 128, 192, 200]


# ---------------------------------------------------------------------------------------------
# Episode window (rollout metrics over the last 100 episodes)
# ---------------------------------------------------------------------------------------------


def test_episode_window_keeps_the_last_hundred_finished_episodes():
    window = window_init(jnp.float32)
    add = jax.jit(window_add)
    returns = []
    for step in range(60):
        done = jnp.array([step % 2 == 0, True, step % 3 == 0])
        value = jnp.array([step, 1000 + step, 2000 + step], jnp.float32)
        window = add(window, done, value, jnp.ones(3, jnp.int32), done & (value > 2000), jnp.zeros(3))
        returns += [float(v) for v, d in zip(value, done, strict=True) if d]
    means, filled = jax.device_get(window_means(window, scenario_kind("tracking").rollout_velocity))
    assert filled
    assert int(window.count) == len(returns)
    assert means["rollout/avg_episode_return"] == pytest.approx(np.mean(returns[-100:]), rel=1e-6)
    last = returns[-100:]
    assert means["rollout/early_termination_rate"] == pytest.approx(np.mean([r > 2000 for r in last]))


def test_empty_window_has_no_data():
    means, filled = window_means(window_init(jnp.float32), scenario_kind("tracking").rollout_velocity)
    assert not filled and int(means["rollout/episodes"]) == 0


# ---------------------------------------------------------------------------------------------
# The compiled trainer (tiny smoke configuration, shared with test_cli through the trainer cache)
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def smoke_trainer(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2)
    return cfg, T.get_trainer(cfg)


def test_memory_plan_groups_seeds_or_refuses(smoke_trainer):
    cfg, trainer = smoke_trainer
    sizes = T.estimate_seed_bytes(trainer)
    assert sizes["buffer"] > 0 and sizes["agent"] > 0
    assert sizes["total"] == sizes["buffer"] + sizes["agent"] + sizes["env"] + sizes["workspace_estimate"]
    # Buffer: one stored observation per transition (compact layout) plus one spare row.
    rows = -(-cfg.buffer_size // cfg.num_envs) + 1
    assert sizes["buffer"] >= rows * cfg.num_envs * (6 + 25 * 4) * 4
    shared = tree_bytes((trainer.env_params, trainer.eval_params))
    five = cfg.replace(num_seeds=5)
    plan = T.plan_memory(trainer, five, budget_bytes=shared + 2 * sizes["total"] + 1)
    assert plan["groups"] == [[0, 1, 2], [3, 4]] or plan["groups"] == [[0, 1], [2, 3], [4]]
    assert all(len(g) <= 2 for g in plan["groups"]) and sum(map(len, plan["groups"])) == 5
    assert plan["groups_limited_by"] == "memory"
    roomy = T.plan_memory(trainer, five, budget_bytes=10**15)
    assert roomy["groups"] == [[0, 1, 2, 3, 4]] and roomy["groups_limited_by"] is None
    capped = T.plan_memory(trainer, five.replace(max_group_size=2), budget_bytes=10**15)
    assert len(capped["groups"]) == 3 and capped["groups_limited_by"] == "max_group_size"
    with pytest.raises(MemoryPlanError, match="one member needs about"):
        T.plan_memory(trainer, five, budget_bytes=sizes["total"] // 2)


def test_warmup_then_one_update_per_transition(smoke_trainer):
    cfg, trainer = smoke_trainer
    state = trainer.init(jnp.int32(0), jnp.arange(2, dtype=jnp.int32))
    updates, rows = [], []
    for chunk in range(cfg.num_chunks):
        state, report = trainer.chunk(state, jnp.int32(chunk * cfg.chunk_vector_steps))
        updates.append(np.asarray(report.metrics["train/updates"]))
        rows.append(np.asarray(report.metrics["buffer/stored_rows"]))
        assert np.isfinite(np.asarray(report.metrics["train/loss_critic"])).all()
        # the warm-up chunk has no update, so its losses have no data (written as null)
        assert np.asarray(report.has_data["train/loss_critic"]).tolist() == [chunk > 0] * 2
        assert np.asarray(report.health.first_nonfinite_step).tolist() == [-1, -1]
        assert np.asarray(report.health.agent_finite).all()
    # 64 warm-up transitions without updates, then exactly one update per collected transition.
    assert [u.tolist() for u in updates] == [[0, 0], [64, 64], [128, 128]]
    assert [r.tolist() for r in rows] == [[16, 16], [32, 32], [48, 48]]
    keys, episodes = trainer.evaluate(state)
    assert episodes["return"].shape == (2, cfg.eval_episodes)
    assert not np.array_equal(np.asarray(keys), np.asarray(state.eval_key))  # a fresh eval stream


def test_fresh_tracks_give_every_episode_a_new_track_from_the_seeds_own_stream(tmp_path):
    """``train_tracks=0`` (the default): each seed's envs take new tracks from the seed's own stream
    (envs/track_feed.py), the metrics count them (distinct tracks = every env's first episode plus
    every finished one, none reused), and refills between chunks keep the feed's memory fixed.
    Episodes are cut to 8 steps so that 4 chunks (8 episodes each per seed) need refills of a
    16-track feed."""
    from envs.track_generator import generate_track
    from xrl_jax.train import make_envs

    prepare_cache(tmp_path)
    cfg = resolve_config(
        "tracking", "xdsac", "smoke", num_seeds=2, total_steps=256,
        overrides={"train_tracks": "0", "track_feed_size": "16", "track_seed": "7"},
    )  # fmt: skip
    env, params, eval_params = make_envs(cfg)
    trainer = T.make_trainer(cfg, (env, params.replace(max_steps=8), eval_params))
    state = trainer.init(jnp.int32(3), jnp.arange(2, dtype=jnp.int32))
    capacity = state.feed.slot_number.shape
    for chunk in range(cfg.num_chunks):
        state, report = trainer.chunk(state, jnp.int32(chunk * cfg.chunk_vector_steps))
    used = np.asarray(report.metrics["rollout/tracks_used"])
    finished = np.asarray(report.metrics["rollout/episodes"])
    assert (finished >= 28).all()  # 4 envs x 64 steps / 8 steps = 32 (more if a car leaves the track)
    np.testing.assert_array_equal(used, cfg.num_envs + finished)
    np.testing.assert_array_equal(np.asarray(report.metrics["rollout/tracks_reused"]), [0, 0])
    feed = state.feed
    assert feed.slot_number.shape == capacity == (2, 16)
    assert (np.asarray(feed.generated) >= used).all()
    for row in np.asarray(feed.slot_number):  # the feed holds distinct, recent track numbers
        assert len(set(row.tolist())) == 16
    # Seed i's stream: track n = generate_track(fold_in(fold_in(fold_in(PRNGKey(track_seed), base
    # seed), i), n)); two seeds never share it. Length tolerance as in tests/test_track_feed.py.
    stream = jax.random.fold_in(jax.random.PRNGKey(7), 3)
    for seed in (0, 1):
        newest = int(np.argmax(np.asarray(feed.slot_number[seed])))
        number = int(feed.slot_number[seed, newest])
        expected = jax.jit(generate_track)(jax.random.fold_in(jax.random.fold_in(stream, seed), number))
        length = float(feed.params.tracks.length[seed, newest])
        np.testing.assert_allclose(length, float(expected.length), atol=0.2)
    assert abs(float(feed.params.tracks.length[0, 0]) - float(feed.params.tracks.length[1, 0])) > 1.0
    # The feed is part of the checkpointed run state: a restore gives it back exactly.
    from xrl_jax.checkpoint import Checkpointer

    checkpointer = Checkpointer(tmp_path / "checkpoints")
    try:
        checkpointer.save(256, state, {"step": 256})
        restored, _ = checkpointer.restore(trainer.abstract_state(2))
    finally:
        checkpointer.close()
    for saved, loaded in zip(jax.tree.leaves(state.feed), jax.tree.leaves(restored.feed), strict=True):
        np.testing.assert_array_equal(np.asarray(saved), np.asarray(loaded))


# ---------------------------------------------------------------------------------------------
# Learning (slow): the quick preset must improve the evaluation return on Tracking
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.optimised
def test_quick_preset_learns_on_tracking(tmp_path):
    """Two seeds of XDSAC, quick preset cut to the README quick start's 80k steps and evaluated every 5k
    steps as when measured (14 min on 2 CPU cores; the preset's own 240k steps take twice that): the
    final evaluation on the 100 fixed tracks beats the first one (at 5k steps) clearly, for the IQM
    over seeds."""
    from xrl_jax.runs.folder import read_rows as read_jsonl

    cfg = resolve_config("tracking", "xdsac", "quick", 2, 80_000, overrides={"eval_interval": "5000"})
    summary = T.train(cfg, tmp_path, progress=False, log=lambda *_: None)
    assert summary["complete"]
    first = np.mean([read_jsonl(tmp_path / "eval" / f"seed_{s}.jsonl")[0]["avg_return"] for s in range(2)])
    final = summary["aggregate"]["avg_return"]["estimate"]
    # Measured (the README's quick start): first evaluation 4.0 and 1.4, final 20.7 and 55.5; single
    # seeds have ended anywhere from 16 to 65, so this only checks clear learning.
    assert final > first + 5.0, (first, final)


# ---------------------------------------------------------------------------------------------
# Compile once: the design rests on one trace of the env step per compiled program
# ---------------------------------------------------------------------------------------------


class TraceCountingEnv:
    """Delegates to an env and counts the calls of its step: under ``jit`` a Python call is a trace."""

    def __init__(self, env):
        self._env = env
        self.step_traces = 0

    def __getattr__(self, name):
        return getattr(self._env, name)

    def step_env(self, key, state, action, params):
        self.step_traces += 1
        return self._env.step_env(key, state, action, params)

    def step(self, key, state, action, params):
        return self.step_env(key, state, action, params)


def test_the_env_step_is_traced_once_for_the_chunk_and_once_for_evaluation(tmp_path):
    """As Brax's SAC test counts env traces: a run, its resume from a checkpoint and a second run in
    the same process reuse the compiled chunk and evaluation (a retrace would recompile for minutes)."""
    prepare_cache(tmp_path / "cache")
    cfg = resolve_config("tracking", "xdsac", "smoke", num_seeds=2, overrides={"eval_interval": "64"})
    env, params, eval_params = T.make_envs(cfg)
    counting = TraceCountingEnv(env)
    trainer = T.make_trainer(cfg, (counting, params, eval_params))
    quiet = {"progress": False, "log": lambda *_: None, "trainer": trainer}
    assert T.train(cfg, tmp_path / "run", stop_after_chunks=2, **quiet) is None
    assert counting.step_traces == 2  # the chunk's scan body and the evaluation's loop body
    assert T.train(cfg, tmp_path / "run", resume=True, **quiet)["complete"]
    assert T.train(cfg.replace(seed=3), tmp_path / "other", **quiet)["complete"]
    assert counting.step_traces == 2


@pytest.mark.slow  # ~28 s; tests/test_checkpoint.py's manifest tests check the same verdicts by default
def test_a_resume_says_what_it_could_not_verify_or_find(tmp_path):
    """Papercuts of issue 28: a resume whose checkpoint has no digest manifest lists it in the summary
    (it was only checked for finiteness), and a resume that finds no checkpoint at all (deleted, or
    every one set aside as damaged) warns that it starts again from step 0 instead of doing so silently."""
    prepare_cache(tmp_path / "cache")
    with fast_env_registered() as env:  # the host loop's resume: any env will do
        cfg = resolve_config(env, "xdsac", "smoke", num_seeds=2)
        resume_says_what_it_could_not_verify_or_find(tmp_path, cfg)


def resume_says_what_it_could_not_verify_or_find(tmp_path, cfg):
    import shutil

    warnings = []
    quiet = {
        "progress": False,
        "log": lambda *_: None,
        "warn": warnings.append,
        "trainer": T.make_trainer(cfg),
    }
    assert T.train(cfg, tmp_path / "run", stop_after_chunks=2, **quiet) is None
    shutil.copytree(tmp_path / "run", tmp_path / "lost")
    for manifest in (tmp_path / "run" / "checkpoints").rglob("xrl_manifest.json"):
        manifest.unlink()
    summary = T.train(cfg, tmp_path / "run", resume=True, **quiet)
    assert summary["complete"] and summary["unverified_checkpoints"] == [{"group": 0, "step": 128}]
    shutil.rmtree(tmp_path / "lost" / "checkpoints")
    warnings.clear()
    assert "unverified_checkpoints" not in T.train(cfg, tmp_path / "lost", resume=True, **quiet)
    assert (
        len(warnings) == 1
        and "has no checkpoint" in warnings[0]
        and "starts again from step 0" in warnings[0]
    )
    # Seeds one after another: a group that had not started when the run stopped has no checkpoint
    # either, and nothing was lost; the resume says so in its log, without a warning.
    one_by_one = cfg.replace(max_group_size=1)
    logged, warnings[:] = [], []
    quiet |= {"log": logged.append, "trainer": T.make_trainer(one_by_one)}
    assert T.train(one_by_one, tmp_path / "one_by_one", stop_after_chunks=1, **quiet) is None
    assert T.train(one_by_one, tmp_path / "one_by_one", resume=True, **quiet)["complete"]
    assert warnings == [] and "member group 2 of 2 had not started; it starts now" in logged
