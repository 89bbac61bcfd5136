"""Calibrations: how fast a configuration trains on this machine, measured once
(:mod:`xrl_jax.benchmarks.calibration` measures) and kept in ``XRL_JAX_CACHE_DIR/calibrations``, so
that a run's cost can be told before anything of it runs (``paper.py --dry-run``, and a run's first
estimate before its first chunk).

A calibration holds the seconds of one vector step of the configuration's compiled chunk, warm-up
and updating, with the members per device and the devices a run of it has, and of one evaluation.
It is keyed by the machine (:func:`machine_fingerprint`: CPU model, usable cores, backend and device,
JAX and the compile settings, the code) and by what shapes the compiled chunk
(:func:`chunk_fields`), never by host-only settings, the seeds, the step counts or the traced
hyper-parameters, which change what a run computes but not how long a step of it takes. Each
calibration is one JSON file, written atomically; a file that cannot be read, or that holds another
key, is skipped with a one-line warning.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from xrl_jax.config import TrainConfig
from xrl_jax.config.names import TRACED_FIELDS
from xrl_jax.config.user_envs import user_env_record
from xrl_jax.resources import cpu_model
from xrl_jax.runs.folder import write_atomic
from xrl_jax.tracks import cache_dir
from xrl_jax.train.cpu_devices import (
    HOST_DEVICE_FLAG,
    PATIENT_COLLECTIVES,
    auto_cpu_devices,
    cpu_cores,
    flagged_host_devices,
)

FORMAT = 1  # of a calibration file; another one is a foreign file
# TrainConfig fields that change what a run computes or for how long, not what one vector step costs:
# the seeds and steps, where the run starts and ends (the warm-up and the run's length count the
# steps, which the estimate multiplies), the buffer's capacity (sampling costs the same), how often
# the host evaluates and checkpoints, the track seeds, the sweep (its values are traced; its members
# count through ``members_per_device``) and the primacy-bias resets (rare).
RUN_LENGTH_FIELDS = (
    "preset", "num_seeds", "seed", "total_steps", "warmup_steps", "buffer_size", "log_interval",
    "eval_interval", "checkpoint_interval", "track_seed", "eval_track_seed", "reinit_steps", "sweep",
)  # fmt: skip


def cache_folder() -> Path:
    return cache_dir() / "calibrations"


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """A hash of the sources of ``xrl_jax`` and ``envs``: any change of code may change a step's cost."""
    import envs

    digest = hashlib.sha256()
    for package in (Path(__file__).resolve().parents[1], Path(envs.__file__).resolve().parent):
        for path in sorted(package.rglob("*.py")):
            digest.update(str(path.relative_to(package.parent)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def compile_settings() -> dict[str, Any]:
    """The settings XLA compiles with (they change the speed: the tests compile unoptimised), without
    the host split and the collectives' patience, which the devices of a key already say."""
    flags = [
        flag
        for flag in os.environ.get("XLA_FLAGS", "").split()
        if not any(f"--{name}=" in flag for name in (HOST_DEVICE_FLAG, *PATIENT_COLLECTIVES))
    ]
    return {
        "xla_flags": sorted(flags),
        "disable_most_optimizations": bool(jax.config.read("jax_disable_most_optimizations")),
    }


def machine_fingerprint() -> dict[str, Any]:
    """What a calibration holds for: this machine, its software and the code."""
    device = jax.local_devices()[0]
    return {
        "cpu": cpu_model(),
        "cores": cpu_cores(),
        "backend": jax.default_backend(),
        "device_kind": getattr(device, "device_kind", str(device)),
        "jax": jax.__version__,
        "code": code_digest(),
        **compile_settings(),
    }


def chunk_fields(cfg: TrainConfig) -> dict[str, Any]:
    """The settings that shape a vector step of ``cfg``'s compiled chunk (its cost): the host-only
    ones, :data:`RUN_LENGTH_FIELDS` and the traced hyper-parameters left out; a learning-rate decay
    only as whether it is on (its length follows the run's)."""
    fields = cfg.without_host_settings().to_dict()
    for name in RUN_LENGTH_FIELDS:
        fields.pop(name)
    agent = fields.pop("agent")
    for name in TRACED_FIELDS:
        agent.pop(name)
    agent["lr_decay_updates"] = bool(agent["lr_decay_updates"])
    record = user_env_record(cfg.env)
    return {**fields, "agent": agent, "user_env": record}


def calibration_key(cfg: TrainConfig, members_per_device: int, devices: int) -> dict[str, Any]:
    """Everything a calibration of ``cfg`` holds for: the machine, the chunk, and the members per
    device on how many devices."""
    return {
        "format": FORMAT,
        "machine": machine_fingerprint(),
        "chunk": chunk_fields(cfg),
        "members_per_device": int(members_per_device),
        "devices": int(devices),
    }


def key_path(key: dict[str, Any]) -> Path:
    text = json.dumps(key, sort_keys=True)
    return cache_folder() / f"{hashlib.sha256(text.encode()).hexdigest()[:24]}.json"


def store_calibration(key: dict[str, Any], record: dict[str, Any]) -> Path:
    """Write ``record`` under ``key`` (atomically: readers, and another process writing the same
    calibration, see one whole file)."""
    path = key_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps({"key": key, "record": record}, indent=2, sort_keys=True) + "\n")
    return path


def _warn_stderr(message: str) -> None:
    import sys

    print(message, file=sys.stderr)


def load_calibration(key: dict[str, Any], warn: Callable[[str], None] = _warn_stderr) -> dict | None:
    """The record stored under ``key``, or None: none stored, or a file that is not a calibration of
    this key (damaged, another format, another key), which ``warn`` hears about in one line."""
    path = key_path(key)
    try:
        document = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        warn(f"warning: ignoring the calibration file {path}: unreadable ({type(err).__name__})")
        return None
    if not isinstance(document, dict) or document.get("key") != key:
        warn(f"warning: ignoring the calibration file {path}: it holds another calibration")
        return None
    record = document.get("record")
    if not isinstance(record, dict) or not all(isinstance(record.get(n), (int, float)) for n in RECORD_RATES):
        warn(f"warning: ignoring the calibration file {path}: it lacks the measured rates")
        return None
    return record


def cached_calibrations(machine: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Every readable calibration of this machine in the cache (for how long calibrating takes)."""
    machine = machine_fingerprint() if machine is None else machine
    found = []
    for path in sorted(cache_folder().glob("*.json")):
        try:
            document = json.loads(path.read_text())
            if document["key"]["machine"] == machine:
                found.append(document["record"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return found


# What an estimate reads of a record (the rest says how it was measured).
RECORD_RATES = ("warmup_vector_step_s", "vector_step_s", "eval_s", "setup_s")


def run_devices(cfg: TrainConfig, new_run: bool) -> int:
    """The devices a run of ``cfg`` spreads over, as ``run.py`` would start it on this machine (its
    ``num_devices``; on a CPU host a new run's split by the member rule, a started one's as the
    user's XLA_FLAGS split it, else one), but no more than this process has."""
    available = len(jax.local_devices())
    if cfg.num_devices:
        wanted = cfg.num_devices
    elif jax.default_backend() != "cpu":
        wanted = available
    else:
        flagged = flagged_host_devices()
        rule = auto_cpu_devices(cfg, cpu_cores()) if new_run else 1
        wanted = flagged or rule
    return min(wanted, available)


def members_per_device(groups: list[list[int]], devices: int) -> int:
    """Members one device trains at once: the largest group (the first; groups are balanced) spread
    over the devices, padded as the trainer pads it."""
    return -(-len(groups[0]) // max(devices, 1))


def predicted_seconds(cfg: TrainConfig, record: dict[str, Any], groups_done: list[int]) -> dict[str, float]:
    """The seconds a run of ``cfg`` takes by ``record``, its member groups one after another, group
    ``g`` having done ``groups_done[g]`` steps per member: warm-up and updating vector steps, the
    evaluations after the steps done, and (once, when anything is left) the chunk's compilation and
    the evaluation's. Checkpoints are not counted."""
    steps = {"warmup": 0.0, "updating": 0.0}
    evaluations = 0
    for done in groups_done:
        if done >= cfg.total_steps:
            continue
        steps["warmup"] += max(min(cfg.warmup_steps, cfg.total_steps) - done, 0) / cfg.num_envs
        steps["updating"] += max(cfg.total_steps - max(done, cfg.warmup_steps), 0) / cfg.num_envs
        chunks = range(done // cfg.log_interval, cfg.num_chunks)
        evaluations += sum(cfg.evaluates_at(cfg.chunk_end_step(c)) for c in chunks)
    left = any(done < cfg.total_steps for done in groups_done)
    out = {
        "training_s": steps["warmup"] * record["warmup_vector_step_s"]
        + steps["updating"] * record["vector_step_s"],
        "evaluation_s": evaluations * record["eval_s"],
        "setup_s": record["setup_s"] if left else 0.0,
    }
    out["total_s"] = sum(out.values())
    return out


def calibrated_remaining_s(
    cfg: TrainConfig, groups: list[list[int]], devices: int, group_index: int, next_chunk: int, warn
) -> tuple[float, dict[str, Any]] | None:
    """The seconds left of a run from chunk ``next_chunk`` of member group ``group_index`` on (the
    groups before it done, those after it not begun), by the cached calibration of its configuration
    on this machine, and that calibration; None without one (a run never calibrates itself)."""
    key = calibration_key(cfg, members_per_device(groups, devices), devices)
    record = load_calibration(key, warn=warn)
    if record is None:
        return None
    done = cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
    groups_done = [cfg.total_steps] * group_index + [done] + [0] * (len(groups) - group_index - 1)
    return predicted_seconds(cfg, record, groups_done)["total_s"], record
