"""The host loop of a run (:func:`train`): member groups one after another, chunk after chunk, and
between chunks the metric lines, the health check, evaluation, checkpoints, the progress bar, the
cost estimate and clean stops. A member is one seed at one sweep point; a plain run's members are
its seeds. In a run of several processes (:mod:`xrl_jax.train.hosts`) each process writes the
records of the members its devices hold."""

from __future__ import annotations

import functools
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from xrl_jax.checkpoint import Checkpointer
from xrl_jax.config import ConfigError, TrainConfig
from xrl_jax.evaluation import summarize_episodes
from xrl_jax.interrupts import RunInterrupted, StopController
from xrl_jax.resources import backend_summary, disk_free_bytes, format_bytes
from xrl_jax.runs.folder import (
    RunLock,
    append_lines,
    check_history,
    disk_full_message,
    is_disk_full,
    member_fields,
    member_stem,
    read_checkpoint_plan,
    remove_leftovers,
    run_paths,
    truncate_lines,
    write_atomic,
)
from xrl_jax.runs.plots import plot_learning_curve, plot_sweep
from xrl_jax.runs.provenance import config_document
from xrl_jax.runs.summary import summarize_run
from xrl_jax.runs.trackers import TrackerMirror
from xrl_jax.train import hosts
from xrl_jax.train.chunk import RunState, Trainer, get_trainer, member_hparams
from xrl_jax.train.clock import RunClock, cost_lines
from xrl_jax.train.memory import padded_members, plan_memory, tree_bytes
from xrl_jax.train.records import divergence_message, expected_rows, metric_lines
from xrl_jax.train.restore import config_fingerprint, restore_group


class DivergenceError(RuntimeError):
    """A seed produced a non-finite loss or parameter; the message (one line) names the seed, the
    step and the quantity, and what was kept."""


class DiskFullError(RuntimeError):
    """The disk filled up while the run wrote its results; the last committed checkpoint is intact."""


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, unit="step", unit_scale=True, dynamic_ncols=True, file=sys.stderr
    )


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
    trackers: tuple[str, ...] = (),
) -> dict[str, Any] | None:
    """Run (or continue) the whole experiment into ``out``; returns the summary.

    Writes ``config.json`` (a new run: the resolved config, versions and ``command``, see
    :func:`xrl_jax.runs.provenance.config_document`), ``plan.json`` (memory plan and seed groups),
    per seed ``metrics/seed_<i>.jsonl`` (one line per chunk) and ``eval/seed_<i>.jsonl`` (one line
    per evaluation), per group ``checkpoints/group_<g>`` (the newest two, verified on restore),
    ``timing.jsonl`` and at the end ``summary.json`` (with ``unverified_checkpoints`` when a resume
    restored one without its digests). Lines
    written after the newest checkpoint are dropped on resume and recomputed, so a resumed run's
    files equal an uninterrupted run's.

    The folder is locked for the duration (:class:`~xrl_jax.runs.folder.RunLock`). Checkpoints are
    written every ``checkpoint_interval`` steps and every ``checkpoint_minutes`` of wall time, never
    after a chunk in which a seed went non-finite: that raises :class:`DivergenceError` with the
    last good checkpoint kept. ``stop`` (installed by the CLI) turns SIGINT/SIGTERM into a stop at a
    chunk boundary with a checkpoint, raising :class:`~xrl_jax.interrupts.RunInterrupted`.
    ``stop_after_chunks`` stops (returning None) after that many chunks of this session, as an
    interruption would; ``resume=True`` continues from the newest good checkpoint of each group.
    ``log`` takes progress lines; ``warn`` (default: standard error, also when ``log`` is silent)
    takes what the user must see: damaged checkpoints, too little disk, a run longer than a day.
    ``trackers`` (``"tensorboard"``, ``"wandb"``) mirror the records as they are written
    (:mod:`xrl_jax.runs.trackers`).
    """
    out = Path(out)
    if warn is None:
        warn = functools.partial(print, file=sys.stderr)
    try:  # from the folder's first write on: a full disk ends in one line
        out.mkdir(parents=True, exist_ok=True)
        with RunLock(out, jax.process_index()):
            if hosts.is_primary():
                remove_leftovers(out)
                if not resume:
                    document = config_document(cfg, command)
                    text = json.dumps(document, indent=2, sort_keys=True) + "\n"
                    write_atomic(run_paths(out)["config"], text)
            hosts.sync("xrl-jax: run folder ready")
            loop = _HostLoop(cfg, out, trainer, log, warn, progress, stop)
            return loop.run(resume, stop_after_chunks, trackers)
    except Exception as err:  # orbax reports a full disk as ValueError("RESOURCE_EXHAUSTED ...")
        if not is_disk_full(err):
            raise
        raise DiskFullError(disk_full_message(out, resume, err)) from None


