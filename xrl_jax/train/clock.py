"""Wall-time bookkeeping of the host loop: when a checkpoint is due by time, and how long the rest of
the run takes (the progress bar's time left, and the whole run's cost told once).

The estimate counts the remaining chunks at the mean duration of recent *steady* chunks, plus the
remaining evaluations and step-interval checkpoints at their measured durations. It leaves out what
would mislead it. Chunks that are mostly warm-up (random actions, no updates) cost a fraction of an
updating chunk: 0.09 s against about 12.5 s at the quick preset on Tracking (``timing.jsonl`` of
tests/test_train.py::test_quick_preset_learns_on_tracking, 2 CPU cores). Each member group's first
updating chunk in the session carries first-time costs although the chunk is compiled ahead of it:
0.10 s against 0.05 s for every later chunk on 2 CPU cores (``run.py --env tracking --algo xdsac
--preset smoke --seeds 2 --steps 1920``). The first evaluation of a session compiles the evaluation,
so a later one, once measured, is the one counted."""

from __future__ import annotations

import time
from collections import deque

from xrl_jax.config import TrainConfig
from xrl_jax.resources import format_duration

CHECKPOINT_TIME_SHARE = 0.02  # time-based checkpoints never take more than this share of the run
LONG_RUN_S = 86_400.0  # estimates above a day come with a warning and the faster alternatives
# Steady chunks averaged for the time left: recent ones, so that the estimate follows a machine whose
# load changes during the run, and enough of them that one slow chunk moves it little.
RATE_WINDOW = 20


class RunClock:
    """Wall-time bookkeeping of the host loop: time-based checkpoints and the time left."""

    def __init__(self, cfg: TrainConfig, num_groups: int):
        self.cfg = cfg
        self.num_groups = num_groups
        self.last_save = time.monotonic()
        self.save_s: float | None = None  # the last checkpoint's duration
        self.first_eval_s: float | None = None  # this session's first evaluation (with its compilation)
        self.later_eval_s: float | None = None  # the newest evaluation after it
        self.first_update_s: float | None = None  # the group's first updating chunk, scaled (below)
        # Durations of recent steady chunks, each scaled to a chunk that updates on every transition.
        self.steady_chunks: deque[float] = deque(maxlen=RATE_WINDOW)
        self.group_updating = False  # the running group has had its first updating chunk
        self.estimated = False

    def saved(self, seconds: float) -> None:
        self.save_s = seconds
        self.last_save = time.monotonic()

    def evaluated(self, seconds: float) -> None:
        if self.first_eval_s is None:
            self.first_eval_s = seconds
        else:
            self.later_eval_s = seconds

    @property
    def eval_s(self) -> float | None:
        """What an evaluation costs: the newest one after the first (which compiled), else the first."""
        return self.later_eval_s if self.later_eval_s is not None else self.first_eval_s

    def checkpoint_due_by_time(self) -> bool:
        minutes = self.cfg.checkpoint_minutes
        if not minutes:
            return False
        interval = max(60.0 * minutes, (self.save_s or 0.0) / CHECKPOINT_TIME_SHARE)
        return time.monotonic() - self.last_save >= interval

    def start_group(self) -> None:
        """A member group starts (or resumes): its next updating chunk is its first."""
        self.group_updating = False

    def updating_share(self, chunk_index: int) -> float:
        """The share of the chunk's transitions that are followed by an update (not warm-up)."""
        cfg = self.cfg
        first, last = chunk_index * cfg.log_interval, cfg.chunk_end_step(chunk_index)
        return max(last - max(first, cfg.warmup_steps), 0) / (last - first)

    def observe_chunk(self, chunk_index: int, seconds: float) -> None:
        """Learn from a chunk in which at least half the transitions update (updates dominate; its
        time is scaled up to a chunk that updates on every transition). The group's first such chunk
        is kept apart: it stands in only until a steady one has been timed."""
        share = self.updating_share(chunk_index)
        if share < 0.5:
            return
        if not self.group_updating:
            self.group_updating = True
            self.first_update_s = seconds / share
            return
        self.steady_chunks.append(seconds / share)

    @property
    def steady(self) -> bool:
        """Whether a steady chunk has been timed, so that the time left can be trusted."""
        return bool(self.steady_chunks)

    @property
    def chunk_s(self) -> float | None:
        """An updating chunk's duration: the mean of the recent steady chunks, until one is timed the
        group's first updating chunk (an over-estimate), None before any."""
        if self.steady_chunks:
            return sum(self.steady_chunks) / len(self.steady_chunks)
        return self.first_update_s

    def expected_chunk_s(self) -> float | None:
        """How long the next chunk and a checkpoint after it should take (None until measured)."""
        if self.chunk_s is None:
            return None
        return self.chunk_s + (self.save_s or 0.0)

    def remaining_s(self, group_index: int, next_chunk: int) -> float | None:
        """Time left for the whole run from chunk ``next_chunk`` of group ``group_index`` on: chunks
        by their updating share (warm-up is nearly free), evaluations and step-interval checkpoints
        at their measured durations (None until an updating chunk has been timed)."""
        chunk_s = self.chunk_s
        if chunk_s is None:
            return None
        cfg = self.cfg

        def cost(first_chunk: int) -> float:  # chunks first_chunk.. of one group, with their events
            chunks = range(first_chunk, cfg.num_chunks)
            ends = [cfg.chunk_end_step(c) for c in chunks]
            evals = sum(map(cfg.evaluates_at, ends))
            saves = sum(map(cfg.checkpoints_at, ends))
            training = chunk_s * sum(self.updating_share(c) for c in chunks)
            return training + evals * (self.eval_s or 0.0) + saves * (self.save_s or 0.0)

        return cost(next_chunk) + (self.num_groups - group_index - 1) * cost(0)


def cost_lines(
    cfg: TrainConfig, elapsed_s: float, remaining_s: float, backend: str, basis: str = ""
) -> list[str]:
    """The estimate of the whole run's time (``basis``: what it rests on, when not this session's
    measured chunks), with a warning and the alternatives beyond a day."""
    total = elapsed_s + remaining_s
    steps = cfg.num_members * cfg.total_steps
    finish = time.strftime("%a %H:%M", time.localtime(time.time() + remaining_s))
    points = f" x {cfg.num_points} sweep points" if cfg.num_points > 1 else ""
    lines = [
        f"estimate: the whole run ({cfg.num_seeds} seed(s){points} x {cfg.total_steps:,} steps) takes "
        f"~{format_duration(total)} on {backend} ({steps / max(total, 1e-9):,.0f} steps/s); "
        f"done around {finish}" + (f" ({basis})" if basis else "")
    ]
    if total > LONG_RUN_S:
        lines.append(
            f"warning: this run needs ~{format_duration(total)}; for a result today use --preset quick "
            "(its wall times are in the README's Results), fewer --seeds or --steps, or a GPU "
            "(pip install -e '.[cuda]'). Stop with Ctrl-C; --resume continues from the last checkpoint."
        )
    return lines
