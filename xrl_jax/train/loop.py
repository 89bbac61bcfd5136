"""The host loop of a run (:func:`train`): seed groups one after another, chunk after chunk, and
between chunks the metric lines, the health check, evaluation, checkpoints, the progress bar, the
cost estimate and clean stops."""

from __future__ import annotations

import functools
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax.checkpoint import Checkpointer, CorruptCheckpointError
from xrl_jax.config import HOST_ONLY_FIELDS, ConfigError, TrainConfig
from xrl_jax.interrupts import RunInterrupted, StopController
from xrl_jax.resources import backend_summary, disk_free_bytes, format_bytes, format_duration
from xrl_jax.train.chunk import ChunkReport, RunState, Trainer, get_trainer, tree_all_finite
from xrl_jax.train.memory import plan_memory, tree_bytes
from xrl_jax.train.run_folder import (
    RunLock,
    append_lines,
    check_history,
    encode_metric,
    is_disk_full,
    remove_leftovers,
    run_paths,
    truncate_lines,
    write_atomic,
)


class DivergenceError(RuntimeError):
    """A seed produced a non-finite loss or parameter; the message (one line) names the seed, the
    step and the quantity, and what was kept."""


class DiskFullError(RuntimeError):
    """The disk filled up while the run wrote its results; the last committed checkpoint is intact."""


CHECKPOINT_TIME_SHARE = 0.02  # time-based checkpoints never take more than this share of the run
LONG_RUN_S = 86_400.0  # estimates above a day come with a warning and the faster alternatives


def config_fingerprint(cfg: TrainConfig) -> str:
    """A hash of every setting that shapes the run's results (not the host-only settings); stored
    with each checkpoint so that a resume never continues another configuration's state."""
    fields = cfg.to_dict()
    for host_only in HOST_ONLY_FIELDS:
        fields.pop(host_only)
    if not fields["sweep"]:  # a plain run hashes as before sweeps existed
        fields.pop("sweep")
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True, file=sys.stderr
    )


def _metric_lines(step: int, seeds: list[int], report: ChunkReport) -> list[tuple[int, dict]]:
    """One metrics line per seed: ``null`` where an average has no data yet, non-finite values as
    the strings "nan"/"inf"/"-inf" (see :func:`xrl_jax.train.run_folder.encode_metric`)."""
    lines = []
    for row, seed in enumerate(seeds):
        line = {"step": step, "seed": seed}
        for name, values in report.metrics.items():
            present = report.has_data.get(name)
            line[name] = encode_metric(values[row]) if present is None or present[row] else None
        lines.append((seed, line))
    return lines


def _first_nonfinite_leaf(tree) -> str:
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(path)
    return "(none found)"


def divergence_message(
    report: ChunkReport, seeds: list[int], chunk_end: int, loss_names: tuple[str, ...], agent_of_row
) -> str | None:
    """None when every seed of the chunk is healthy, else one line naming the first seed to go
    non-finite, the step and the quantity (``agent_of_row(row)`` gives that seed's agent state)."""
    health = report.health
    loss_step = np.asarray(health.first_nonfinite_step)
    bad_rows = [r for r in range(len(seeds)) if loss_step[r] >= 0 or not health.agent_finite[r]]
    if not bad_rows:
        return None
    first_step = {r: int(loss_step[r]) if loss_step[r] >= 0 else chunk_end for r in bad_rows}
    row = min(bad_rows, key=lambda r: (first_step[r], r))
    if loss_step[row] >= 0:
        name = loss_names[int(health.first_nonfinite_loss[row])]
        what = f"{name} became non-finite"
    else:
        what = f"the agent's {_first_nonfinite_leaf(agent_of_row(row))} became non-finite"
    others = len(bad_rows) - 1
    also = f" ({others} other seed{'s' if others > 1 else ''} too)" if others else ""
    return f"seed {seeds[row]} diverged at step {first_step[row]}{also}: {what}"


