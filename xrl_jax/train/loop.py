"""The host loop of a run (:func:`train`), shaped as Brax's training loop: a compiled chunk
(:mod:`xrl_jax.train.chunk`, Brax's training epoch) trains every member of a group for ``log_interval``
transitions, and between chunks the host writes the records, checks the members' health, evaluates,
checkpoints, shows its progress and hands the records to the progress callbacks (``progress_fns``,
Brax's ``progress_fn``; ``run.py --log`` mirrors them to TensorBoard and W&B through one). Member groups
run one after another. A member is one seed at one sweep point; a plain run's members are its seeds.
In a run of several processes (:mod:`xrl_jax.train.hosts`) each process writes the records of the
members its devices hold, and every process's callbacks receive every member's."""

from __future__ import annotations

import functools
import json
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from xrl_jax.checkpoint import Checkpointer
from xrl_jax.config import TrainConfig
from xrl_jax.interrupts import RunInterrupted, StopController
from xrl_jax.resources import backend_summary, disk_free_bytes, format_bytes
from xrl_jax.runs.folder import (
    RunLock,
    append_lines,
    check_history,
    checkpoint_dir,
    disk_full_message,
    is_disk_full,
    refused_write,
    remove_leftovers,
    run_paths,
    truncate_lines,
    write_atomic,
)
from xrl_jax.runs.plots import plot_learning_curve, plot_sweep
from xrl_jax.runs.provenance import config_document
from xrl_jax.runs.references import measured_yardstick
from xrl_jax.runs.summary import summarize_run, training_curve
from xrl_jax.train import hosts
from xrl_jax.train.chunk import ChunkReport, RunState, Trainer, get_trainer, member_hparams
from xrl_jax.train.clock import RunClock
from xrl_jax.train.console import Console
from xrl_jax.train.kinds import scenario_kind
from xrl_jax.train.memory import padded_members, plan_run, tree_bytes
from xrl_jax.train.records import Progress, RecordWriter, divergence_message, expected_rows, member_name
from xrl_jax.train.restore import config_fingerprint, restore_group


class DivergenceError(RuntimeError):
    """A seed produced a non-finite loss or parameter, or its env a non-finite reward or observation;
    the message (one line) names the seed, the step and the quantity, and what was kept."""


class DiskFullError(RuntimeError):
    """The disk filled up while the run wrote its results; the last committed checkpoint is intact."""


class FolderWriteError(RuntimeError):
    """A file of the results folder could not be written (no permission, a read-only file system);
    the message is one line and says what is kept."""


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
    command: list[str] | None = None,
    progress_fns: Sequence[Callable[[Progress], None]] = (),
) -> dict[str, Any] | None:
    """Run (or continue) the whole experiment into ``out``; returns the summary.

    Writes the results folder that :mod:`xrl_jax.runs.folder` lays out: the configuration (a new
    run: the resolved config, versions and ``command``, see
    :func:`xrl_jax.runs.provenance.config_document`), the memory plan and member groups, per member a
    metrics line per chunk and an evaluation line per evaluation, per group the newest two
    checkpoints (verified on restore), the chunk timings and at the end the summary (with
    ``unverified_checkpoints`` when a resume restored one without its digests). Lines written after
    the newest checkpoint are dropped on resume and recomputed, so a resumed run's files equal an
    uninterrupted run's.

    The folder is locked for the duration (:class:`~xrl_jax.runs.folder.RunLock`). Checkpoints are
    written every ``checkpoint_interval`` steps and every ``checkpoint_minutes`` of wall time, never
    after a chunk in which a seed went non-finite: that raises :class:`DivergenceError` with the
    last good checkpoint kept. ``stop`` (installed by the CLI) turns SIGINT/SIGTERM into a stop at a
    chunk boundary with a checkpoint, raising :class:`~xrl_jax.interrupts.RunInterrupted`.
    ``stop_after_chunks`` stops (returning None) after that many chunks of this session, as an
    interruption would; ``resume=True`` continues from the newest good checkpoint of each group.
    ``log`` takes progress lines; ``warn`` (default: standard error, also when ``log`` is silent)
    takes what the user must see: damaged checkpoints, too little disk, a run longer than a day.
    Each of ``progress_fns`` is called after every chunk with its :class:`~xrl_jax.train.records.Progress`
    (the records just written). A folder that cannot be written raises :class:`DiskFullError` or
    :class:`FolderWriteError` (one line, saying what is kept).
    """
    out = Path(out)
    if warn is None:
        warn = functools.partial(print, file=sys.stderr)
    loop = None
    try:  # from the folder's first write on: a full disk or a refused write ends in one line
        out.mkdir(parents=True, exist_ok=True)
        with RunLock(out, jax.process_index()):
            if hosts.is_primary():
                remove_leftovers(out)
                if not resume:
                    document = config_document(cfg, command)
                    text = json.dumps(document, indent=2, sort_keys=True) + "\n"
                    write_atomic(run_paths(out)["config"], text)
            hosts.sync("xrl-jax: run folder ready")
            records = RecordWriter(cfg, out, progress_fns)
            loop = _HostLoop(cfg, out, trainer, log, warn, progress, stop, records)
            return loop.run(resume, stop_after_chunks)
    except Exception as err:  # orbax reports a full disk as ValueError("RESOURCE_EXHAUSTED ...")
        failure = _folder_failure(err, out, resume, loop)
        if failure is None:
            raise
        raise failure from None


