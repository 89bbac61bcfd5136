"""Aggregate scores over seeds the way the paper reports them (its ref. [29], Agarwal et al. 2021).

* **IQM**, the interquartile mean: sort the runs, drop the lowest and highest 25 % (``floor(n/4)`` runs
  each side, as ``scipy.stats.trim_mean(x, 0.25)`` does), average the rest. It is robust to a
  few failed seeds yet uses half of the runs, unlike the median.
* **Stratified bootstrap confidence interval**: resample the runs of every task (stratum) with
  replacement, recompute the statistic, repeat, and take percentiles of the replicates. With one
  task it is the ordinary percentile bootstrap over seeds.
* **Probability of improvement** P(X > Y): the chance that a run of X beats a run of Y (ties count
  half), averaged over tasks, with a bootstrap interval resampling both algorithms' runs, and the
  Mann-Whitney U test's p-value (the test behind P(X > Y): U / (n_x n_y) is P(X > Y)).
* **What an interval covers.** A percentile bootstrap over few seeds covers less than it says: at 4
  seeds the IQM's "95 %" interval is always [lowest, highest seed], which holds the median of a
  continuous distribution with probability 1 - 2 * 0.5**4 = 87.5 %. :func:`iqm_interval_coverage` and
  :func:`improvement_interval_coverage` measure the actual coverage at a number of seeds by Monte
  Carlo on normal scores, so that a report can print it beside every interval.

Host-side numpy: these run once per report, on a few hundred numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.stats


def _as_score_matrix(scores) -> np.ndarray:
    """Scores as ``(runs, tasks)``; a 1-D array is one task. Rejects empty or non-finite input."""
    matrix = np.asarray(scores, dtype=np.float64)
    if matrix.ndim == 1:
        matrix = matrix[:, None]
    if matrix.ndim != 2 or matrix.shape[0] == 0 or matrix.shape[1] == 0:
        raise ValueError(
            f"scores must be a non-empty (runs,) or (runs, tasks) array, got shape {matrix.shape}"
        )
    if not np.all(np.isfinite(matrix)):
        raise ValueError("scores contain NaN or infinite values")
    return matrix


def iqm(scores) -> float:
    """Interquartile mean over all runs and tasks (trimming ``floor(n/4)`` values at each end)."""
    values = np.sort(_as_score_matrix(scores), axis=None)
    cut = values.size // 4
    return float(values[cut : values.size - cut].mean())


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap confidence interval."""

    estimate: float
    low: float
    high: float
    confidence: float

    def as_dict(self) -> dict[str, float]:
        return {"estimate": self.estimate, "low": self.low, "high": self.high, "confidence": self.confidence}

    def __str__(self) -> str:
        return f"{self.estimate:.3f} [{self.low:.3f}, {self.high:.3f}]"


def stratified_bootstrap_ci(
    scores,
    statistic: Callable[[np.ndarray], float] = iqm,
    *,
    confidence: float = 0.95,
    replicates: int = 2000,
    seed: int = 0,
) -> Interval:
    """Percentile bootstrap interval of ``statistic``, resampling runs within each task.

    Args:
      scores: ``(runs,)`` or ``(runs, tasks)`` final scores, one row per seed.
      statistic: maps a ``(runs, tasks)`` matrix to a number (default: IQM).
      confidence: e.g. 0.95 for the 2.5 % and 97.5 % percentiles.
      replicates: number of bootstrap resamples.
      seed: seed of the resampling generator, so reports are reproducible.
    """
    matrix = _as_score_matrix(scores)
    _check_bootstrap(confidence, replicates)
    resampled = _resample_runs(matrix, replicates, np.random.default_rng(seed))
    values = [statistic(sample) for sample in resampled]
    return _percentile_interval(float(statistic(matrix)), values, confidence)


def _check_bootstrap(confidence: float, replicates: int) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if replicates < 1:
        raise ValueError(f"replicates must be >= 1, got {replicates}")


def _resample_runs(matrix: np.ndarray, replicates: int, rng: np.random.Generator) -> np.ndarray:
    """``replicates`` same-shape resamples: row indices drawn independently for every task (the strata)."""
    runs, tasks = matrix.shape
    rows = rng.integers(0, runs, size=(replicates, runs, tasks))
    return np.take_along_axis(matrix[None], rows, axis=1)


def _percentile_interval(estimate: float, values, confidence: float) -> Interval:
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(np.asarray(values), [tail, 100.0 - tail])
    return Interval(estimate, float(low), float(high), confidence)


def probability_of_improvement(scores_x, scores_y) -> float:
    """P(X > Y) of the rliable paper (Agarwal et al. 2021, section 4.3): for every task, the probability that
    a run of algorithm X scores higher than a run of Y, ties counting one half (the Mann-Whitney U
    statistic over ``runs_x * runs_y`` pairs), averaged over tasks.

    ``scores_x`` is ``(runs_x,)`` or ``(runs_x, tasks)``, ``scores_y`` ``(runs_y,)`` or ``(runs_y,
    tasks)``; the run counts may differ, the tasks must match."""
    x, y = _as_score_matrix(scores_x), _as_score_matrix(scores_y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"X and Y must cover the same tasks, got {x.shape[1]} and {y.shape[1]}")
    pairs = x[:, None, :] - y[None, :, :]  # (runs_x, runs_y, tasks)
    per_task = np.mean((pairs > 0) + 0.5 * (pairs == 0), axis=(0, 1))
    return float(per_task.mean())


