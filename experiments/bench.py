"""Throughput benchmarks; every sub-command prints one JSON document to stdout.

    python experiments/bench.py env      [--scenarios tracking country_road] [--batches 1 64 1024 4096 8192]
    python experiments/bench.py intersection [--vehicles 1 2 4 8] [--batches 1 64 1024 4096] [--discrete]
    python experiments/bench.py matmul   [--size 2048]
    python experiments/bench.py update   [--env tracking] [--algos sac dsac xsac xdsac] [--widths 64 128 256]
                                         [--seeds 1 5 20] [--preset paper] [--batch-size B]
    python experiments/bench.py train    [--env tracking] [--algos xsac xdsac] [--seeds 1 5 20]
                                         [--widths 256 64] [--chunks 2] [--set KEY=VALUE ...]
                                         [--devices 1 2]  (members spread over that many devices)
    python experiments/bench.py tracks   [--seeds 1 4 20] [--count 64]

Numbers are wall-clock rates after compilation (compile time is reported separately), measured with
``block_until_ready`` on the default JAX device (``train --devices``: on that many devices; on a
CPU-only machine the host is split into that many XLA devices). Tests never assert timings; these
scripts do.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax.config import PRESETS


def machine_info() -> dict:
    device = jax.devices()[0]
    return {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "device": getattr(device, "device_kind", str(device)),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }


def timed(fn: Callable[[], object], repeats: int) -> float:
    """Best-of-``repeats`` wall time of ``fn()`` (its result blocked on), in seconds."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def timed_alternately(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Best-of-``repeats`` wall times of several calls timed in turn, so that a noisy machine (other
    jobs, a shared VM's stolen cycles) slows all of them alike instead of whichever ran last."""
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            best[name] = min(best[name], timed(fn, 1))
    return best


def matmul_call(size: int = 2048) -> tuple[Callable[[], object], float]:
    """A compiled, warmed-up ``size``² float32 matmul and its FLOPs: the compute ceiling."""
    a = jax.random.normal(jax.random.PRNGKey(0), (size, size), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (size, size), jnp.float32)
    matmul = jax.jit(jnp.matmul)
    jax.block_until_ready(matmul(a, b))
    return (lambda: matmul(a, b)), 2.0 * size**3


def bench_matmul(size: int = 2048, repeats: int = 5) -> dict:
    """Float32 matmul throughput of this device: the ceiling that compute-bound updates are compared to."""
    call, flops = matmul_call(size)
    seconds = timed(call, repeats)
    return {"size": size, "seconds": seconds, "gflops": flops / seconds / 1e9}


def compile_rollout(reset, rollout, key):
    """First calls of a jitted ``reset(key)`` and ``rollout(key, state)``: returns the reset state,
    the rollout's output and the two first-call times (compilation plus one run each)."""
    start = time.perf_counter()
    _, state = jax.block_until_ready(reset(key))
    reset_compile = time.perf_counter() - start
    start = time.perf_counter()
    output = jax.block_until_ready(rollout(key, state))
    rollout_compile = time.perf_counter() - start
    return state, output, {"reset": reset_compile, "rollout": rollout_compile}


def bench_env(scenario: str, batch: int, steps: int, repeats: int) -> dict:
    """Env-steps/s of ``batch`` auto-resetting envs driven by random actions inside one ``lax.scan``."""
    import envs
    from envs.core import vmap_env

    env, params = envs.make(scenario)
    venv = vmap_env(env, batch)

    @jax.jit
    def reset(key):
        return venv.reset(key, params)

    @jax.jit
    def rollout(key, state):
        def body(state, key):
            key_act, key_step = jax.random.split(key)
            action = venv.sample_actions(key_act, params)
            _, state, reward, *_ = venv.step(key_step, state, action, params)
            return state, reward.sum()

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    key = jax.random.PRNGKey(0)
    state, _, compile_s = compile_rollout(reset, rollout, key)
    reset_seconds = timed(lambda: reset(key), repeats)
    rollout_seconds = timed(lambda: rollout(key, state), repeats)
    return {
        "scenario": scenario,
        "batch": batch,
        "steps_per_call": steps,
        "env_steps_per_s": batch * steps / rollout_seconds,
        "reset_us_per_env": 1e6 * reset_seconds / batch,
        "compile_s": compile_s,
    }


