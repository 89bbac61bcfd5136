"""The run's time left (xrl_jax.train.clock), from synthetic chunk, evaluation and checkpoint timings:
warm-up chunks and each group's first updating chunk do not set the rate, the first (compiling)
evaluation counts only until a later one is timed, and the bar shows the clock's estimate."""

import time

import pytest

from xrl_jax.train import resolve_config
from xrl_jax.train.clock import RATE_WINDOW, RunClock, cost_lines
from xrl_jax.train.console import BAR_FORMAT, Console, time_left


def quick_start_config():
    """The README's quick start: 80 chunks of 1,000 steps, the first all warm-up, evaluations at 40k
    and 80k, checkpoints every 10k."""
    cfg = resolve_config("tracking", "xdsac", "quick", num_seeds=2, total_steps=80_000)
    assert (cfg.num_chunks, cfg.log_interval, cfg.warmup_steps) == (80, 1_000, 1_000)
    assert (cfg.eval_interval, cfg.checkpoint_interval) == (40_000, 10_000)
    return cfg


def test_warm_up_and_the_first_updating_chunk_do_not_set_the_rate():
    cfg = quick_start_config()
    clock = RunClock(cfg, num_groups=1)
    clock.start_group()
    clock.observe_chunk(0, seconds=0.09)  # all warm-up: no updates
    assert clock.chunk_s is None and clock.remaining_s(0, 1) is None and not clock.steady
    clock.observe_chunk(1, seconds=16.0)  # the first updating chunk: first-time costs
    assert clock.chunk_s == 16.0 and not clock.steady  # stands in until a steady chunk is timed
    for chunk in range(2, 40):
        clock.observe_chunk(chunk, seconds=10.0)
        if chunk % 10 == 9:
            clock.saved(seconds=1.0)
    assert clock.steady and clock.chunk_s == 10.0
    clock.evaluated(seconds=30.0)  # at 40k: the first evaluation, with its compilation
    assert clock.eval_s == 30.0
    # Chunks 40..79 updating, the evaluation at 80k and the checkpoints at 50k, 60k, 70k, 80k.
    assert clock.remaining_s(0, 40) == pytest.approx(40 * 10.0 + 30.0 + 4 * 1.0)
    clock.evaluated(seconds=5.0)  # a later evaluation: compiled already
    assert clock.eval_s == 5.0
    clock.evaluated(seconds=6.0)
    assert clock.eval_s == 6.0  # the newest one after the first


def test_the_rate_follows_the_recent_chunks():
    """A machine whose load changes: the estimate follows the last RATE_WINDOW steady chunks."""
    clock = RunClock(quick_start_config(), num_groups=1)
    clock.start_group()
    clock.observe_chunk(1, seconds=20.0)
    for chunk in range(2, 2 + RATE_WINDOW):
        clock.observe_chunk(chunk, seconds=10.0)
    assert clock.chunk_s == 10.0
    for chunk in range(2 + RATE_WINDOW, 2 + RATE_WINDOW + RATE_WINDOW // 2):
        clock.observe_chunk(chunk, seconds=16.0)
    assert clock.chunk_s == pytest.approx(13.0)  # half of the window at each rate
    for chunk in range(2 + RATE_WINDOW + RATE_WINDOW // 2, 2 + 2 * RATE_WINDOW):
        clock.observe_chunk(chunk, seconds=16.0)
    assert clock.chunk_s == pytest.approx(16.0)


def test_later_groups_count_their_warm_up_as_free_and_their_first_updating_chunk_apart():
    cfg = quick_start_config()
    clock = RunClock(cfg, num_groups=2)
    clock.start_group()
    for chunk in range(1, 80):
        clock.observe_chunk(chunk, seconds=10.0)
    clock.saved(seconds=1.0)
    clock.evaluated(seconds=30.0)
    clock.evaluated(seconds=3.0)
    # The second group: 79 updating chunks, its warm-up chunk free, 2 evaluations, 8 checkpoints.
    assert clock.remaining_s(0, 80) == pytest.approx(79 * 10.0 + 2 * 3.0 + 8 * 1.0)
    clock.start_group()
    clock.observe_chunk(0, seconds=0.1)
    clock.observe_chunk(1, seconds=100.0)  # the second group's first updating chunk
    assert clock.chunk_s == 10.0


def test_a_partly_warm_up_chunk_is_scaled_to_a_full_one_and_the_estimate_warns_beyond_a_day():
    cfg = resolve_config("tracking", "xsac", "paper", num_seeds=20)  # 500 chunks of 2,000 steps
    clock = RunClock(cfg, num_groups=1)
    clock.start_group()
    clock.observe_chunk(0, seconds=1740.0)  # 256 warm-up transitions of 2,000: 1,744 updating
    assert clock.chunk_s == pytest.approx(1740.0 * 2000 / 1744) and not clock.steady
    clock.observe_chunk(1, seconds=1700.0)
    remaining = clock.remaining_s(0, 2)
    assert remaining == pytest.approx(498 * 1700.0)
    lines = cost_lines(cfg, 3600.0, remaining, "cpu (2 cores: test)")
    assert "20 seed(s) x 1,000,000 steps" in lines[0] and "days" in lines[0]
    assert len(lines) == 2 and "--preset quick" in lines[1] and "GPU" in lines[1]
    assert len(cost_lines(quick_start_config(), 60.0, 600.0, "cpu")) == 1  # under a day: no warning


def test_the_estimate_is_told_once_a_steady_chunk_is_timed():
    cfg = quick_start_config()
    lines = []
    console = Console(
        cfg, lines.append, lines.append, enabled=False, backend="cpu", start_time=time.perf_counter()
    )
    clock = RunClock(cfg, num_groups=1)
    clock.start_group()
    for chunk, seconds in enumerate([0.09, 16.0]):
        clock.observe_chunk(chunk, seconds)
        console.estimate_once(clock, 0, chunk)
    assert lines == []
    clock.observe_chunk(2, 10.0)
    console.estimate_once(clock, 0, 2)
    clock.observe_chunk(3, 10.0)
    console.estimate_once(clock, 0, 3)
    assert len(lines) == 1 and lines[0].startswith("estimate: the whole run (2 seed(s) x 80,000 steps)")


def test_the_bar_shows_the_clocks_time_left_not_tqdms():
    from tqdm import tqdm

    assert time_left(None) == "? left" and time_left(754.2) == "~12:34 left"
    bar = tqdm.format_meter(
        n=4_000, total=160_000, elapsed=20.0, unit="step", bar_format=BAR_FORMAT,
        postfix=f"{time_left(754.2)}, group 1/1 return 3.20",
    )  # fmt: skip
    assert "[00:20, 200.00step/s, ~12:34 left, group 1/1 return 3.20]" in bar
    assert "<" not in bar  # tqdm's own time left, from its rate since the start, is not shown
