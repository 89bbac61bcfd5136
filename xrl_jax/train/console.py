"""What the host loop shows while it trains: the progress bar with the time left, lines written above
it, and once a steady chunk has been timed, the whole run's cost estimate. Both estimates are the
clock's (:mod:`xrl_jax.train.clock`), not tqdm's own: tqdm's rate would start from the warm-up chunks,
which run without updates, and mix the evaluations and checkpoints into it. Before the first chunk,
where this machine has calibrated the run's configuration (:mod:`xrl_jax.train.calibrations`), the
whole run's cost by that calibration."""

from __future__ import annotations

import sys
import time

import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.train.calibrations import calibrated_remaining_s
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
        self.warned = False  # the long-run warning has been given
        self.calibration_told = False  # the estimate by a cached calibration, before the first chunk

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
        self._tell(remaining, "")

    def estimate_calibrated(
        self, groups: list[list[int]], devices: int, group_index: int, next_chunk: int
    ) -> None:
        """Before the session's first chunk (once): the run's cost from chunk ``next_chunk`` of member
        group ``group_index`` on, by this machine's cached calibration of its configuration, if there
        is one (a run never calibrates itself); the measured estimate follows once a chunk is timed."""
        if self.calibration_told:
            return
        self.calibration_told = True
        found = calibrated_remaining_s(self.cfg, groups, devices, group_index, next_chunk, self.warn)
        if found is not None:
            created = str(found[1].get("created", "an earlier day"))[:10]
            self._tell(found[0], f"by this machine's calibration of {created}; measured after some chunks")

    def _tell(self, remaining_s: float, basis: str) -> None:
        estimate, *warnings = cost_lines(
            self.cfg, time.perf_counter() - self.start_time, remaining_s, self.backend, basis
        )
        self.above_bar(self.log, estimate)
        for line in warnings if not self.warned else ():  # once: the first estimate's
            self.above_bar(self.warn, line)
        self.warned = self.warned or bool(warnings)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