def bench_intersection(max_vehicles: int, batch: int, steps: int, repeats: int, discrete: bool) -> dict:
    """Env-steps/s and agent-steps/s of ``batch`` intersection envs (fixed ``max_vehicles``), random
    actions for all 8 slots, inside one jitted ``lax.scan``. The env restarts itself every 600 steps,
    so no auto-reset wrapper is needed; agent-steps count the slots that acted (``info["acted"]``)."""
    import envs
    from envs.core import VmapWrapper

    name = "intersection_discrete" if discrete else "intersection"
    env, params = envs.make(name, max_vehicles=max_vehicles)
    venv = VmapWrapper(env, batch)

    @jax.jit
    def reset(key):
        return venv.reset(key, params)

    @jax.jit
    def rollout(key, state):
        def body(carry, key):
            state, agent_steps = carry
            key_act, key_step = jax.random.split(key)
            action = jax.vmap(env.sample_actions, in_axes=(0, None))(jax.random.split(key_act, batch), params)
            _, state, reward, _, _, info = venv.step(key_step, state, action, params)
            return (state, agent_steps + jnp.sum(info["acted"], dtype=jnp.int32)), reward.sum()

        (state, agent_steps), rewards = jax.lax.scan(
            body, (state, jnp.zeros((), jnp.int32)), jax.random.split(key, steps)
        )
        return state, agent_steps, rewards

    key = jax.random.PRNGKey(0)
    state, (_, agent_steps, _), compile_s = compile_rollout(reset, rollout, key)
    rollout_seconds = timed(lambda: rollout(key, state), repeats)
    return {
        "scenario": name,
        "max_vehicles": max_vehicles,
        "batch": batch,
        "steps_per_call": steps,
        "env_steps_per_s": batch * steps / rollout_seconds,
        "agent_steps_per_s": int(agent_steps) / rollout_seconds,
        "mean_alive_agents": int(agent_steps) / (batch * steps),
        "compile_s": compile_s,
    }


