"""Wall-time bookkeeping of the host loop: when a checkpoint is due by time, and what the whole
run will cost (told to the user once the first updating chunk has been measured)."""

from __future__ import annotations

import time

from xrl_jax.config import TrainConfig
from xrl_jax.resources import format_duration

CHECKPOINT_TIME_SHARE = 0.02  # time-based checkpoints never take more than this share of the run
LONG_RUN_S = 86_400.0  # estimates above a day come with a warning and the faster alternatives


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
    steps = cfg.num_members * cfg.total_steps
    finish = time.strftime("%a %H:%M", time.localtime(time.time() + remaining_s))
    points = f" x {cfg.num_points} sweep points" if cfg.num_points > 1 else ""
    lines = [
        f"estimate: the whole run ({cfg.num_seeds} seed(s){points} x {cfg.total_steps:,} steps) takes "
        f"~{format_duration(total)} on {backend} ({steps / max(total, 1e-9):,.0f} steps/s); "
        f"done around {finish}"
    ]
    if total > LONG_RUN_S:
        lines.append(
            f"warning: this run needs ~{format_duration(total)}; for a result today use --preset quick "
            "(its wall times are in the README's Results), fewer --seeds or --steps, or a GPU "
            "(pip install -e '.[cuda]'). Stop with Ctrl-C; --resume continues from the last checkpoint."
        )
    return lines
