"""What the host loop shows while it trains: the progress bar, lines written above it, and once the
first updating chunk has been timed, the whole run's cost estimate (:mod:`xrl_jax.train.clock`)."""

from __future__ import annotations

import sys
import time

import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.train.chunk import ChunkReport
from xrl_jax.train.clock import RunClock, cost_lines


class Console:
    """The progress bar (over every member's steps, on standard error) and the lines above it."""

    def __init__(self, cfg: TrainConfig, log, warn, enabled: bool, backend: str, start_time: float):
        self.cfg, self.log, self.warn, self.enabled = cfg, log, warn, enabled
        self.backend, self.start_time = backend, start_time
        self.bar = None

    def open(self, done_steps: int) -> None:
        """Show the bar (once), ``done_steps`` of every member's steps already done."""
        if self.bar is not None or not self.enabled:
            return
        from tqdm import tqdm

        total = self.cfg.total_steps * self.cfg.num_members
        self.bar = tqdm(
            total=total, initial=done_steps, unit="step", unit_scale=True, dynamic_ncols=True, file=sys.stderr
        )

    def advance(self, collected: int, report: ChunkReport, rows: list[int], where: str) -> None:
        """Move the bar by ``collected`` steps, with the mean return of the rows this process holds."""
        if self.bar is None:
            return
        name = "rollout/avg_episode_return"
        returns = np.where(report.has_data[name], report.metrics[name], np.nan)[rows]
        shown = f" return {np.nanmean(returns):.2f}" if np.any(np.isfinite(returns)) else ""
        self.bar.set_postfix_str(f"{where}{shown}", refresh=False)
        self.bar.update(collected)

    def above_bar(self, write, line: str) -> None:
        if self.bar is None:
            write(line)
            return
        from tqdm import tqdm

        with tqdm.external_write_mode(file=sys.stderr):
            write(line)

    def estimate_once(self, clock: RunClock, group_index: int, chunk_index: int) -> None:
        """Tell the whole run's estimated duration once the clock has timed an updating chunk."""
        if clock.estimated or clock.chunk_s is None:
            return
        clock.estimated = True
        remaining = clock.remaining_s(group_index, chunk_index + 1)
        estimate, *warnings = cost_lines(
            self.cfg, time.perf_counter() - self.start_time, remaining, self.backend
        )
        self.above_bar(self.log, estimate)
        for line in warnings:
            self.above_bar(self.warn, line)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