class _StopAfterChunks(Exception):
    pass


class _HostLoop:
    """The host side of :func:`train`: member groups one after another, chunk after chunk, and
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
        self.saved_step = 0  # the newest checkpoint of the running member group
        self.rows: list[int] = []  # the running group's rows that this process holds and writes
        self.unverified: list[tuple[int, int]] = []  # (group, step) restored without digests

    # ---- the run ------------------------------------------------------------------------------
    def run(
        self, resume: bool, stop_after_chunks: int | None, trackers: tuple[str, ...]
    ) -> dict[str, Any] | None:
        self.chunks_left = stop_after_chunks
        self.plan = self._plan(resume)
        self.groups = self.plan["groups"]
        self.clock = RunClock(self.cfg, len(self.groups))
        self.done_steps = 0
        # The primary process mirrors every member's records (the folder is shared by all processes).
        self.mirror = TrackerMirror(self.out, self.cfg, trackers, self.warn) if hosts.is_primary() else None
        try:
            try:
                for group_index, members in enumerate(self.groups):
                    self._run_group(group_index, members, resume)
            except _StopAfterChunks:
                return None
            finally:
                if self.bar is not None:
                    self.bar.close()
            if self.stop is not None:
                self.stop.idle()
            return self._summarise()
        finally:
            if self.mirror is not None:
                self.mirror.close()

    def _plan(self, resume: bool) -> dict[str, Any]:
        cfg, paths, log = self.cfg, self.paths, self.log
        plan = plan_memory(self.trainer, cfg)
        smallest = int(hosts.gathered(len(plan["groups"][0])).min())  # all processes run the same groups
        if smallest < len(plan["groups"][0]):
            plan = plan_memory(self.trainer, cfg.replace(max_group_size=smallest))
            plan["groups_limited_by"] = "memory"  # another process's
        devices = self.trainer.num_devices
        if resume and paths["plan"].exists():  # keep the grouping the checkpoints were made with
            stored_groups, was = read_checkpoint_plan(self.out, cfg.num_members)
            plan["groups"], plan["groups_limited_by"] = stored_groups, "the checkpoints"
            padded = [len(padded_members(g, devices)) for g in stored_groups]
            if padded != [len(padded_members(g, was)) for g in stored_groups]:
                raise ConfigError(
                    f"{self.out} was trained on {was} device(s) in all; its checkpoints hold rows for that "
                    f"count, so resume it on {was} device(s) (--devices, or as many processes as before)"
                )
        elif hosts.is_primary():
            write_atomic(paths["plan"], json.dumps(plan, indent=2, sort_keys=True) + "\n")
        groups, per_seed = plan["groups"], plan["per_seed_bytes"]
        total, buffer = format_bytes(per_seed["total"]), format_bytes(per_seed["buffer"])
        budget = format_bytes(plan["budget_bytes"])
        what = "seed" if cfg.num_points == 1 else "member (a seed at a sweep point)"
        source = plan["budget_source"]
        log(f"memory: ~{total} per {what} (buffer {buffer}), budget {budget} per device ({source})")
        if devices > 1 or jax.process_count() > 1:
            per_device = -(-len(groups[0]) // devices)
            log(f"devices: {cfg.num_members} members over {devices} devices in {jax.process_count()} "
                f"process(es), up to {per_device} per device")  # fmt: skip
        if len(groups) > 1:
            why = {
                "max_group_size": f"max_group_size={cfg.max_group_size}",
                "the checkpoints": "as the run began",
            }.get(plan["groups_limited_by"], f"memory: {cfg.num_members} members do not fit at once")
            log(f"{why}: running {len(groups)} groups of up to {len(groups[0])} one after another")
        # Two checkpoints kept per group, plus the one being written.
        needed = 3 * len(groups[0]) * (per_seed["buffer"] + per_seed["agent"] + per_seed["env"])
        needed //= jax.process_count()  # each process writes its members' share
        free = disk_free_bytes(self.out)
        if free < needed:
            self.warn(f"warning: {format_bytes(free)} free on the disk of {self.out}, but the checkpoints "
                      f"of a member group need up to {format_bytes(needed)}")  # fmt: skip
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
        where = f" (member group {group_index + 1} of {len(self.groups)})" if len(self.groups) > 1 else ""
        if step <= 0:
            return f"nothing has been checkpointed yet{where}, so a resume starts this group afresh"
        return f"the checkpoint at step {step:,} of {self.cfg.total_steps:,} per seed is kept{where}"

    def _member_name(self, member: int) -> str:
        point, seed = self.cfg.member_point_seed(member)
        if self.cfg.num_points == 1:
            return f"seed {seed}"
        values = ", ".join(f"{k}={v:g}" for k, v in self.cfg.sweep_points[point].items())
        return f"seed {seed} at sweep point {point} ({values})"

    def _files(self, member: int) -> tuple[Path, Path]:
        stem = member_stem(self.cfg, member)
        return self.paths["metrics"] / f"{stem}.jsonl", self.paths["eval"] / f"{stem}.jsonl"

    def _run_group(self, group_index: int, members: list[int], resume: bool) -> None:
        """Train one group: its members padded to a multiple of the device count (rows), of which
        this process writes the rows its devices hold (``self.rows``)."""
        cfg, trainer = self.cfg, self.trainer
        rows = padded_members(members, trainer.num_devices)
        self.rows = [r for r in hosts.local_rows(trainer.member_sharding, len(rows)) if r < len(members)]
        mine = [members[r] for r in self.rows]
        ckpt = Checkpointer(self.paths["checkpoints"] / f"group_{group_index}")
        try:
            state, next_chunk = self._restore(ckpt, members, len(rows), group_index, resume)
            resumed_step = cfg.chunk_end_step(next_chunk - 1) if next_chunk else 0
            self.saved_step = resumed_step
            metric_steps, eval_steps = expected_rows(cfg, next_chunk)
            for member in mine:  # what the checkpoint continues must still be on disk
                metrics, evals = self._files(member)
                check_history(metrics, metric_steps, "metric")
                check_history(evals, eval_steps, "evaluation")
            for member in mine:  # drop anything written after the checkpoint (or everything, when fresh)
                for path in self._files(member):
                    truncate_lines(path, resumed_step)
            self.done_steps += resumed_step * len(members)
            if self.stop is not None:
                self.stop.keep(self._kept(resumed_step, group_index))
            if next_chunk >= cfg.num_chunks:
                return
            if state is None:
                seeds = [cfg.member_point_seed(m)[1] for m in rows]
                state = trainer.init(cfg.seed, seeds, member_hparams(cfg, trainer.agent, rows))
            self._compile(state, next_chunk)
            if self.bar is None:
                self.bar = _progress_bar(cfg.total_steps * cfg.num_members, self.done_steps, self.progress)
            self.clock.last_save = time.monotonic()
            for chunk_index in range(next_chunk, cfg.num_chunks):
                state = self._chunk(state, ckpt, group_index, members, chunk_index)
        finally:
            ckpt.close()

    def _restore(self, ckpt, members: list[int], num_rows: int, group_index: int, resume: bool):
        """``(state or None, next_chunk)`` of a member group: its newest good checkpoint when resuming.
        A resume that finds none says so: the group starts again from step 0."""
        if not resume:
            return None, 0
        if ckpt.latest_step() is None:
            group = f"member group {group_index + 1} of {len(self.groups)}"
            if not any(path.is_file() and path.stat().st_size for m in members for path in self._files(m)):
                self.log(f"{group} had not started; it starts now")  # groups run one after another
                return None, 0
            self.warn(
                f"--resume: {group} has no checkpoint in "
                f"{ckpt.directory} (deleted, or every one was damaged and set aside in "
                f"{ckpt.directory.name}.rejected); it starts again from step 0"
            )
            return None, 0
        state, meta = restore_group(
            ckpt, self.trainer, members, num_rows, self.fingerprint, group_index, self.warn
        )
        self.unverified += [(group_index, step) for step in ckpt.unverified_steps]
        self.log(f"resuming member group {group_index + 1} from its checkpoint at step {meta['step']:,}")
        return state, int(meta["next_chunk"])

    def _compile(self, state: RunState, next_chunk: int) -> None:
        """Compile the chunk ahead of its first call, so that chunk timings are execution alone."""
        tic = time.perf_counter()
        self.log("compiling the training chunk ...")
        start = np.int32(next_chunk * self.cfg.chunk_vector_steps)
        self.trainer.chunk.lower(state, start).compile()  # jit reuses this executable
        seconds = time.perf_counter() - tic
        self.timing["compile_s"] += seconds
        self.log(f"compiled in {seconds:.0f} s")

    def _chunk(self, state, ckpt, group_index, members, chunk_index) -> RunState:
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
        start = np.int32(chunk_index * cfg.chunk_vector_steps)
        state, report = self.trainer.chunk(state, start)
        report = hosts.fetch(report)
        elapsed = time.perf_counter() - tic
        if stop is not None:  # the host work until the next chunk: short, and known once measured
            stop.training((clock.eval_s or 0.0) + (clock.save_s or 0.0))
        step = cfg.chunk_end_step(chunk_index)
        collected = (step - (cfg.chunk_end_step(chunk_index - 1) if chunk_index else 0)) * len(members)
        self.timing["train_s"] += elapsed
        self.timing["env_steps"] += collected
        for member, line in metric_lines(cfg, step, members, self.rows, report):
            append_lines(self._files(member)[0], [line])

        def agent_of_row(row):
            return jax.tree.map(lambda x: x[row], hosts.fetch(state.agent))

        names = [self._member_name(m) for m in members]
        diverged = divergence_message(report, names, step, self.trainer.loss_names, agent_of_row, self.rows)
        if diverged:
            kept = self._kept(self.saved_step, group_index)
            raise DivergenceError(
                f"{diverged}; stopped, and {kept} (resuming would diverge again: start a new run with "
                "other settings, e.g. lower actor_lr and critic_lr)"
            )
        if cfg.evaluates_at(step):
            state = self._evaluate(state, members, step)
        if cfg.checkpoints_at(step) or self._agreed(clock.checkpoint_due_by_time()):
            self._save(ckpt, state, members, chunk_index, step, group_index)
        self.done_steps += collected
        if self.bar is not None:
            name = "rollout/avg_episode_return"
            returns = np.where(report.has_data[name], report.metrics[name], np.nan)[self.rows]
            shown = f" return {np.nanmean(returns):.2f}" if np.any(np.isfinite(returns)) else ""
            self.bar.set_postfix_str(f"group {group_index + 1}/{len(self.groups)}{shown}", refresh=False)
            self.bar.update(collected)
        if hosts.is_primary():
            append_lines(paths["timing"], [{"group": group_index, "step": step, "seconds": elapsed}])
        if self.mirror is not None:
            self.mirror.sync()
        if self._agreed(stop is not None and stop.requested is not None):  # asked during or after this chunk
            if self.saved_step != step:
                self._save(ckpt, state, members, chunk_index, step, group_index)
            signum = stop.requested if stop is not None and stop.requested is not None else signal.SIGTERM
            raise RunInterrupted(signum, self._kept(self.saved_step, group_index))
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

    def _evaluate(self, state: RunState, members: list[int], step: int) -> RunState:
        tic = time.perf_counter()
        eval_keys, episodes = self.trainer.evaluate(state)
        state = state.replace(eval_key=eval_keys)
        episodes = hosts.fetch(episodes)
        self.clock.eval_s = time.perf_counter() - tic
        self.timing["eval_s"] += self.clock.eval_s
        for row in self.rows:
            per_episode = jax.tree.map(lambda x, r=row: np.asarray(x[r]), episodes)
            fields = member_fields(self.cfg, members[row])
            line = {"step": step, **fields, **summarize_episodes(per_episode)}
            append_lines(self._files(members[row])[1], [line])
        return state

    def _agreed(self, wish: bool) -> bool:
        """True on every process when it is true on any (a stop signal or a checkpoint by wall time
        must be acted on by all processes at the same chunk, since checkpoints are collective)."""
        return bool(hosts.gathered(bool(wish)).any())

    def _save(self, ckpt, state, members, chunk_index: int, step: int, group_index: int) -> None:
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
        meta = {"next_chunk": chunk_index + 1, "members": members, "step": step, "config": self.fingerprint}
        ckpt.save(step, state, meta)
        self.clock.saved(time.perf_counter() - tic)
        self.timing["checkpoint_s"] += self.clock.save_s
        self.saved_step = step
        if self.stop is not None:
            self.stop.keep(self._kept(step, group_index))

    def _summarise(self) -> dict[str, Any]:
        timing = self.timing
        timing["wall_s"] = time.perf_counter() - self.start_time
        timing["env_steps_per_s"] = timing["env_steps"] / timing["train_s"] if timing["train_s"] > 0 else None
        hosts.sync("xrl-jax: all records written")  # every process's members are in their files
        summary = summarize_run(self.out, self.cfg)
        summary["timing_this_session"] = timing
        if self.unverified:  # restored with only a finiteness check (no digest manifest)
            summary["unverified_checkpoints"] = [{"group": g, "step": s} for g, s in self.unverified]
        summary["memory_plan"] = {k: v for k, v in self.plan.items() if k != "groups"} | {
            "groups": len(self.groups),
            "processes": jax.process_count(),
        }
        if self.mirror is not None:  # the other processes' last records are written now
            self.mirror.sync()
        if hosts.is_primary():
            write_atomic(self.paths["summary"], json.dumps(summary, indent=2, sort_keys=True) + "\n")
            if summary["curve"] or summary.get("sweep"):
                plot_learning_curve(summary, self.paths["curve"])
            if summary.get("sweep"):
                plot_sweep(summary, self.paths["sweep"])
        return summary
