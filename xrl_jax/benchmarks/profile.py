"""Where a training step's time goes: one compiled chunk traced with ``jax.profiler``, its ops' time
summed by the model part that XLA's optimised HLO names in each instruction's metadata (the actor's
per-object trunk, a critic layer, the mixture's reductions, the env ...), forward and backward apart.

The trace's CPU events are named after the HLO instructions they execute (``dot.36``, ``fusion.12``);
the compiled chunk's HLO text maps each name to the ``op_name`` that JAX recorded while tracing, e.g.
``.../transpose(jvp(MixtureCategoricalActor))/MixtureCategoricalActor.per_object/trunk.branch/...``.
The part of a name is its module path with JAX's transformations (vmap, jvp, cond branches) dropped;
``transpose(`` marks the backward pass. docs/performance.md, "Where an update's time goes", reads one.
"""

from __future__ import annotations

import collections
import gzip
import json
import re
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

# Trace events that enclose or wait for others (their time is their children's) or belong to the
# host, not to an op of the program.
_ENCLOSING = ("ThunkExecutor", "$", "SlinkyThreadPool", "PjRt", "Pjit", "TfrtCpu", "ExecuteHelper")
_TRANSFORMS = re.compile(
    r"^(jvp|transpose|vmap|cond|branch_\d+_fun|while|body|closed_call|jit\(chunk_block\))"
)
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%?([\w.\-]+) = .*?op_name=\"([^\"]*)\"", re.M)


def instruction_sources(hlo_text: str) -> dict[str, str]:
    """Each optimised HLO instruction's ``op_name`` metadata (the first, for a name seen twice)."""
    sources: dict[str, str] = {}
    for match in _INSTRUCTION.finditer(hlo_text):
        sources.setdefault(match.group(1), match.group(2))
    return sources


def model_part(op_name: str, depth: int = 3) -> str:
    """The model part of an ``op_name``: its first ``depth`` path components that are not JAX
    transformations, prefixed with "backward: " inside a ``transpose(...)``; "(unnamed)" if none."""
    parts = [p for p in op_name.split("/") if p and not _TRANSFORMS.match(p)]
    name = "/".join(parts[:depth]) or "(unnamed)"
    return f"backward: {name}" if "transpose(" in op_name else name


def op_times(trace_events: list[dict]) -> dict[str, float]:
    """Microseconds per op name over complete ("X") events, enclosing events left out."""
    totals: collections.Counter = collections.Counter()
    for event in trace_events:
        if event.get("ph") == "X" and not event["name"].startswith(_ENCLOSING):
            totals[event["name"]] += float(event.get("dur", 0.0))
    return dict(totals)


def time_by_part(op_us: dict[str, float], sources: dict[str, str], depth: int = 3) -> list[dict]:
    """Op times summed by model part, largest first, with their share of all ops' time; ops the HLO
    does not name (runtime events) go to "(not in the program)"."""
    totals: collections.Counter = collections.Counter()
    for op, us in op_us.items():
        totals[model_part(sources[op], depth) if op in sources else "(not in the program)"] += us
    whole = sum(totals.values()) or 1.0
    return [{"part": part, "ms": us / 1e3, "share": us / whole} for part, us in totals.most_common()]


def _read_trace(folder: Path) -> list[dict]:
    files = sorted(folder.rglob("*.trace.json.gz"))
    if not files:
        raise RuntimeError(f"jax.profiler wrote no trace under {folder}")
    data = json.loads(gzip.decompress(files[-1].read_bytes()))
    return data["traceEvents"] if isinstance(data, dict) else data


def profile_chunk(trainer, state, start_vector_step: int, depth: int = 3) -> tuple[object, dict]:
    """Trace one chunk of ``trainer`` from ``state`` (compiled first, so the trace holds execution
    only); returns the new state (the old one is donated) and the time per model part."""
    start = np.int32(start_vector_step)
    compiled = trainer.chunk.lower(state, start).compile()  # the jitted chunk reuses this executable
    sources = instruction_sources(compiled.as_text())
    with tempfile.TemporaryDirectory() as folder:
        tic = time.perf_counter()
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            state, report = trainer.chunk(state, start)
            jax.block_until_ready(report)
        seconds = time.perf_counter() - tic
        op_us = op_times(_read_trace(Path(folder)))
    return state, {
        "chunk_s_traced": seconds,
        "ops_ms": sum(op_us.values()) / 1e3,
        "parts": time_by_part(op_us, sources, depth),
        "slowest_ops": [
            {"op": op, "ms": us / 1e3, "source": sources.get(op, "")}
            for op, us in sorted(op_us.items(), key=lambda item: -item[1])[:15]
        ],
    }


def bench_profile(env: str, algo: str, seeds: int, width: int | None, preset_name: str, overrides: list,
                  devices: int = 1, depth: int = 3) -> dict:  # fmt: skip
    """The time per model part of one updating chunk of ``env``/``algo`` at ``preset_name`` (the
    chunk after the first, which runs the warm-up), ``seeds`` members on ``devices`` devices."""
    from xrl_jax import train
    from xrl_jax.benchmarks.updates import short_run_config

    cfg = short_run_config(env, algo, preset_name, seeds, width, overrides, chunks=3, log_interval=1000)
    trainer = train.make_trainer(cfg, devices=jax.devices()[:devices])
    state = trainer.init(0, range(seeds))
    state, report = trainer.chunk(state, np.int32(0))
    jax.block_until_ready(report)
    _, profile = profile_chunk(trainer, state, cfg.chunk_vector_steps, depth)
    shape = {"env": env, "algo": algo, "seeds": seeds, "devices": devices, "width": cfg.agent.actor_width}
    return {**shape, "vector_steps": cfg.chunk_vector_steps, **profile}
