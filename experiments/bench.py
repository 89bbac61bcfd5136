"""Throughput benchmarks; every sub-command prints one JSON document to stdout.

    python experiments/bench.py env      [--scenarios tracking country_road] [--batches 1 64 1024 4096 8192]
    python experiments/bench.py matmul   [--size 2048]

Numbers are wall-clock rates after compilation (compile time is reported separately), measured with
``block_until_ready`` on the default JAX device. Tests never assert timings; these scripts do.
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


def bench_matmul(size: int = 2048, repeats: int = 5) -> dict:
    """Float32 matmul throughput of this device: the ceiling that compute-bound updates are compared to."""
    a = jax.random.normal(jax.random.PRNGKey(0), (size, size), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (size, size), jnp.float32)
    matmul = jax.jit(jnp.matmul)
    jax.block_until_ready(matmul(a, b))
    seconds = timed(lambda: matmul(a, b), repeats)
    return {"size": size, "seconds": seconds, "gflops": 2 * size**3 / seconds / 1e9}


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
    start = time.perf_counter()
    _, state = jax.block_until_ready(reset(key))
    reset_compile = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(rollout(key, state))
    rollout_compile = time.perf_counter() - start
    reset_seconds = timed(lambda: reset(key), repeats)
    rollout_seconds = timed(lambda: rollout(key, state), repeats)
    return {
        "scenario": scenario,
        "batch": batch,
        "steps_per_call": steps,
        "env_steps_per_s": batch * steps / rollout_seconds,
        "reset_us_per_env": 1e6 * reset_seconds / batch,
        "compile_s": {"reset": reset_compile, "rollout": rollout_compile},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench.py", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    env_parser = sub.add_parser("env", help="environment steps per second (random actions, auto-reset)")
    env_parser.add_argument("--scenarios", nargs="+", default=["tracking", "country_road"])
    env_parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024, 4096, 8192])
    env_parser.add_argument("--steps", type=int, default=100, help="steps per timed call")
    env_parser.add_argument("--repeats", type=int, default=3)
    mm_parser = sub.add_parser("matmul", help="float32 matmul GFLOP/s of the default device")
    mm_parser.add_argument("--size", type=int, default=2048)
    args = parser.parse_args(argv)

    report: dict = {"machine": machine_info(), "command": args.command}
    if args.command == "env":
        if min(args.batches) < 1 or args.steps < 1 or args.repeats < 1:
            parser.error("--batches, --steps and --repeats must be positive")
        report["results"] = [
            bench_env(scenario, batch, args.steps, args.repeats)
            for scenario in args.scenarios
            for batch in args.batches
        ]
    elif args.command == "matmul":
        report["results"] = bench_matmul(args.size)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