def _expected_rows(cfg: TrainConfig, next_chunk: int) -> tuple[list[int], list[int]]:
    """The metric and evaluation steps a seed's files must hold when ``next_chunk`` chunks are done."""
    ends = [cfg.chunk_end_step(c) for c in range(next_chunk)]
    evals = [s for s in ends if cfg.evaluates_at(s)]
    return ends, evals


class RunClock:
    """Wall-time bookkeeping of the host loop: time-based checkpoints and the run's cost estimate."""

    def __init__(self, cfg: TrainConfig, num_groups: int):
        self.cfg = cfg
        self.num_groups = num_groups
        self.last_save = time.monotonic()
        self.save_s: float | None = None  # the last checkpoint's duration
        self.eval_s: float | None = None  # the last evaluation's duration
        self.chunk_s: float | None = None  # a chunk's duration with an update per transition
        self.estimated = False

    def saved(self, seconds: float) -> None:
        self.save_s = seconds
        self.last_save = time.monotonic()

    def checkpoint_due_by_time(self) -> bool:
        minutes = self.cfg.checkpoint_minutes
        if not minutes:
            return False
        interval = max(60.0 * minutes, (self.save_s or 0.0) / CHECKPOINT_TIME_SHARE)
        return time.monotonic() - self.last_save >= interval

    def expected_chunk_s(self) -> float | None:
        """How long the next chunk and a checkpoint after it should take (None until measured)."""
        if self.chunk_s is None:
            return None
        return self.chunk_s + (self.save_s or 0.0)

    def observe_chunk(self, chunk_index: int, seconds: float) -> None:
        """Learn a chunk's cost from the first one in which at least half the transitions update
        (updates dominate; scaled up to a chunk that updates on every transition)."""
        if self.chunk_s is not None:
            return
        cfg = self.cfg
        first = chunk_index * cfg.log_interval
        last = cfg.chunk_end_step(chunk_index)
        updating = max(last - max(first, cfg.warmup_steps), 0)
        if updating * 2 >= last - first:
            self.chunk_s = seconds * (last - first) / updating

    def remaining_s(self, group_index: int, next_chunk: int) -> float | None:
        """Time left for the whole run (chunks, evaluations, step-interval checkpoints)."""
        if self.chunk_s is None:
            return None
        cfg = self.cfg

        def cost(first_chunk: int) -> float:  # chunks first_chunk.. of one group, with their events
            ends = [cfg.chunk_end_step(c) for c in range(first_chunk, cfg.num_chunks)]
            evals = sum(map(cfg.evaluates_at, ends))
            saves = sum(map(cfg.checkpoints_at, ends))
            return len(ends) * self.chunk_s + evals * (self.eval_s or 0.0) + saves * (self.save_s or 0.0)

        return cost(next_chunk) + (self.num_groups - group_index - 1) * cost(0)