def _folder_failure(err: Exception, out: Path, resume: bool, loop: _HostLoop | None) -> Exception | None:
    """The one-line error of a write into ``out`` that failed (a full disk, no permission), or None."""
    if is_disk_full(err):
        return DiskFullError(disk_full_message(out, resume, err))
    refused = refused_write(err)
    if refused is None:
        return None
    where = f"{refused.filename}" if refused.filename else f"a file in {out}"
    kept = loop.kept(loop.saved_step) if loop is not None and loop.groups else "nothing has been trained yet"
    return FolderWriteError(
        f"cannot write {where} ({refused.strerror or refused}); {kept}: make the folder writable and "
        f"continue with --resume {out}"
    )


def _summarise(out: Path, cfg: TrainConfig, timing: dict, plan: dict, unverified: list) -> dict[str, Any]:
    """The run's summary over its folder's records, with this session's timing and memory plan and
    the checkpoints restored without digests; written (with its figures) by the primary process."""
    timing["env_steps_per_s"] = timing["env_steps"] / timing["train_s"] if timing["train_s"] > 0 else None
    hosts.sync("xrl-jax: all records written")  # every process's members are in their files
    summary = summarize_run(out, cfg)
    summary["timing_this_session"] = timing
    if unverified:  # restored with only a finiteness check (no digest manifest)
        summary["unverified_checkpoints"] = [{"group": g, "step": s} for g, s in unverified]
    summary["memory_plan"] = {k: v for k, v in plan.items() if k != "groups"} | {
        "groups": len(plan["groups"]),
        "processes": jax.process_count(),
    }
    if hosts.is_primary():
        paths = run_paths(out)
        write_atomic(paths["summary"], json.dumps(summary, indent=2, sort_keys=True) + "\n")
        if summary["curve"] or summary.get("sweep"):
            kind = scenario_kind(cfg)
            training = training_curve(out, cfg) if kind.training_episodes_like_evaluation else {}
            reference = measured_yardstick(cfg)
            plot_learning_curve(summary, paths["curve"], reference=reference, training=training)
        if summary.get("sweep"):
            plot_sweep(summary, paths["sweep"])
    return summary


class _StopAfterChunks(Exception):
    pass