def peak_memory_bytes() -> dict:
    """Peak device memory (accelerators) and the process's peak resident memory (always)."""
    import resource

    out = {"host_peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:
        stats = {}
    if "peak_bytes_in_use" in stats:
        out["device_peak_bytes"] = int(stats["peak_bytes_in_use"])
    return out


def bench_train(
    env: str,
    algo: str,
    seeds: int,
    width: int | None,
    chunks: int,
    preset: str,
    overrides: list,
    devices: int = 1,
) -> dict:
    """End-to-end training env-steps/s (one gradient step per transition included), all seeds together,
    spread over ``devices`` devices as a run spreads its members.

    Times ``chunks`` compiled chunks after the first (which carries compilation and the warm-up);
    reports the compile time, the per-seed memory estimate and the peak memory.
    """
    from xrl_jax import train as T

    sets = {"log_interval": "2000", "warmup_steps": "256", **dict(item.split("=", 1) for item in overrides)}
    # Evaluation and checkpoints happen between chunks (not timed): every chunk, so any preset fits.
    sets.setdefault("eval_interval", sets["log_interval"])
    sets.setdefault("checkpoint_interval", sets["log_interval"])
    if width is not None:
        sets.update(actor_width=str(width), critic_width=str(width))
    log_interval = int(sets["log_interval"])
    steps = log_interval * (chunks + 1)
    cfg = T.resolve_config(env, algo, preset, num_seeds=seeds, total_steps=steps, overrides=sets)
    cfg = cfg.replace(buffer_size=max(cfg.batch_size, min(cfg.buffer_size, steps)))
    start = time.perf_counter()
    trainer = T.make_train(cfg, devices=jax.devices()[:devices])
    state = jax.block_until_ready(trainer.init(0, range(seeds)))
    setup_s = time.perf_counter() - start
    start = time.perf_counter()
    state, metrics = trainer.chunk(state, np.int32(0))
    jax.block_until_ready(metrics)
    first_chunk_s = time.perf_counter() - start  # compile + one chunk (mostly warm-up)
    updates_before = int(np.sum(np.asarray(metrics.metrics["train/updates"])))
    start = time.perf_counter()
    for c in range(1, chunks + 1):
        state, metrics = trainer.chunk(state, np.int32(c * cfg.chunk_vector_steps))
    jax.block_until_ready(metrics)
    seconds = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(trainer.evaluate(state))
    eval_first_s = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(trainer.evaluate(state))
    eval_s = time.perf_counter() - start
    steps_timed = chunks * log_interval * seeds
    updates = int(np.sum(np.asarray(metrics.metrics["train/updates"]))) - updates_before
    per_seed = T.estimate_seed_bytes(trainer)
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


def bench_tracks(seeds: int, count: int, repeats: int) -> dict:
    """Fresh-track cost: a refill of ``count`` tracks into each of ``seeds`` feeds (generation, ring
    tables, reset observations, the slot writes), as the training chunk runs it; and XLA's FLOP count
    of one track, which counts every loop body once (a lower bound: the generator's pairwise checks
    loop over ~50 blocks for a typical track)."""
    import envs
    from envs.track_feed import init_feed, refill_feed
    from envs.track_generator import generate_track
    from xrl_jax.tracks import cached_track_bank

    bank = cached_track_bank(1, 1)
    env, template = envs.make("tracking", track=jax.tree.map(lambda leaf: leaf[0], bank))
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    feeds = jax.jit(jax.vmap(lambda key: init_feed(env, template, key, 2 * count, 4)))(keys)
    feeds = feeds.replace(issued=feeds.generated, driving=jnp.full_like(feeds.driving, -1))  # all slots free
    refill = jax.jit(lambda feed: refill_feed(env, feed, count))
    start = time.perf_counter()
    jax.block_until_ready(refill(feeds))
    compile_s = time.perf_counter() - start
    seconds = timed(lambda: refill(feeds), repeats)
    step_us = _env_step_costs(env, template, init_feed, repeats)
    params = feeds.params
    bank_leaves = (params.tracks, params.tables, params.start_s, params.reset_obs)
    cost = jax.jit(generate_track).lower(jax.random.PRNGKey(0)).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return {
        "seeds": seeds,
        "tracks_per_refill": seeds * count,
        "ms_per_track": 1e3 * seconds / (seeds * count),
        "refill_s": seconds,
        "compile_s": compile_s,
        "xla_flops_per_track_loop_bodies_once": cost.get("flops"),
        "bytes_per_track_in_feed": sum(x.nbytes for x in jax.tree.leaves(bank_leaves)) // (seeds * 2 * count),
        "vector_step_us_4_envs": step_us,
    }


def _env_step_costs(env, template, init_feed, repeats: int, steps: int = 2000) -> dict:
    """Microseconds per step of 4 auto-resetting envs (a training seed's vector step) under random
    actions: on a fixed bank of 128 (the auto-reset wrapper) and on a fresh-track feed of 128, so the
    feed's per-step overhead is measured apart from the (much larger) agent update."""
    from envs.core import vmap_env
    from envs.racing import with_bank
    from envs.track_feed import reset_with_feed, step_with_feed
    from envs.track_generator import make_track_bank

    space = env.action_space(template)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, 4, *space.shape), minval=-1, maxval=1)
    bank_params = env.prepare(with_bank(template, make_track_bank(jax.random.PRNGKey(0), 128)))
    venv = vmap_env(env, 4)

    @jax.jit
    def on_bank(key):
        _, states = venv.reset(key, bank_params)

        def body(states, inputs):
            key, action = inputs
            return venv.step(key, states, action, bank_params)[1], None

        return jax.lax.scan(body, states, (jax.random.split(key, steps), actions))[0]

    @jax.jit
    def on_feed(key, states, feed):
        def body(carry, inputs):
            key, action = inputs
            states, feed = carry
            out = step_with_feed(env, key, states, action, feed)
            return (out[1], out[-1]), None

        return jax.lax.scan(body, (states, feed), (jax.random.split(key, steps), actions))[0]

    key = jax.random.PRNGKey(2)
    _, states, feed = reset_with_feed(env, jax.jit(lambda k: init_feed(env, template, k, 128, 4))(key))
    jax.block_until_ready((on_bank(key), on_feed(key, states, feed)))
    calls = {"bank": lambda: on_bank(key), "feed": lambda: on_feed(key, states, feed)}
    seconds = timed_alternately(calls, repeats)
    return {name: 1e6 * value / steps for name, value in seconds.items()}


