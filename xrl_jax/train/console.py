"""What the host loop shows while it trains: the progress bar with the time left, lines written above
it, and once a steady chunk has been timed, the whole run's cost estimate. Both estimates are the
clock's (:mod:`xrl_jax.train.clock`), not tqdm's own: tqdm's rate would start from the warm-up chunks,
which run without updates, and mix the evaluations and checkpoints into it."""

from __future__ import annotations

import sys
import time

import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.train.chunk import ChunkReport
from xrl_jax.train.clock import RunClock, cost_lines

# tqdm's default without its own time left ("<{remaining}"): the postfix leads with the clock's.
BAR_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}]"


def time_left(remaining_s: float | None) -> str:
    """The bar's time left, as tqdm writes durations; ``?`` until a steady chunk has been timed."""
    from tqdm import tqdm

    return "? left" if remaining_s is None else f"~{tqdm.format_interval(remaining_s)} left"


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
            total=total, initial=done_steps, unit="step", unit_scale=True, dynamic_ncols=True,
            file=sys.stderr, bar_format=BAR_FORMAT,
        )  # fmt: skip

    def advance(
        self, collected: int, report: ChunkReport, rows: list[int], where: str, remaining_s: float | None
    ) -> None:
        """Move the bar by ``collected`` steps, with the time left (``remaining_s``, None: not known
        yet) and the mean return of the rows this process holds."""
        if self.bar is None:
            return
        name = "rollout/avg_episode_return"
        returns = np.where(report.has_data[name], report.metrics[name], np.nan)[rows]
        shown = f" return {np.nanmean(returns):.2f}" if np.any(np.isfinite(returns)) else ""
        self.bar.set_postfix_str(f"{time_left(remaining_s)}, {where}{shown}", refresh=False)
        self.bar.update(collected)

    def above_bar(self, write, line: str) -> None:
        if self.bar is None:
            write(line)
            return
        from tqdm import tqdm

        with tqdm.external_write_mode(file=sys.stderr):
            write(line)

    def estimate_once(self, clock: RunClock, group_index: int, chunk_index: int) -> None:
        """Tell the whole run's estimated duration once the clock has timed a steady chunk."""
        if clock.estimated or not clock.steady:
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