class _HostLoop:
    """The host side of :func:`train`: member groups one after another, chunk after chunk, and
    between chunks the records, the health check, evaluation, checkpoints and clean stops."""

    def __init__(self, cfg: TrainConfig, out: Path, trainer, log, warn, progress: bool, stop, records):
        self.cfg, self.out, self.log, self.warn, self.stop, self.records = cfg, out, log, warn, stop, records
        for key in ("metrics", "eval", "checkpoints"):
            run_paths(out)[key].mkdir(parents=True, exist_ok=True)
        self.start_time = time.perf_counter()
        if stop is not None:
            stop.idle()
        backend = backend_summary()
        log(f"backend: {backend}")
        self.trainer = get_trainer(cfg) if trainer is None else trainer
        self.console = Console(cfg, log, warn, progress, backend, self.start_time)
        self.timing = {"compile_s": 0.0, "train_s": 0.0, "eval_s": 0.0, "checkpoint_s": 0.0, "env_steps": 0}
        self.fingerprint = config_fingerprint(cfg)
        self.chunks_left: int | None = None
        self.groups: list[list[int]] = []
        self.group_index = 0  # the running member group
        self.saved_step = 0  # the newest checkpoint of the running group
        self.rows: list[int] = []  # the running group's rows that this process holds and writes
        self.unverified: list[tuple[int, int]] = []  # (group, step) restored without digests

    # ---- the run and its groups ---------------------------------------------------------------
    def run(self, resume: bool, stop_after_chunks: int | None) -> dict[str, Any] | None:
        self.chunks_left = stop_after_chunks
        self.plan = plan_run(self.trainer, self.cfg, self.out, resume, self.log, self.warn)
        self.groups = self.plan["groups"]
        self.clock = RunClock(self.cfg, len(self.groups))
        self.done_steps = 0
        try:
            for group_index, members in enumerate(self.groups):
                self._run_group(group_index, members, resume)
        except _StopAfterChunks:
            return None
        finally:
            self.console.close()
        if self.stop is not None:
            self.stop.idle()
        self.timing["wall_s"] = time.perf_counter() - self.start_time
        return _summarise(self.out, self.cfg, self.timing, self.plan, self.unverified)

    def kept(self, step: int) -> str:
        """What a resume would continue from, in words."""
        groups = len(self.groups)
        where = f" (member group {self.group_index + 1} of {groups})" if groups > 1 else ""
        if step <= 0:
            return f"nothing has been checkpointed yet{where}, so a resume starts this group afresh"
        return f"the checkpoint at step {step:,} of {self.cfg.total_steps:,} per seed is kept{where}"

    def _run_group(self, group_index: int, members: list[int], resume: bool) -> None:
        """Train one group: its members padded to a multiple of the device count (rows), of which
        this process writes the rows its devices hold (``self.rows``)."""
        cfg, trainer = self.cfg, self.trainer
        self.group_index = group_index
        rows = padded_members(members, trainer.num_devices)
        self.rows = [r for r in hosts.local_rows(trainer.member_sharding, len(rows)) if r < len(members)]
        ckpt = Checkpointer(checkpoint_dir(self.out, group_index))
        try:
            state, next_chunk = self._restore(ckpt, members, len(rows), resume)
            self._continue_files(members, next_chunk)
            if next_chunk >= cfg.num_chunks:
                return
            if state is None:
                seeds = [cfg.member_point_seed(m)[1] for m in rows]
                state = trainer.init(cfg.seed, seeds, member_hparams(cfg, trainer.agent, rows))
            self.console.estimate_calibrated(self.groups, trainer.num_devices, group_index, next_chunk)
            self._compile(state, next_chunk)
            self.clock.start_group()
            self.console.open(self.done_steps)
            self.clock.last_save = time.monotonic()
            for chunk_index in range(next_chunk, cfg.num_chunks):
                state = self._chunk(state, ckpt, members, chunk_index)
        finally:
            ckpt.close()

    def _restore(self, ckpt: Checkpointer, members: list[int], num_rows: int, resume: bool):
        """``(state or None, next_chunk)`` of a member group: its newest good checkpoint when resuming.
        A resume that finds none says so: the group starts again from step 0."""
        if not resume:
            return None, 0
        group = f"member group {self.group_index + 1} of {len(self.groups)}"
        if ckpt.latest_step() is None:
            files = [path for m in members for path in self.records.files(m)]
            if not any(path.is_file() and path.stat().st_size for path in files):
                self.log(f"{group} had not started; it starts now")  # groups run one after another
                return None, 0
            self.warn(
                f"--resume: {group} has no checkpoint in {ckpt.directory} (deleted, or every one was "
                f"damaged and set aside in {ckpt.rejected_directory.name}); it starts again from step 0"
            )
            return None, 0
        state, meta = restore_group(
            ckpt, self.trainer, members, num_rows, self.fingerprint, self.group_index, self.warn
        )
        self.unverified += [(self.group_index, step) for step in ckpt.unverified_steps]
        self.log(f"resuming member group {self.group_index + 1} from its checkpoint at step {meta['step']:,}")
        return state, int(meta["next_chunk"])

    def _continue_files(self, members: list[int], next_chunk: int) -> None:
        """Check that this process's member files hold what the checkpoint continues, and drop what
        was written after it (or everything, when the group starts afresh)."""
        resumed_step = self.cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
        self.saved_step = resumed_step
        metric_steps, eval_steps = expected_rows(self.cfg, next_chunk)
        mine = [members[r] for r in self.rows]
        for member in mine:
            metrics, evals = self.records.files(member)
            check_history(metrics, metric_steps, "metric")
            check_history(evals, eval_steps, "evaluation")
        for member in mine:
            for path in self.records.files(member):
                truncate_lines(path, resumed_step)
        self.done_steps += resumed_step * len(members)
        if self.stop is not None:
            self.stop.keep(self.kept(resumed_step))

    def _compile(self, state: RunState, next_chunk: int) -> None:
        """Compile the chunk ahead of its first call, so that chunk timings are execution alone."""
        tic = time.perf_counter()
        self.log("compiling the training chunk ...")
        start = np.int32(next_chunk * self.cfg.chunk_vector_steps)
        self.trainer.chunk.lower(state, start).compile()  # jit reuses this executable
        seconds = time.perf_counter() - tic
        self.timing["compile_s"] += seconds
        self.log(f"compiled in {seconds:.0f} s")

    # ---- one chunk and what follows it ---------------------------------------------------------
    def _chunk(self, state: RunState, ckpt: Checkpointer, members: list[int], chunk_index: int) -> RunState:
        """Run one chunk and everything the host does after it, in this order."""
        cfg = self.cfg
        self._count_chunk()
        state, report, elapsed = self._train_chunk(state, chunk_index)
        self.clock.observe_chunk(chunk_index, elapsed)
        step = cfg.chunk_end_step(chunk_index)
        metrics = self.records.metrics(step, members, self.rows, report)
        self._check_health(state, report, members, step)
        evaluations = ()
        if cfg.evaluates_at(step):
            state, evaluations = self._evaluate(state, members, step)
        if cfg.checkpoints_at(step) or self._agreed(self.clock.checkpoint_due_by_time()):
            self._save(ckpt, state, members, chunk_index, step)
        self._account(chunk_index, members, report, elapsed)
        self.records.tell(Progress(step, self.group_index, metrics, evaluations))
        self._stop_if_asked(ckpt, state, members, chunk_index, step)
        self.console.estimate_once(self.clock, self.group_index, chunk_index)
        return state

    def _count_chunk(self) -> None:
        """``stop_after_chunks``: stop as an interruption would once this session ran that many."""
        if self.chunks_left is not None:
            if self.chunks_left <= 0:
                raise _StopAfterChunks
            self.chunks_left -= 1

    def _train_chunk(self, state: RunState, chunk_index: int) -> tuple[RunState, ChunkReport, float]:
        """The compiled chunk, its report (every member's, on every process) and its wall time."""
        stop, clock = self.stop, self.clock
        if stop is not None:
            stop.training(clock.expected_chunk_s())
        tic = time.perf_counter()
        state, report = self.trainer.chunk(state, np.int32(chunk_index * self.cfg.chunk_vector_steps))
        report = hosts.fetch_all(report)
        elapsed = time.perf_counter() - tic
        if stop is not None:  # the host work until the next chunk: short, and known once measured
            stop.training((clock.eval_s or 0.0) + (clock.save_s or 0.0))
        self.timing["train_s"] += elapsed
        return state, report, elapsed

    def _check_health(self, state: RunState, report: ChunkReport, members: list[int], step: int) -> None:
        """Stop with :class:`DivergenceError` when a member went non-finite in the chunk."""

        def agent_of_row(row):
            return jax.tree.map(lambda x: x[row], hosts.fetch(state.agent))

        names = [member_name(self.cfg, m) for m in members]
        diverged = divergence_message(report, names, step, self.trainer.loss_names, agent_of_row, self.rows)
        if diverged:
            line, advice = diverged
            raise DivergenceError(f"{line}; stopped, and {self.kept(self.saved_step)} ({advice})")

    def _evaluate(self, state: RunState, members: list[int], step: int) -> tuple[RunState, tuple]:
        tic = time.perf_counter()
        eval_keys, episodes = self.trainer.evaluate(state)
        state = state.replace(eval_key=eval_keys)
        episodes = hosts.fetch_all(episodes)
        seconds = time.perf_counter() - tic
        self.clock.evaluated(seconds)
        self.timing["eval_s"] += seconds
        return state, self.records.evaluations(step, members, self.rows, episodes)

    def _account(self, chunk_index: int, members: list[int], report: ChunkReport, elapsed: float) -> None:
        """Count the chunk's transitions, move the progress bar, append the chunk's timing."""
        cfg = self.cfg
        step = cfg.chunk_end_step(chunk_index)
        collected = (step - (cfg.chunk_end_step(chunk_index - 1) if chunk_index else 0)) * len(members)
        self.timing["env_steps"] += collected
        self.done_steps += collected
        where = f"group {self.group_index + 1}/{len(self.groups)}"
        remaining = self.clock.remaining_s(self.group_index, chunk_index + 1) if self.clock.steady else None
        self.console.advance(collected, report, self.rows, where, remaining)
        if hosts.is_primary():
            row = {"group": self.group_index, "step": step, "seconds": elapsed}
            append_lines(run_paths(self.out)["timing"], [row])

    def _stop_if_asked(self, ckpt, state: RunState, members: list[int], chunk_index: int, step: int) -> None:
        """A stop asked for during or after this chunk: checkpoint (if not just done) and raise."""
        stop = self.stop
        if self._agreed(stop is not None and stop.requested is not None):
            if self.saved_step != step:
                self._save(ckpt, state, members, chunk_index, step)
            signum = stop.requested if stop is not None and stop.requested is not None else signal.SIGTERM
            raise RunInterrupted(signum, self.kept(self.saved_step))

    def _agreed(self, wish: bool) -> bool:
        """True on every process when it is true on any (a stop signal or a checkpoint by wall time
        must be acted on by all processes at the same chunk, since checkpoints are collective)."""
        return bool(hosts.gathered(bool(wish)).any())

    def _save(
        self, ckpt: Checkpointer, state: RunState, members: list[int], chunk_index: int, step: int
    ) -> None:
        # A checkpoint can take up to the state's raw size on disk (compression helps only while the
        # buffer is empty). Checked first, because orbax reports a disk that fills during the save
        # from several threads at once.
        needed, free = tree_bytes(state), disk_free_bytes(ckpt.directory)
        if free < needed:
            raise DiskFullError(
                f"the disk of {self.out} has {format_bytes(free)} free, but the checkpoint at step {step:,} "
                f"needs up to {format_bytes(needed)}; {self.kept(self.saved_step)}: free some "
                f"space and continue with --resume {self.out}"
            )
        tic = time.perf_counter()
        meta = {"next_chunk": chunk_index + 1, "members": members, "step": step, "config": self.fingerprint}
        ckpt.save(step, state, meta)
        self.clock.saved(time.perf_counter() - tic)
        self.timing["checkpoint_s"] += self.clock.save_s
        self.saved_step = step
        if self.stop is not None:
            self.stop.keep(self.kept(step))