def real_batch(observations: dict, batch_size: int, discrete: bool, key) -> dict:
    """A replay batch of ``batch_size`` observations and next observations drawn from real rollouts
    (``xrl_jax.occupancy``), so that its sets hold as many objects as training sees; random actions
    and rewards (they do not change the cost)."""
    total = next(iter(observations.values())).shape[0]
    k_obs, k_next, k_action, k_reward = jax.random.split(key, 4)

    def draw(k):
        rows = np.asarray(jax.random.randint(k, (batch_size,), 0, total))
        return {name: jnp.asarray(values[rows]) for name, values in observations.items()}

    return {
        "obs": draw(k_obs),
        "next_obs": draw(k_next),
        "action": (
            jax.random.randint(k_action, (batch_size,), 0, 12)
            if discrete
            else jax.random.uniform(k_action, (batch_size, 3), minval=-1)
        ),
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
    import envs
    from xrl_jax.agents import make_agent
    from xrl_jax.config import preset, preset_train_fields
    from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation
    from xrl_jax.sets import MEMBERS_AXIS

    config = preset(preset_name, env, algo)
    if width is not None:
        config = config.replace(actor_width=width, critic_width=width)
    if batch_size is None:
        batch_size = int(preset_train_fields(preset_name, env).get("batch_size", 256))
    discrete = algo in ("dsac", "xdsac")
    example = dummy_observation(ENV_OBSERVATIONS[env])
    variants = {"packed": config} if config.packed_rows is not None else {}
    variants["dense" if variants else "update"] = config.replace(dense_sets=True)
    size = envs.action_size(envs.action_space(f"{env}_discrete" if discrete else env))
    agents = {name: make_agent(c, example, size) for name, c in variants.items()}
    key = jax.random.PRNGKey(0)
    any_agent = next(iter(agents.values()))
    states = jax.jit(jax.vmap(any_agent.init))(jax.random.split(key, seeds))  # same parameters for all
    batches = _stacked_batches(observations, batch_size, discrete, updates)

    calls, out = {}, {"env": env, "algo": algo, "width": config.actor_width, "seeds": seeds,
                      "batch_size": batch_size, "packed_rows": config.packed_rows}  # fmt: skip
    for name, agent in agents.items():
        update_all = jax.vmap(agent.update, in_axes=(0, 0, None), axis_name=MEMBERS_AXIS)

        def run(states, key, update_all=update_all):
            def body(states, inputs):
                key, batch = inputs
                return update_all(jax.random.split(key, seeds), states, batch)[0], None

            return jax.lax.scan(body, states, (jax.random.split(key, updates), batches))[0]

        start = time.perf_counter()
        compiled = jax.jit(run).lower(states, key).compile()
        compile_s = time.perf_counter() - start
        one = jax.tree.map(lambda x: x[0], batches)
        flops = update_flops(agent if name != "packed" else _packed_only(agent), states, one, seeds)
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


def _stacked_batches(observations: dict, batch_size: int, discrete: bool, count: int) -> dict:
    keys = jax.random.split(jax.random.PRNGKey(1), count)
    batches = [real_batch(observations, batch_size, discrete, k) for k in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *batches)


def _packed_only(agent):
    """The same agent with its packed computation compiled alone (no dense fallback), to count the
    FLOPs that run: XLA's cost analysis counts the larger branch of a conditional."""
    from xrl_jax.agents import make_agent

    return make_agent(agent.config, agent.dummy_observation(), agent.action_size, packing_fallback=False)


def update_flops(agent, states, batch: dict, seeds: int) -> float:
    """XLA's FLOPs of one update per member (cost analysis of the compiled, vmapped update)."""
    from xrl_jax.sets import MEMBERS_AXIS

    update_all = jax.vmap(agent.update, in_axes=(0, 0, None), axis_name=MEMBERS_AXIS)
    one = jax.jit(lambda s, k: update_all(jax.random.split(k, seeds), s, batch)[0])
    analysis = one.lower(states, jax.random.PRNGKey(0)).compile().cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return float(analysis.get("flops", float("nan"))) / seeds


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bench.py", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    env_parser = sub.add_parser("env", help="environment steps per second (random actions, auto-reset)")
    env_parser.add_argument("--scenarios", nargs="+", default=["tracking", "country_road"])
    env_parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024, 4096, 8192])
    env_parser.add_argument("--steps", type=int, default=100, help="steps per timed call")
    env_parser.add_argument("--repeats", type=int, default=3)
    ix_parser = sub.add_parser(
        "intersection", help="intersection env-steps/s and agent-steps/s (random actions, 8 slots)"
    )
    ix_parser.add_argument("--vehicles", nargs="+", type=int, default=[1, 2, 4, 8])
    ix_parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024, 4096])
    ix_parser.add_argument("--steps", type=int, default=100, help="steps per timed call")
    ix_parser.add_argument("--repeats", type=int, default=3)
    ix_parser.add_argument("--discrete", action="store_true", help="the Discrete(12) variant")
    mm_parser = sub.add_parser("matmul", help="float32 matmul GFLOP/s of the default device")
    mm_parser.add_argument("--size", type=int, default=2048)
    up_parser = sub.add_parser(
        "update", help="agent updates/s per seed on real batches, packed beside dense, FLOPs per update"
    )
    up_parser.add_argument("--env", default="tracking", choices=["tracking", "country_road", "intersection"])
    up_parser.add_argument("--preset", default="paper", choices=PRESETS, help="the agents' preset")
    up_parser.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    up_parser.add_argument(
        "--algos",
        nargs="+",
        default=["sac", "dsac", "xsac", "xdsac"],
        choices=["sac", "dsac", "xsac", "xdsac"],
    )
    up_parser.add_argument("--widths", nargs="+", type=int, default=[64, 128, 256])
    up_parser.add_argument("--seeds", nargs="+", type=int, default=[1, 5, 20])
    up_parser.add_argument("--repeats", type=int, default=5)
    tr_parser = sub.add_parser(
        "train", help="end-to-end training env-steps/s (updates included), compile, memory"
    )
    tr_parser.add_argument("--env", default="tracking", choices=["tracking", "country_road", "intersection"])
    tr_parser.add_argument(
        "--algos", nargs="+", default=["xsac", "xdsac"], choices=["sac", "dsac", "xsac", "xdsac"]
    )
    tr_parser.add_argument("--seeds", nargs="+", type=int, default=[1, 5, 20])
    tr_parser.add_argument(
        "--widths", nargs="+", type=int, default=[256, 64], help="actor/critic widths (paper: 256)"
    )
    tr_parser.add_argument("--chunks", type=int, default=2, help="timed chunks after the first")
    tr_parser.add_argument(
        "--devices", nargs="+", type=int, default=[1], help="device counts to spread the seeds over"
    )
    tr_parser.add_argument("--preset", default="paper", choices=PRESETS)
    tr_parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="extra config overrides")
    tk_parser = sub.add_parser("tracks", help="fresh-track refill cost per track, FLOPs per track")
    tk_parser.add_argument("--seeds", nargs="+", type=int, default=[1, 4, 20])
    tk_parser.add_argument("--count", type=int, default=64, help="tracks per seed and refill (half a feed)")
    tk_parser.add_argument("--repeats", type=int, default=3)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "train" and max(args.devices) > 1:
        # A CPU host becomes that many XLA devices (read when the backend starts, i.e. below).
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_force_host_platform_device_count" not in flags:
            count = max(args.devices)
            os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()

    report: dict = {"machine": machine_info(), "command": args.command}
    if args.command == "env":
        if min(args.batches) < 1 or args.steps < 1 or args.repeats < 1:
            parser.error("--batches, --steps and --repeats must be positive")
        report["results"] = [
            bench_env(scenario, batch, args.steps, args.repeats)
            for scenario in args.scenarios
            for batch in args.batches
        ]
    elif args.command == "intersection":
        if min(args.batches) < 1 or args.steps < 1 or args.repeats < 1:
            parser.error("--batches, --steps and --repeats must be positive")
        if not all(1 <= n <= 8 for n in args.vehicles):
            parser.error("--vehicles must lie in 1..8")
        report["results"] = [
            bench_intersection(n, batch, args.steps, args.repeats, args.discrete)
            for n in args.vehicles
            for batch in args.batches
        ]
    elif args.command == "train":
        if min(args.seeds) < 1 or min(args.widths) < 1 or args.chunks < 1 or min(args.devices) < 1:
            parser.error("--seeds, --widths, --chunks and --devices must be positive")
        if max(args.devices) > len(jax.devices()):
            parser.error(f"--devices {max(args.devices)}: only {len(jax.devices())} device(s) here")
        if any(seeds % n for seeds in args.seeds for n in args.devices):
            parser.error("every --seeds value must be a multiple of every --devices value")
        report["results"] = [
            bench_train(args.env, algo, seeds, width, args.chunks, args.preset, args.set, devices)
            for algo in args.algos
            for width in args.widths
            for seeds in args.seeds
            for devices in args.devices
        ]
    elif args.command == "update":
        if min(args.widths) < 1 or min(args.seeds) < 1 or args.repeats < 1:
            parser.error("--widths, --seeds and --repeats must be positive")
        if args.batch_size is not None and args.batch_size < 1:
            parser.error("--batch-size must be positive")
        from xrl_jax.occupancy import rollout_observations

        observations = rollout_observations(args.env)["observations"]
        report["results"] = []
        for width in args.widths:
            for seeds in args.seeds:
                for algo in args.algos:
                    updates = max(2, 40 * 64 // (width * seeds))  # keep each timed call ~1 s or more
                    report["results"].append(
                        bench_update(
                            args.env, algo, width, seeds, updates, args.repeats, observations,
                            args.preset, args.batch_size,
                        )
                    )  # fmt: skip
    elif args.command == "tracks":
        if min(args.seeds) < 1 or args.count < 1 or args.repeats < 1:
            parser.error("--seeds, --count and --repeats must be positive")
        report["results"] = [bench_tracks(seeds, args.count, args.repeats) for seeds in args.seeds]
    elif args.command == "matmul":
        report["results"] = bench_matmul(args.size)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