def probability_of_improvement_ci(
    scores_x, scores_y, *, confidence: float = 0.95, replicates: int = 2000, seed: int = 0
) -> Interval:
    """:func:`probability_of_improvement` with its percentile bootstrap interval: the runs of X and of
    Y are resampled independently within every task, as rliable does for two algorithms."""
    x, y = _as_score_matrix(scores_x), _as_score_matrix(scores_y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"X and Y must cover the same tasks, got {x.shape[1]} and {y.shape[1]}")
    _check_bootstrap(confidence, replicates)
    rng = np.random.default_rng(seed)
    pairs = zip(_resample_runs(x, replicates, rng), _resample_runs(y, replicates, rng), strict=True)
    values = [probability_of_improvement(a, b) for a, b in pairs]
    return _percentile_interval(probability_of_improvement(x, y), values, confidence)


def improvement_test(scores_x, scores_y, *, seed: int = 0) -> float:
    """Two-sided p-value of the Mann-Whitney U test that X's and Y's runs come from one distribution,
    on one task's ``(runs_x,)`` and ``(runs_y,)`` scores: twice the smaller tail of U over every split
    of the pooled runs into groups of their sizes (ties kept, as P(X > Y) keeps them), exact up to
    20,000 splits (8 vs 8 is 12,870), a 20,000-permutation Monte Carlo beyond."""
    x, y = _as_score_matrix(scores_x), _as_score_matrix(scores_y)
    if x.shape[1] != 1 or y.shape[1] != 1:
        raise ValueError("the test takes one task's scores: (runs,) arrays")
    method = scipy.stats.PermutationMethod(n_resamples=20_000, rng=np.random.default_rng(seed))
    result = scipy.stats.mannwhitneyu(x[:, 0], y[:, 0], alternative="two-sided", method=method)
    return float(result.pvalue)


def _iqm_last_axis(values: np.ndarray) -> np.ndarray:
    """:func:`iqm` of every row of ``values`` (runs on the last axis)."""
    ordered = np.sort(values, axis=-1)
    cut = ordered.shape[-1] // 4
    return ordered[..., cut : ordered.shape[-1] - cut].mean(axis=-1)


def _percentiles_last_axis(values: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(values, [tail, 100.0 - tail], axis=-1)
    return low, high


# Monte Carlo sizes of the coverage estimates: 2,000 trials give a coverage to about +-0.7 % (one
# binomial standard error at 90 %), and 1,000 resamples per trial place its 2.5 % percentile well.
COVERAGE_TRIALS, COVERAGE_RESAMPLES, _TRIAL_CHUNK = 2_000, 1_000, 100


@lru_cache(maxsize=64)
def iqm_interval_coverage(runs: int, confidence: float = 0.95, seed: int = 0) -> float:
    """The share of :data:`COVERAGE_TRIALS` samples of ``runs`` standard-normal scores whose percentile
    bootstrap interval of the IQM (one task, as :func:`stratified_bootstrap_ci`) holds the
    distribution's IQM, 0: the interval's actual coverage at that many seeds, for scores spread
    symmetrically. Below 5 runs the interval is [lowest, highest] and the coverage 1 - 2**(1 - runs)."""
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")

    def replicates(rng):
        samples = rng.standard_normal((_TRIAL_CHUNK, 1, runs))
        rows = rng.integers(0, runs, size=(_TRIAL_CHUNK, COVERAGE_RESAMPLES, runs))
        return _iqm_last_axis(np.take_along_axis(samples, rows, axis=-1))

    return _coverage(replicates, 0.0, confidence, seed)


@lru_cache(maxsize=256)
def improvement_interval_coverage(runs_x: int, runs_y: int, confidence: float = 0.95, seed: int = 0) -> float:
    """The share of :data:`COVERAGE_TRIALS` pairs of samples (``runs_x`` and ``runs_y`` standard-normal
    scores: no difference, P(X > Y) = 0.5) whose percentile bootstrap interval of P(X > Y)
    (:func:`probability_of_improvement_ci`) holds 0.5. One minus it is how often the interval alone
    would call a difference where there is none."""
    if runs_x < 1 or runs_y < 1:
        raise ValueError(f"runs must be >= 1, got {runs_x} and {runs_y}")

    def replicates(rng):
        x = rng.standard_normal((_TRIAL_CHUNK, 1, runs_x))
        y = rng.standard_normal((_TRIAL_CHUNK, 1, runs_y))
        xs = np.take_along_axis(x, rng.integers(0, runs_x, (_TRIAL_CHUNK, COVERAGE_RESAMPLES, runs_x)), -1)
        ys = np.take_along_axis(y, rng.integers(0, runs_y, (_TRIAL_CHUNK, COVERAGE_RESAMPLES, runs_y)), -1)
        pairs = xs[..., :, None] - ys[..., None, :]
        return np.mean((pairs > 0) + 0.5 * (pairs == 0), axis=(-2, -1))

    return _coverage(replicates, 0.5, confidence, seed)


def _coverage(replicates, truth: float, confidence: float, seed: int) -> float:
    """The share of :data:`COVERAGE_TRIALS` trials whose percentile interval holds ``truth``;
    ``replicates(rng)`` draws :data:`_TRIAL_CHUNK` trials' bootstrap replicates, (chunk, resamples)."""
    _check_bootstrap(confidence, COVERAGE_RESAMPLES)
    rng = np.random.default_rng(seed)
    covered = 0
    for _ in range(COVERAGE_TRIALS // _TRIAL_CHUNK):
        low, high = _percentiles_last_axis(replicates(rng), confidence)
        covered += int(np.sum((low <= truth) & (high >= truth)))
    return covered / COVERAGE_TRIALS