def cost_lines(cfg: TrainConfig, elapsed_s: float, remaining_s: float, backend: str) -> list[str]:
    """The estimate of the whole run's time, with a warning and the alternatives beyond a day."""
    total = elapsed_s + remaining_s
    steps = cfg.num_seeds * cfg.total_steps
    finish = time.strftime("%a %H:%M", time.localtime(time.time() + remaining_s))
    lines = [
        f"estimate: the whole run ({cfg.num_seeds} seed(s) x {cfg.total_steps:,} steps) takes "
        f"~{format_duration(total)} on {backend} ({steps / max(total, 1e-9):,.0f} steps/s); "
        f"done around {finish}"
    ]
    if total > LONG_RUN_S:
        lines.append(
            f"warning: this run needs ~{format_duration(total)}; for a result today use --preset quick "
            "(two Tracking XDSAC seeds take ~14 min on a 2-core CPU), fewer --seeds or --steps, or a GPU "
            "(pip install -e '.[cuda]'). Stop with Ctrl-C; --resume continues from the last checkpoint."
        )
    return lines


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    resume: bool = False,
    progress: bool = True,
    log=print,
    trainer: Trainer | None = None,
    stop_after_chunks: int | None = None,
    stop: StopController | None = None,
    warn=None,
) -> dict[str, Any] | None:
    """Run (or continue) the whole experiment into ``out``; returns the summary.

    Writes (``config.json`` is the caller's, see :func:`xrl_jax.evaluate.config_document`):
    ``plan.json`` (memory plan and seed groups), per seed ``metrics/seed_<i>.jsonl`` (one line per
    chunk) and ``eval/seed_<i>.jsonl`` (one line per evaluation), per group ``checkpoints/group_<g>``
    (the newest two, verified on restore), ``timing.jsonl`` and at the end ``summary.json``. Lines
    written after the newest checkpoint are dropped on resume and recomputed, so a resumed run's
    files equal an uninterrupted run's.

    The folder is locked for the duration (:class:`~xrl_jax.train.run_folder.RunLock`). Checkpoints are
    written every ``checkpoint_interval`` steps and every ``checkpoint_minutes`` of wall time, never
    after a chunk in which a seed went non-finite: that raises :class:`DivergenceError` with the
    last good checkpoint kept. ``stop`` (installed by the CLI) turns SIGINT/SIGTERM into a stop at a
    chunk boundary with a checkpoint, raising :class:`~xrl_jax.interrupts.RunInterrupted`.
    ``stop_after_chunks`` stops (returning None) after that many chunks of this session, as an
    interruption would; ``resume=True`` continues from the newest good checkpoint of each group.
    ``log`` takes progress lines; ``warn`` (default: standard error, also when ``log`` is silent)
    takes what the user must see: damaged checkpoints, too little disk, a run longer than a day.
    """
    out = Path(out)
    if warn is None:
        warn = functools.partial(print, file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    with RunLock(out):
        remove_leftovers(out)
        try:
            return _HostLoop(cfg, out, trainer, log, warn, progress, stop).run(resume, stop_after_chunks)
        except Exception as err:  # orbax reports a full disk as ValueError("RESOURCE_EXHAUSTED ...")
            if not is_disk_full(err):
                raise
            raise DiskFullError(
                f"the disk of {out} is full (No space left on device); committed checkpoints are intact: "
                f"free some space and continue with --resume {out}"
            ) from None


class _StopAfterChunks(Exception):
    pass


class _HostLoop:
    """The host side of :func:`train`: seed groups one after another, chunk after chunk, and
    between chunks the metric lines, the health check, evaluation and checkpoints."""

    def __init__(self, cfg: TrainConfig, out: Path, trainer: Trainer | None, log, warn, progress: bool, stop):
        self.cfg, self.out, self.log, self.warn, self.stop = cfg, out, log, warn, stop
        self.paths = run_paths(out)
        for key in ("metrics", "eval", "checkpoints"):
            self.paths[key].mkdir(parents=True, exist_ok=True)
        self.start_time = time.perf_counter()
        if stop is not None:
            stop.idle()
        self.backend = backend_summary()
        log(f"backend: {self.backend}")
        self.trainer = get_trainer(cfg) if trainer is None else trainer
        self.progress = progress
        self.bar = None
        self.timing = {"compile_s": 0.0, "train_s": 0.0, "eval_s": 0.0, "checkpoint_s": 0.0, "env_steps": 0}
        self.fingerprint = config_fingerprint(cfg)
        self.chunks_left: int | None = None
        self.saved_step = 0  # the newest checkpoint of the running seed group

    # ---- the run ------------------------------------------------------------------------------
    def run(self, resume: bool, stop_after_chunks: int | None) -> dict[str, Any] | None:
        self.chunks_left = stop_after_chunks
        self.plan = self._plan(resume)
        self.groups = self.plan["groups"]
        self.clock = RunClock(self.cfg, len(self.groups))
        self.done_steps = 0
        try:
            for group_index, seeds in enumerate(self.groups):
                self._run_group(group_index, seeds, resume)
        except _StopAfterChunks:
            return None
        finally:
            if self.bar is not None:
                self.bar.close()
        if self.stop is not None:
            self.stop.idle()
        return self._summarise()

    def _plan(self, resume: bool) -> dict[str, Any]:
        cfg, paths, log = self.cfg, self.paths, self.log
        plan = plan_memory(self.trainer, cfg)
        if resume and paths["plan"].exists():  # keep the grouping the checkpoints were made with
            plan["groups"] = json.loads(paths["plan"].read_text())["groups"]
        else:
            write_atomic(paths["plan"], json.dumps(plan, indent=2, sort_keys=True) + "\n")
        groups, per_seed = plan["groups"], plan["per_seed_bytes"]
        total, buffer = format_bytes(per_seed["total"]), format_bytes(per_seed["buffer"])
        budget = format_bytes(plan["budget_bytes"])
        log(f"memory: ~{total} per seed (buffer {buffer}), budget {budget} ({plan['budget_source']})")
        if len(groups) > 1:
            log(f"memory: {cfg.num_seeds} seeds do not fit at once; running {len(groups)} groups of up to "
                f"{len(groups[0])} seeds one after another")  # fmt: skip
        # Two checkpoints kept per group, plus the one being written.
        needed = 3 * len(groups[0]) * (per_seed["buffer"] + per_seed["agent"] + per_seed["env"])
        free = disk_free_bytes(self.out)
        if free < needed:
            self.warn(f"warning: {format_bytes(free)} free on the disk of {self.out}, but the checkpoints "
                      f"of a seed group need up to {format_bytes(needed)}")  # fmt: skip
        return plan

    def _above_bar(self, write, line: str) -> None:
        if self.bar is None:
            write(line)
            return
        from tqdm import tqdm

        with tqdm.external_write_mode(file=sys.stderr):
            write(line)

    def _kept(self, step: int, group_index: int) -> str:
        """What a resume would continue from, in words."""
        where = f" (seed group {group_index + 1} of {len(self.groups)})" if len(self.groups) > 1 else ""
        if step <= 0:
            return f"nothing has been checkpointed yet{where}, so a resume starts this group afresh"
        return f"the checkpoint at step {step:,} of {self.cfg.total_steps:,} per seed is kept{where}"

    def _run_group(self, group_index: int, seeds: list[int], resume: bool) -> None:
        cfg, paths, trainer = self.cfg, self.paths, self.trainer
        ckpt = Checkpointer(paths["checkpoints"] / f"group_{group_index}")
        try:
            state, next_chunk = _restore_group(
                cfg, trainer, ckpt, seeds, group_index, self.fingerprint, resume, self.log, self.warn
            )
            resumed_step = cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
            self.saved_step = resumed_step
            metric_steps, eval_steps = _expected_rows(cfg, next_chunk)
            for seed in seeds:  # what the checkpoint continues must still be on disk
                check_history(paths["metrics"] / f"seed_{seed}.jsonl", metric_steps, "metric")
                check_history(paths["eval"] / f"seed_{seed}.jsonl", eval_steps, "evaluation")
            for seed in seeds:  # drop anything written after the checkpoint (or everything, when fresh)
                truncate_lines(paths["metrics"] / f"seed_{seed}.jsonl", resumed_step)
                truncate_lines(paths["eval"] / f"seed_{seed}.jsonl", resumed_step)
            self.done_steps += resumed_step * len(seeds)
            if self.stop is not None:
                self.stop.keep(self._kept(resumed_step, group_index))
            if next_chunk >= cfg.num_chunks:
                return
            if state is None:
                state = trainer.init(jnp.asarray(cfg.seed, jnp.int32), jnp.asarray(seeds, jnp.int32))
            # Committed to the device like a restored state, so both hit the same compiled chunk.
            state = jax.device_put(state, jax.devices()[0])
            self._compile(state, next_chunk)
            if self.bar is None:
                self.bar = _progress_bar(cfg.total_steps * cfg.num_seeds, self.done_steps, self.progress)
            self.clock.last_save = time.monotonic()
            for chunk_index in range(next_chunk, cfg.num_chunks):
                state = self._chunk(state, ckpt, group_index, seeds, chunk_index)
        finally:
            ckpt.close()

    def _compile(self, state: RunState, next_chunk: int) -> None:
        """Compile the chunk ahead of its first call, so that chunk timings are execution alone."""
        tic = time.perf_counter()
        self.log("compiling the training chunk ...")
        start = jnp.asarray(next_chunk * self.cfg.chunk_vector_steps, jnp.int32)
        self.trainer.chunk.lower(state, start).compile()  # jit reuses this executable
        seconds = time.perf_counter() - tic
        self.timing["compile_s"] += seconds
        self.log(f"compiled in {seconds:.0f} s")

    def _chunk(self, state, ckpt, group_index, seeds, chunk_index) -> RunState:
        """Run one chunk and everything the host does after it (``self.saved_step`` follows the
        newest checkpoint of the group)."""
        cfg, paths, stop, clock = self.cfg, self.paths, self.stop, self.clock
        if self.chunks_left is not None:
            if self.chunks_left <= 0:
                raise _StopAfterChunks
            self.chunks_left -= 1
        if stop is not None:
            stop.training(clock.expected_chunk_s())
        tic = time.perf_counter()
        start = jnp.asarray(chunk_index * cfg.chunk_vector_steps, jnp.int32)
        state, report = self.trainer.chunk(state, start)
        report = jax.device_get(report)
        elapsed = time.perf_counter() - tic
        if stop is not None:  # the host work until the next chunk: short, and known once measured
            stop.training((clock.eval_s or 0.0) + (clock.save_s or 0.0))
        step = cfg.chunk_end_step(chunk_index)
        collected = (step - (cfg.chunk_end_step(chunk_index - 1) if chunk_index else 0)) * len(seeds)
        self.timing["train_s"] += elapsed
        self.timing["env_steps"] += collected
        for seed, line in _metric_lines(step, seeds, report):
            append_lines(paths["metrics"] / f"seed_{seed}.jsonl", [line])
        def agent_of_row(row):
            return jax.tree.map(lambda x: x[row], state.agent)

        diverged = divergence_message(report, seeds, step, self.trainer.loss_names, agent_of_row)
        if diverged:
            kept = self._kept(self.saved_step, group_index)
            raise DivergenceError(
                f"{diverged}; stopped, and {kept} (resuming would diverge again: start a new run with "
                "other settings, e.g. lower actor_lr and critic_lr)"
            )
        if cfg.evaluates_at(step):
            state = self._evaluate(state, seeds, step)
        if cfg.checkpoints_at(step) or clock.checkpoint_due_by_time():
            self._save(ckpt, state, seeds, chunk_index, step, group_index)
        self.done_steps += collected
        if self.bar is not None:
            name = "rollout/avg_episode_return"
            returns = np.where(report.has_data[name], report.metrics[name], np.nan)
            shown = f" return {np.nanmean(returns):.2f}" if np.any(np.isfinite(returns)) else ""
            self.bar.set_postfix_str(f"group {group_index + 1}/{len(self.groups)}{shown}", refresh=False)
            self.bar.update(collected)
        append_lines(paths["timing"], [{"group": group_index, "step": step, "seconds": elapsed}])
        if stop is not None and stop.requested is not None:  # asked during this chunk or after it
            if self.saved_step != step:
                self._save(ckpt, state, seeds, chunk_index, step, group_index)
            raise RunInterrupted(stop.requested, self._kept(self.saved_step, group_index))
        clock.observe_chunk(chunk_index, elapsed)
        if not clock.estimated and clock.chunk_s is not None:
            clock.estimated = True
            remaining = clock.remaining_s(group_index, chunk_index + 1)
            so_far = time.perf_counter() - self.start_time
            estimate, *warnings = cost_lines(cfg, so_far, remaining, self.backend)
            self._above_bar(self.log, estimate)
            for line in warnings:
                self._above_bar(self.warn, line)
        return state

    def _evaluate(self, state: RunState, seeds: list[int], step: int) -> RunState:
        from xrl_jax import evaluate as evaluate_mod

        tic = time.perf_counter()
        eval_keys, episodes = self.trainer.evaluate(state)
        state = state.replace(eval_key=eval_keys)
        episodes = jax.device_get(episodes)
        self.clock.eval_s = time.perf_counter() - tic
        self.timing["eval_s"] += self.clock.eval_s
        for row, seed in enumerate(seeds):
            per_episode = jax.tree.map(lambda x, r=row: np.asarray(x[r]), episodes)
            line = {"step": step, "seed": seed, **evaluate_mod.summarize_episodes(per_episode)}
            append_lines(self.paths["eval"] / f"seed_{seed}.jsonl", [line])
        return state

    def _save(self, ckpt, state, seeds, chunk_index: int, step: int, group_index: int) -> None:
        # A checkpoint can take up to the state's raw size on disk (compression helps only while the
        # buffer is empty). Checked first, because orbax reports a disk that fills during the save
        # from several threads at once.
        needed, free = tree_bytes(state), disk_free_bytes(ckpt.directory)
        if free < needed:
            raise DiskFullError(
                f"the disk of {self.out} has {format_bytes(free)} free, but the checkpoint at step {step:,} "
                f"needs up to {format_bytes(needed)}; {self._kept(self.saved_step, group_index)}: free some "
                f"space and continue with --resume {self.out}"
            )
        tic = time.perf_counter()
        meta = {"next_chunk": chunk_index + 1, "seeds": seeds, "step": step, "config": self.fingerprint}
        ckpt.save(step, state, meta)
        self.clock.saved(time.perf_counter() - tic)
        self.timing["checkpoint_s"] += self.clock.save_s
        self.saved_step = step
        if self.stop is not None:
            self.stop.keep(self._kept(step, group_index))

    def _summarise(self) -> dict[str, Any]:
        from xrl_jax import evaluate as evaluate_mod

        timing = self.timing
        timing["wall_s"] = time.perf_counter() - self.start_time
        timing["env_steps_per_s"] = timing["env_steps"] / timing["train_s"] if timing["train_s"] > 0 else None
        summary = evaluate_mod.summarize_run(self.out, self.cfg)
        summary["timing_this_session"] = timing
        summary["memory_plan"] = {k: v for k, v in self.plan.items() if k != "groups"} | {
            "groups": len(self.groups)
        }
        write_atomic(self.paths["summary"], json.dumps(summary, indent=2, sort_keys=True) + "\n")
        if summary["curve"]:
            evaluate_mod.plot_learning_curve(summary, self.paths["curve"])
        return summary


def _restore_group(cfg, trainer, ckpt, seeds, group_index, fingerprint, resume, log, warn):
    """``(state or None, next_chunk)`` of a seed group: its newest good checkpoint when resuming."""
    if not resume or ckpt.latest_step() is None:
        return None, 0
    try:
        meta = ckpt.metadata()
    except CorruptCheckpointError:
        meta = None  # a damaged newest checkpoint: restore_newest_good reports it and falls back
    if meta is not None and meta.get("config", fingerprint) != fingerprint:
        raise ConfigError(
            f"checkpoint group {group_index} in {ckpt.directory.parent} was written by another "
            "configuration than config.json describes; start a new run with --out"
        )
    if meta is not None and meta.get("seeds") != seeds:
        raise ConfigError(f"checkpoint group {group_index} holds seeds {meta.get('seeds')}, expected {seeds}")

    def check(state, meta) -> str | None:
        if meta.get("config") != fingerprint or meta.get("seeds") != seeds:
            return "it belongs to another configuration or seed group"
        if not bool(tree_all_finite(state.agent)):
            return f"the agent's {_first_nonfinite_leaf(state.agent)} is not finite"
        return None

    state, meta = ckpt.restore_newest_good(trainer.abstract_state(len(seeds)), check, warn)
    log(f"resuming seed group {group_index + 1} from its checkpoint at step {meta['step']:,}")
    return state, int(meta["next_chunk"])
