"""Learning throughput: gradient updates per second of one agent at a scenario's shapes on batches
of real observations (packed beside dense, against the matmul ceiling), and end-to-end training
steps per second of the trainer itself, compile time and memory included."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from xrl_jax import train
from xrl_jax.agents import Agent, make_agent
from xrl_jax.benchmarks.occupancy import packed_only
from xrl_jax.benchmarks.timing import (
    matmul_call,
    peak_memory_bytes,
    seconds_of,
    timed_alternately,
    update_flops,
)
from xrl_jax.config import parse_overrides, preset, preset_train_fields
from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation
from xrl_jax.sets import MEMBERS_AXIS


def real_batch(observations: dict, batch_size: int, agent: Agent, key) -> dict:
    """A replay batch of ``batch_size`` observations and next observations drawn from real rollouts
    (:mod:`xrl_jax.benchmarks.occupancy`), so that its sets hold as many objects as training sees;
    random actions and rewards (they do not change the cost)."""
    total = next(iter(observations.values())).shape[0]
    k_obs, k_next, k_action, k_reward = jax.random.split(key, 4)

    def draw(k):
        rows = np.asarray(jax.random.randint(k, (batch_size,), 0, total))
        return {name: jnp.asarray(values[rows]) for name, values in observations.items()}

    return {
        "obs": draw(k_obs),
        "next_obs": draw(k_next),
        "action": agent.random_action(k_action, (batch_size,)),
        "reward": jax.random.normal(k_reward, (batch_size,)),
        "terminated": jnp.zeros(batch_size, bool),
        "truncated": jnp.zeros(batch_size, bool),
    }


def bench_update(
    env: str,
    algo: str,
    width: int | None,
    seeds: int,
    updates: int,
    repeats: int,
    observations: dict,
    preset_name: str = "paper",
    batch_size: int | None = None,
) -> dict:
    """Gradient updates/s of one agent at ``env``'s shapes, ``seeds`` agent states vmapped (on the
    named members axis, as the trainer does), on batches of real observations.

    When the preset packs the present objects (``packed_rows``), the packed update and the dense one
    (``dense_sets``) are timed side by side, alternating with each other and with the 2048² matmul
    ceiling, on the same batches and states; otherwise the one update and the ceiling. Every timed
    call runs ``updates`` updates over as many batches. FLOPs per update come from XLA's cost analysis
    of one compiled update (for the packed update: of its packed branches, xrl_jax.sets).
    """

    config = preset(preset_name, env, algo)
    if width is not None:
        config = config.replace(actor_width=width, critic_width=width)
    if batch_size is None:
        batch_size = int(preset_train_fields(preset_name, env).get("batch_size", 256))
    example = dummy_observation(ENV_OBSERVATIONS[env])
    variants = {"packed": config} if config.packed_rows is not None else {}
    variants["dense" if variants else "update"] = config.replace(dense_sets=True)
    size = envs.action_size(envs.action_space(f"{env}_discrete" if config.is_discrete else env))
    agents = {name: make_agent(c, example, size) for name, c in variants.items()}
    key = jax.random.PRNGKey(0)
    any_agent = next(iter(agents.values()))
    states = jax.jit(jax.vmap(any_agent.init))(jax.random.split(key, seeds))  # same parameters for all
    batches = _stacked_batches(observations, batch_size, any_agent, updates)

    calls, out = {}, {"env": env, "algo": algo, "width": config.actor_width, "seeds": seeds,
                      "batch_size": batch_size, "packed_rows": config.packed_rows}  # fmt: skip
    for name, agent in agents.items():
        update_all = jax.vmap(agent.update, in_axes=(0, 0, None), axis_name=MEMBERS_AXIS)

        def run(states, key, update_all=update_all):
            def body(states, inputs):
                key, batch = inputs
                return update_all(jax.random.split(key, seeds), states, batch)[0], None

            return jax.lax.scan(body, states, (jax.random.split(key, updates), batches))[0]

        compiled, compile_s = seconds_of(lambda run=run: jax.jit(run).lower(states, key).compile())
        flops = update_flops(
            agent if name != "packed" else packed_only(agent), batch_size, seeds, compiled=True
        )
        jax.block_until_ready(compiled(states, key))
        calls[name] = lambda compiled=compiled: compiled(states, key)
        out[name] = {"gflop_per_update": flops / 1e9, "compile_s": compile_s}
    matmul, matmul_flops = matmul_call()
    seconds = timed_alternately({**calls, "matmul": matmul}, repeats)
    ceiling = matmul_flops / seconds["matmul"] / 1e9
    out["matmul_gflops"] = ceiling
    for name in calls:
        achieved = out[name]["gflop_per_update"] * updates * seeds / seconds[name]
        out[name].update(
            updates_per_s_per_seed=updates / seconds[name],
            achieved_gflops=achieved,
            fraction_of_matmul=achieved / ceiling,
        )
    if "packed" in calls:
        out["packed_time_over_dense"] = seconds["packed"] / seconds["dense"]
    return out


def _stacked_batches(observations: dict, batch_size: int, agent: Agent, count: int) -> dict:
    keys = jax.random.split(jax.random.PRNGKey(1), count)
    batches = [real_batch(observations, batch_size, agent, k) for k in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *batches)


def short_run_config(
    env: str,
    algo: str,
    preset_name: str,
    seeds: int,
    width: int | None,
    overrides: list,
    chunks: int,
    log_interval: int,
    kept_chunks: int | None = None,
):
    """A benchmark's short run: ``chunks`` chunks of ``log_interval`` steps per seed (a ``--set
    log_interval`` wins), a warm-up of 256, evaluation and checkpoints every chunk (between chunks, not
    timed: any preset fits), the buffer no larger than the first ``kept_chunks`` chunks (all by
    default) fill. A malformed or unknown ``KEY=VALUE`` raises :class:`ConfigError` (one line)."""
    sets = {"log_interval": str(log_interval), "warmup_steps": "256", **parse_overrides(overrides)}
    sets.setdefault("eval_interval", sets["log_interval"])
    sets.setdefault("checkpoint_interval", sets["log_interval"])
    if width is not None:
        sets.update(actor_width=str(width), critic_width=str(width))
    interval = train.resolve_config(env, algo, preset_name, overrides=sets).log_interval
    cfg = train.resolve_config(
        env, algo, preset_name, num_seeds=seeds, total_steps=interval * chunks, overrides=sets
    )
    kept = interval * (chunks if kept_chunks is None else kept_chunks)
    return cfg.replace(buffer_size=max(cfg.batch_size, min(cfg.buffer_size, kept)))


def bench_train(
    env: str,
    algo: str,
    seeds: int,
    width: int | None,
    chunks: int,
    preset_name: str,
    overrides: list,
    devices: int = 1,
) -> dict:
    """End-to-end training env-steps/s (one gradient step per transition included), all seeds together,
    spread over ``devices`` devices as a run spreads its members.

    Times ``chunks`` compiled chunks after the first (which carries compilation and the warm-up);
    reports the compile time, the per-seed memory estimate and the peak memory.
    """
    # On the Intersection the run's last step pays every update its members still owe: a run longer by
    # one chunk keeps that settlement out of the timed chunks, which then run as a long run's do.
    last = train.scenario_kind(train.resolve_config(env, algo, preset_name)).steps_read_run_length
    cfg = short_run_config(
        env, algo, preset_name, seeds, width, overrides, chunks + 1 + last, 2000, kept_chunks=chunks + 1
    )
    log_interval = cfg.log_interval
    start = time.perf_counter()
    trainer = train.make_trainer(cfg, devices=jax.devices()[:devices])
    state = jax.block_until_ready(trainer.init(0, range(seeds)))
    setup_s = time.perf_counter() - start
    (state, metrics), first_chunk_s = seconds_of(lambda: trainer.chunk(state, np.int32(0)))  # mostly warm-up
    updates_before = int(np.sum(np.asarray(metrics.metrics["train/updates"])))
    start = time.perf_counter()
    for c in range(1, chunks + 1):
        state, metrics = trainer.chunk(state, np.int32(c * cfg.chunk_vector_steps))
    jax.block_until_ready(metrics)
    seconds = time.perf_counter() - start
    _, eval_first_s = seconds_of(lambda: trainer.evaluate(state))
    _, eval_s = seconds_of(lambda: trainer.evaluate(state))
    steps_timed = chunks * log_interval * seeds
    updates = int(np.sum(np.asarray(metrics.metrics["train/updates"]))) - updates_before
    per_seed = train.estimate_seed_bytes(trainer)
    rate = steps_timed / seconds
    return {
        "env": env,
        "algo": algo,
        "seeds": seeds,
        "devices": devices,
        "width": width or cfg.agent.actor_width,
        "num_envs": cfg.num_envs,
        "batch_size": cfg.batch_size,
        "env_steps_per_s": rate,
        "updates_per_s": updates / seconds,  # racing: one per transition; Intersection: per acting vehicle
        "per_seed_env_steps_per_s": rate / seeds,
        "hours_for_1e6_steps_all_seeds": 1e6 * seeds / rate / 3600,
        "compile_s": {"setup_and_init": setup_s, "first_chunk": first_chunk_s, "first_eval": eval_first_s},
        "eval_s": eval_s,
        "eval_episodes": cfg.eval_episodes,
        "memory": {"per_seed_estimate_bytes": per_seed, **peak_memory_bytes()},
    }
