"""Calibrating a configuration on this machine: the seconds of one vector step of its real compiled
chunk, warm-up and updating, for the members per device and the devices a run of it has, and of one
evaluation. ``paper.py --dry-run`` counts its CPU hours with them, and a run whose calibration is
cached tells its cost before its first chunk (:mod:`xrl_jax.train.calibrations` keeps them).

The trainer is built for a short copy of the configuration (:func:`calibration_config`): chunks of
:data:`VECTOR_STEPS` vector steps, a buffer that holds the calibration, a warm-up of
:data:`WARMUP_TRANSITIONS` (batches drawn from many episodes, as in a long run), a run long enough
never to end inside the measurement. The warm-up chunks after the first give a
vector step's cost without updates (acting and the envs); the updating chunks after the first
(which carries first-time costs) give it with them, and so the cost of one update. A run's updating
vector step is the first plus its updates per vector step at that cost: one per transition on the
racing scenarios, as the calibration makes them; on the Intersection one per acting vehicle, as
many as measured under the training curriculum (``set_occupancy.json``), not as many as the few
episodes of a calibration happen to hold.

A process splits a CPU host into devices only before JAX's backend starts (:mod:`~xrl_jax.train.
cpu_devices`): :func:`calibrate_in_child` measures in a fresh process split as the run would be; a
calibration in a process whose backend already runs uses the devices it has, and its record says so.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from xrl_jax.config import ConfigError, TrainConfig
from xrl_jax.train import calibrations, cpu_devices

VECTOR_STEPS = 8  # per calibration chunk: a paper-preset step of 20 members takes seconds
# Transitions per member of the warm-up: enough episodes that a batch is drawn as in a long run's
# buffer. Country Road's packed per-object layers fall back to every slot when a batch holds more
# cones than they reserve; with a batch's worth of warm-up (4 tracks) 68 % of the updates of 4 members
# did, with ~19 random-action episodes of its ~430 steps 0.08 % (docs/performance.md, "Estimates
# that hold"). Warm-up steps are cheap: acting and the envs.
WARMUP_TRANSITIONS = 8192
# Updating chunks are timed until their median can be trusted: MIN_TIMED_S measured over 3 chunks at
# least (or LONG_TIMED_S over fewer, when a chunk takes that long) ...
MIN_TIMED_S, LONG_TIMED_S = 3.0, 30.0
MAX_UPDATING_CHUNKS = 40  # ... or until this many chunks have run (the first untimed)


class CalibrationError(RuntimeError):
    """A calibration that could not measure (one line: what failed)."""


def warmup_chunks(cfg: TrainConfig) -> int:
    """Warm-up chunks of the calibration: :data:`WARMUP_TRANSITIONS` per member (and a batch at
    least), in two chunks at least (the first carries first-time costs)."""
    return max(2, -(-max(cfg.batch_size, WARMUP_TRANSITIONS) // (VECTOR_STEPS * cfg.num_envs)))


def calibration_config(cfg: TrainConfig, members_per_device: int, devices: int) -> TrainConfig:
    """``cfg`` shortened for a calibration of ``members_per_device`` members on each of ``devices``
    devices, in one group; everything that shapes a vector step kept."""
    interval = VECTOR_STEPS * cfg.num_envs
    chunks = warmup_chunks(cfg) + MAX_UPDATING_CHUNKS
    total = interval * (chunks + 1)  # one chunk more: the Intersection settles its owed updates at the end
    rows = total * cfg.scenario.agent_slots
    return cfg.replace(
        num_seeds=members_per_device * devices, sweep=(), total_steps=total,
        warmup_steps=warmup_chunks(cfg) * interval, log_interval=interval, eval_interval=interval,
        checkpoint_interval=interval, buffer_size=max(cfg.batch_size, min(cfg.buffer_size, rows)),
        max_group_size=0, num_devices=devices,
    )  # fmt: skip


def calibrate(cfg: TrainConfig, members_per_device: int, devices: int) -> dict[str, Any]:
    """Measure ``cfg`` with ``members_per_device`` members on each of ``devices`` devices (fewer where
    this process has fewer; the record's ``note`` says so) on this machine; returns the record
    (:data:`~xrl_jax.train.calibrations.RECORD_RATES` and how they were measured)."""
    from xrl_jax.benchmarks.occupancy import load_occupancy
    from xrl_jax.train import make_trainer, scenario_kind
    from xrl_jax.train.chunk import mesh_devices

    began, load = time.perf_counter(), os.getloadavg()[0]
    available = len(jax.local_devices())
    used = min(devices, available)
    short = calibration_config(cfg, members_per_device, used)
    trainer = make_trainer(short, devices=mesh_devices(used))
    tic = time.perf_counter()
    state = jax.block_until_ready(trainer.init(0, range(members_per_device * used)))
    chunk = trainer.chunk.lower(state, np.int32(0)).compile()
    evaluate = trainer.evaluate.lower(state).compile()
    setup_s = time.perf_counter() - tic
    steps = short.chunk_vector_steps

    def run(index: int) -> tuple[float, float]:  # the chunk's seconds, and the updates per member after it
        nonlocal state
        tic = time.perf_counter()
        state, report = chunk(state, np.int32(index * steps))
        updates = float(np.mean(np.asarray(report.metrics["train/updates"])))
        return time.perf_counter() - tic, updates

    warm = [run(c)[0] for c in range(warmup_chunks(cfg))][1:]
    index = warmup_chunks(cfg)
    _, updates_before = run(index)  # the first updating chunk: first-time costs
    timed, updates, others = [], updates_before, OtherLoad()
    while index + 1 < warmup_chunks(cfg) + MAX_UPDATING_CHUNKS and not _enough(timed):
        index += 1
        seconds, updates = run(index)
        timed.append(seconds)
    others_share = others.share()
    (_, episodes), eval_s = _seconds(lambda: evaluate(state))
    longest, limit = _longest_episode(episodes), _episode_limit(trainer, cfg)
    warmup_step_s = float(np.median(warm)) / steps
    updating_step_s = float(np.median(timed)) / steps
    updates_per_step = (updates - updates_before) / (len(timed) * steps)
    if updates_per_step <= 0:
        raise CalibrationError(f"{cfg.env} {cfg.algo}: the calibration's chunks made no update")
    update_s = max(updating_step_s - warmup_step_s, 0.0) / updates_per_step
    per_env_step = scenario_kind(cfg).updates_per_env_step(cfg, load_occupancy())
    run_updates = per_env_step * cfg.num_envs
    note = "" if used == devices else (
        f"measured on {used} of the {devices} devices asked for: this process had {available} "
        "(a process splits its CPU host before its backend starts)"
    )  # fmt: skip
    return {
        "warmup_vector_step_s": warmup_step_s,
        "vector_step_s": warmup_step_s + update_s * run_updates,
        # A racing evaluation runs until its longest episode ends: a new agent's soon, a trained
        # one's at the time limit (a third of the quick Country Road XDSAC's episodes got there).
        "eval_s": eval_s * (limit / longest if longest and limit and longest < limit else 1.0),
        "setup_s": setup_s,
        "update_s": update_s,
        "updates_per_vector_step": run_updates,
        "measured": {
            "updating_vector_step_s": updating_step_s,
            "updates_per_vector_step": updates_per_step,
            "vector_steps_timed": len(timed) * steps,
            "warmup_vector_steps_timed": len(warm) * steps,
            "eval_episodes": cfg.eval_episodes,
            "eval_s": eval_s,
            "eval_longest_episode": longest,
        },
        "members_per_device": members_per_device,
        "devices": used,
        "devices_in_process": available,
        "note": note,
        "calibration_s": time.perf_counter() - began,
        "load_average": [load, os.getloadavg()[0]],  # before and after: a busy machine measures slow
        "others_cpu_share": others_share,  # of the machine's CPU time, by other processes while timed
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _longest_episode(episodes) -> int | None:
    """The steps the evaluation ran, where its episodes end early (a ``length`` per episode)."""
    if not isinstance(episodes, dict) or "length" not in episodes:
        return None  # the Intersection's episodes run their fixed length
    return int(np.max(np.asarray(episodes["length"])))


def _episode_limit(trainer, cfg: TrainConfig) -> int | None:
    """The steps an evaluation episode runs at most (the racing envs' time limit, a user's env's)."""
    from xrl_jax.config.user_envs import user_env_record

    limit = getattr(trainer.eval_params, "max_steps", None)
    if limit is None:
        limit = (user_env_record(cfg.env) or {}).get("max_episode_steps")
    return int(limit) if limit else None


def _enough(timed: list[float]) -> bool:
    return sum(timed) >= MIN_TIMED_S and (len(timed) >= 3 or sum(timed) >= LONG_TIMED_S)


class OtherLoad:
    """The share of the machine's CPU time that other processes take from now on (Linux's
    ``/proc/stat`` less this process's own time): a calibration beside other work measures slow."""

    def __init__(self):
        self.start = self._sample()

    @staticmethod
    def _sample() -> tuple[float, float, float] | None:
        try:
            fields = [float(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        except (OSError, ValueError):
            return None
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle and waiting for I/O
        own = os.times()
        return sum(fields) - idle, sum(fields), (own.user + own.system) * os.sysconf("SC_CLK_TCK")

    def share(self) -> float | None:
        end = self._sample()
        if self.start is None or end is None or end[1] <= self.start[1]:
            return None
        busy, total, own = (b - a for a, b in zip(self.start, end, strict=True))
        return min(max((busy - own) / total, 0.0), 1.0)


def _seconds(fn):
    tic = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - tic


def calibrate_and_store(cfg: TrainConfig, members_per_device: int, devices: int) -> dict[str, Any]:
    """:func:`calibrate`, kept in the cache under the key of what was asked for."""
    record = calibrate(cfg, members_per_device, devices)
    calibrations.store_calibration(calibrations.calibration_key(cfg, members_per_device, devices), record)
    return record


def calibrate_in_child(cfg: TrainConfig, members_per_device: int, devices: int) -> dict[str, Any]:
    """:func:`calibrate` in a fresh Python process whose CPU host is split into ``devices`` devices,
    as a run's would be (a process that has started its backend cannot split it again); returns
    the record, storing nothing. Built-in scenarios only (a user's env is registered in its own
    process). Raises :class:`CalibrationError` with the child's last line when it fails."""
    root = str(Path(__file__).resolve().parents[2])  # the xrl_jax and envs this process imported
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    command = [
        sys.executable, "-m", "xrl_jax.benchmarks.calibration", "--config", json.dumps(cfg.to_dict()),
        "--members-per-device", str(members_per_device), "--devices", str(devices),
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=root)
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines() or [f"exit status {done.returncode}"]
        raise CalibrationError(lines[-1])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    """The child of :func:`calibrate_in_child`: split the host, calibrate, print the record (one line)."""
    parser = argparse.ArgumentParser(prog="python -m xrl_jax.benchmarks.calibration")
    parser.add_argument("--config", required=True, help="a TrainConfig as JSON (TrainConfig.to_dict)")
    parser.add_argument("--members-per-device", type=int, required=True)
    parser.add_argument("--devices", type=int, required=True)
    args = parser.parse_args(argv)
    cpu_devices.split_cpu_host(args.devices)
    try:
        cfg = TrainConfig.from_dict(json.loads(args.config))
        record = calibrate(cfg, args.members_per_device, args.devices)
    except (CalibrationError, ConfigError) as err:
        print(err, file=sys.stderr)
        return 1
    print(json.dumps(record, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
