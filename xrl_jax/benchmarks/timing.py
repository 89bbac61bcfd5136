"""Timing on a shared machine: best-of-N wall times after compilation, variants timed in turn, the
float32 matmul ceiling that compute-bound work is compared to, XLA's FLOP count (of any function, and
of one update), peak memory."""

from __future__ import annotations

import os
import platform
import resource
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp

from xrl_jax.sets import MEMBERS_AXIS


def machine_info() -> dict:
    """What a benchmark ran on, printed beside its numbers."""
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


def seconds_of(fn: Callable[[], object]) -> tuple[object, float]:
    """``fn()``'s result and the wall time of this one call (blocked on; a first call includes its
    compilation)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


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


def compiled_flops(fn: Callable, *args, compiled: bool = True) -> float:
    """XLA's FLOP count of ``jax.jit(fn)(*args)`` (``args`` may be shapes) after compilation, or with
    ``compiled`` False of the lowered program, before XLA's simplifications (no compilation, but more
    FLOPs: the lowered update of Country Road's XDSAC counts about 3x what runs). XLA counts every
    loop body once and a conditional as its larger branch."""
    lowered = jax.jit(fn).lower(*args)
    analysis = (lowered.compile() if compiled else lowered).cost_analysis()
    if isinstance(analysis, list):  # older JAX returns one dict per device
        analysis = analysis[0]
    return float(analysis.get("flops", float("nan")))


def update_flops(agent, batch_size: int, members: int = 1, compiled: bool = False) -> float:
    """XLA's FLOPs of one gradient step of ``agent`` per member on a batch of ``batch_size``, the update
    vmapped over ``members`` agent states on the named members axis (as the trainer runs it: members
    share their packed-or-dense branches), the batch shared. Shapes only: nothing runs. ``compiled``:
    count what runs (costs a compilation; the benchmarks, which compile anyway); otherwise the lowered
    program (:func:`compiled_flops`; the campaign's estimates, for many runs at once)."""
    obs = agent.dummy_observation((batch_size,))
    flags = jnp.zeros(batch_size, bool)
    batch = {
        "obs": obs,
        "action": agent.random_action(jax.random.PRNGKey(0), (batch_size,)),
        "reward": jnp.zeros(batch_size),
        "next_obs": obs,
        "terminated": flags,
        "truncated": flags,
    }
    states = jax.eval_shape(jax.vmap(agent.init), jax.random.split(jax.random.PRNGKey(0), members))
    update_all = jax.vmap(agent.update, in_axes=(0, 0, None), axis_name=MEMBERS_AXIS)

    def one_update(states, key):
        return update_all(jax.random.split(key, members), states, batch)[0]

    return compiled_flops(one_update, states, jax.random.PRNGKey(0), compiled=compiled) / members


def peak_memory_bytes() -> dict:
    """Peak device memory (accelerators) and the process's peak resident memory (always)."""
    out = {"host_peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # backends without memory statistics raise different errors
        stats = {}
    if "peak_bytes_in_use" in stats:
        out["device_peak_bytes"] = int(stats["peak_bytes_in_use"])
    return out
