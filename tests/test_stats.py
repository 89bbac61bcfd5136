"""IQM and stratified bootstrap intervals, against hand-computed values."""

import numpy as np
import pytest

from xrl_jax.stats import iqm, stratified_bootstrap_ci


def test_iqm_hand_computed():
    # 8 runs: drop 2 lowest (0, 1) and 2 highest (90, 100); mean of 2, 3, 4, 5 is 3.5.
    assert iqm([100, 0, 3, 5, 1, 90, 2, 4]) == pytest.approx(3.5)
    # 10 runs: floor(10/4) = 2 dropped at each end, mean of the middle 6.
    assert iqm(np.arange(10.0)) == pytest.approx(np.mean([2, 3, 4, 5, 6, 7]))
    # Fewer than 4 runs: nothing is trimmed.
    assert iqm([1.0, 2.0, 6.0]) == pytest.approx(3.0)


def test_iqm_pools_runs_and_tasks():
    scores = np.array([[0.0, 10.0], [1.0, 11.0], [2.0, 12.0], [3.0, 13.0]])
    assert iqm(scores) == pytest.approx(np.mean([2.0, 3.0, 10.0, 11.0]))


def test_iqm_ignores_outlier_seeds():
    assert iqm([5.0] * 6 + [-1e6, 1e6]) == pytest.approx(5.0)


def test_bootstrap_hand_computed_two_runs():
    # Two runs {0, 1}: resamples are (0,0), (0,1), (1,0), (1,1), so the mean takes 0, 0.5, 1 with
    # probabilities 1/4, 1/2, 1/4; the 95 % percentile interval is [0, 1] with estimate 0.5.
    interval = stratified_bootstrap_ci([0.0, 1.0], statistic=np.mean, replicates=4000)
    assert interval.estimate == pytest.approx(0.5)
    assert interval.low == pytest.approx(0.0)
    assert interval.high == pytest.approx(1.0)


def test_bootstrap_interval_covers_estimate_and_shrinks_with_more_seeds():
    rng = np.random.default_rng(1)
    few = stratified_bootstrap_ci(rng.normal(10, 2, size=5))
    many = stratified_bootstrap_ci(rng.normal(10, 2, size=200))
    for interval in (few, many):
        assert interval.low <= interval.estimate <= interval.high
    assert many.high - many.low < few.high - few.low
    assert many.low < 10 < many.high


def test_bootstrap_resamples_within_tasks():
    # Task columns with very different scales: a stratified resample never mixes their rows, so the
    # mean of each replicate keeps exactly one value per task and row count.
    scores = np.array([[0.0, 1000.0], [0.0, 1000.0], [0.0, 1000.0]])
    interval = stratified_bootstrap_ci(scores, statistic=np.mean, replicates=100)
    assert interval.low == interval.high == pytest.approx(500.0)


def test_bootstrap_is_reproducible_and_constant_data_has_zero_width():
    data = np.linspace(0, 1, 12)
    assert stratified_bootstrap_ci(data, seed=3) == stratified_bootstrap_ci(data, seed=3)
    flat = stratified_bootstrap_ci(np.full(7, 2.5))
    assert flat.low == flat.high == flat.estimate == 2.5


@pytest.mark.parametrize(
    ("scores", "kwargs", "message"),
    [
        ([], {}, "non-empty"),
        ([1.0, np.nan], {}, "NaN"),
        ([1.0, 2.0], {"confidence": 1.5}, "confidence"),
        ([1.0, 2.0], {"replicates": 0}, "replicates"),
    ],
)
def test_bad_input_is_rejected(scores, kwargs, message):
    with pytest.raises(ValueError, match=message):
        stratified_bootstrap_ci(scores, **kwargs)


def test_probability_of_improvement_hand_computed():
    """X = (1, 3), Y = (2, 2, 3): of the 6 pairs, X wins (3, 2) twice, ties (3, 3) once and loses the
    three pairs with 1, so P(X > Y) = (2 + 0.5) / 6; and P(Y > X) = 1 - P(X > Y)."""
    from xrl_jax.stats import probability_of_improvement

    assert probability_of_improvement([1.0, 3.0], [2.0, 2.0, 3.0]) == pytest.approx(2.5 / 6)
    assert probability_of_improvement([2.0, 2.0, 3.0], [1.0, 3.0]) == pytest.approx(3.5 / 6)
    # Two tasks: task 0 X always wins (1.0), task 1 X always loses (0.0): the average over tasks.
    x, y = np.array([[5.0, 0.0], [6.0, 1.0]]), np.array([[1.0, 7.0], [2.0, 8.0], [3.0, 9.0]])
    assert probability_of_improvement(x, y) == pytest.approx(0.5)
    assert probability_of_improvement([4.0], [4.0]) == 0.5


def test_probability_of_improvement_interval():
    """Separated samples give 1 with a zero-width interval; overlapping ones an interval that holds
    the estimate; two runs each give resampled values in {0, 1/4, ..., 1}; bad input is refused."""
    from xrl_jax.stats import probability_of_improvement_ci

    interval = probability_of_improvement_ci([5.0, 6.0, 7.0], [1.0, 2.0])
    assert (interval.estimate, interval.low, interval.high) == (1.0, 1.0, 1.0)
    rng = np.random.default_rng(1)
    interval = probability_of_improvement_ci(rng.normal(0.5, 1, 20), rng.normal(0, 1, 20), replicates=500)
    assert interval.low <= interval.estimate <= interval.high and interval.high - interval.low > 0.05
    small = probability_of_improvement_ci([0.0, 2.0], [1.0, 3.0], replicates=200)
    assert small.estimate == pytest.approx(0.25) and {small.low * 4, small.high * 4} <= set(range(5))
    with pytest.raises(ValueError, match="same tasks"):
        probability_of_improvement_ci(np.zeros((2, 2)), np.zeros((2, 3)))
