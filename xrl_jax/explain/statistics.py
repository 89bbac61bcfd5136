"""Statistics of explanations over many steps: where the weight goes, how many objects a decision
rests on, how steady the weights are from step to step, and whether seeds attend alike.

Every function takes plain arrays of explained steps (host numpy), padded to a fixed number of
object slots ``O`` per step:

* ``weights`` (N, O): each object's mixture weight at one step (0 for absent slots);
* ``present`` (N, O): which slots hold an object;
* ``xy`` (N, O, 2): the objects' ego-frame places in metres (x forward, y left), NaN where an
  object has no place (the neutral, state-only component);
* a per-object label array (object kind, distance, time to contact) or a per-step one (speed).

Sums, not means, come out of the binning functions (``mass``: summed weight; ``count``: objects):
one seed's sums add up over episodes, and the caller divides by its number of steps, so a cell's
mass per step and its mean weight per object both follow. Nothing here knows a scenario: the
run-level code (:mod:`xrl_jax.explain.run_statistics`) turns observations into these arrays.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from xrl_jax.stats import iqm, stratified_bootstrap_ci


@dataclass(frozen=True)
class Binned:
    """Weight summed per bin (``mass``) and present objects per bin (``count``), same shape."""

    mass: np.ndarray
    count: np.ndarray

    def __add__(self, other: Binned) -> Binned:
        return Binned(self.mass + other.mass, self.count + other.count)

    def mean_weight(self) -> np.ndarray:
        """The mean weight of an object in each bin (NaN where no object fell)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.mass / np.maximum(self.count, 1), np.nan)


def _flat_present(weights, present, values):
    """The present objects' weights and values as flat arrays (objects outside every bin are the
    caller's: NaN values fall in none)."""
    weights = np.asarray(weights, np.float64)
    present = np.asarray(present, bool)
    if weights.shape != present.shape:
        raise ValueError(f"weights {weights.shape} and present {present.shape} differ in shape")
    values = np.asarray(values, np.float64)
    if values.shape[: weights.ndim] != weights.shape:
        raise ValueError(f"values {values.shape} do not start with the weights' shape {weights.shape}")
    return weights[present], values[present]


def binned_weight(values, weights, present, edges) -> Binned:
    """Weight and objects per bin of a per-object quantity (distance, time to contact...).

    ``values`` (N, O); ``edges`` the bins' boundaries (increasing, the last bin closed like numpy's
    histogram). Objects whose value is NaN or outside the edges are left out.
    """
    w, v = _flat_present(weights, present, values)
    edges = np.asarray(edges, np.float64)
    mass, _ = np.histogram(v, bins=edges, weights=w)
    count, _ = np.histogram(v, bins=edges)
    return Binned(mass, count.astype(np.int64))


def weight_map(xy, weights, present, x_edges, y_edges) -> Binned:
    """Weight and objects per cell of an ego-frame grid (x forward, y left; cells (X, Y))."""
    w, places = _flat_present(weights, present, xy)
    keep = np.all(np.isfinite(places), axis=-1)
    w, places = w[keep], places[keep]
    bins = (np.asarray(x_edges, np.float64), np.asarray(y_edges, np.float64))
    mass, _, _ = np.histogram2d(places[:, 0], places[:, 1], bins=bins, weights=w)
    count, _, _ = np.histogram2d(places[:, 0], places[:, 1], bins=bins)
    return Binned(mass, count.astype(np.int64))


def weight_by_kind(kinds, weights, present, num_kinds: int) -> Binned:
    """Weight and objects per object kind (``kinds`` (N, O) integers in 0..num_kinds-1)."""
    w, k = _flat_present(weights, present, kinds)
    k = k.astype(np.int64)
    if k.size and (k.min() < 0 or k.max() >= num_kinds):
        raise ValueError(f"object kinds must lie in 0..{num_kinds - 1}, got {k.min()}..{k.max()}")
    mass = np.bincount(k, weights=w, minlength=num_kinds)
    count = np.bincount(k, minlength=num_kinds)
    return Binned(mass, count.astype(np.int64))


def explanation_size(weights, share: float = 0.9) -> np.ndarray:
    """(N,) the fewest objects whose weights add up to at least ``share`` of the step's weight.

    The heaviest objects first: this is the size of the smallest explanation that covers ``share``
    of the policy (pruning the rest changes the action distribution by at most 1 − share in total
    variation, :func:`xrl_jax.explain.prune`). A step with no weight at all has size 0.
    """
    if not 0.0 < share <= 1.0:
        raise ValueError(f"share must lie in (0, 1], got {share}")
    weights = np.asarray(weights, np.float64)
    ordered = -np.sort(-weights, axis=-1)
    covered = np.cumsum(ordered, axis=-1)
    total = covered[..., -1:]
    # A relative slack of 1e-9 absorbs the summation's rounding (weights sum to one in float32,
    # i.e. to within ~1e-7): a share reached only by rounding would otherwise cost an extra object.
    reached = covered >= share * total * (1.0 - 1e-9)
    size = np.argmax(reached, axis=-1) + 1
    return np.where(total[..., 0] > 0, size, 0)


def binned_mean(values, keys, edges) -> tuple[np.ndarray, np.ndarray]:
    """The mean of per-step ``values`` (N,) in bins of a per-step ``keys`` (N,) (speed, objects
    present...): (means per bin, NaN where empty; steps per bin)."""
    values = np.asarray(values, np.float64)
    keys = np.asarray(keys, np.float64)
    if values.shape != keys.shape:
        raise ValueError(f"values {values.shape} and keys {keys.shape} differ in shape")
    edges = np.asarray(edges, np.float64)
    total, _ = np.histogram(keys, bins=edges, weights=values)
    count, _ = np.histogram(keys, bins=edges)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return means, count.astype(np.int64)


def weight_change(weights_a, identity_a, weights_b, identity_b, tolerance: float) -> np.ndarray:
    """(N,) the total variation between two steps' weights over the objects they share.

    Object i of step a and object j of step b are the same object where their identities (N, O, D)
    lie within ``tolerance`` (a cone: its world place; a car: its number; a point ahead: its rank).
    With weights summing to one on both sides the distance is 1 − Σ_matched min(w_a, w_b): the
    weight that has to move between objects, and weight on an object seen at one step only moves
    all of it. Identities must be unique within a step (absent slots carry weight 0 and match
    nothing that matters).
    """
    weights_a, weights_b = (np.asarray(w, np.float64) for w in (weights_a, weights_b))
    identity_a, identity_b = (np.asarray(i, np.float64) for i in (identity_a, identity_b))
    if not weights_a.shape == weights_b.shape == identity_a.shape[:-1] == identity_b.shape[:-1]:
        raise ValueError(
            f"weights {weights_a.shape}, {weights_b.shape} and identities {identity_a.shape}, "
            f"{identity_b.shape} must agree: (N, O) and (N, O, D)"
        )
    overlap = np.empty(weights_a.shape[:-1])
    block = 256  # steps at a time: the (steps, O, O) match of a whole evaluation would not fit
    for start in range(0, weights_a.shape[0], block):
        part = slice(start, start + block)
        gap = np.linalg.norm(identity_a[part, :, None] - identity_b[part, None], axis=-1)
        same = gap <= tolerance  # (n, O, O); NaN identities never match
        shared = np.minimum(weights_a[part, :, None], weights_b[part, None, :])
        overlap[part] = np.sum(np.where(same, shared, 0.0), axis=(-2, -1))
    return 0.5 * (weights_a.sum(-1) + weights_b.sum(-1)) - overlap


def seed_agreement(weights) -> tuple[np.ndarray, np.ndarray]:
    """How alike the seeds' explanations are on the same observations.

    ``weights`` (S, N, O): the policy of each of S seeds at the same N observations (so slot o is
    the same object for all). Returns two (S, S) matrices: the mean of 1 − TV(w_s, w_r) over the
    steps (1 on the diagonal: the same weights), and the share of steps where the two seeds' heaviest
    object is the same.
    """
    weights = np.asarray(weights, np.float64)
    if weights.ndim != 3:
        raise ValueError(f"weights must be (seeds, steps, objects), got shape {weights.shape}")
    seeds = weights.shape[0]
    similarity = np.ones((seeds, seeds))
    top = np.argmax(weights, axis=-1)  # (S, N)
    for s in range(seeds):  # pair by pair: (S, S, N, O) at once would not fit an evaluation's steps
        for r in range(s + 1, seeds):
            similarity[s, r] = similarity[r, s] = 1.0 - 0.5 * np.abs(weights[s] - weights[r]).sum(-1).mean()
    same_top = (top[:, None] == top[None, :]).mean(-1)
    return similarity, same_top


def interval_over_seeds(values, statistic: Callable[[np.ndarray], float] = iqm) -> dict[str, float]:
    """``statistic`` (default the IQM) of the seeds' finite values with its 95 % percentile bootstrap
    interval over seeds, as a JSON-ready dict; one seed gives its value as both ends, none NaN."""
    values = np.asarray(values, np.float64).ravel()
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return {"estimate": float("nan"), "low": float("nan"), "high": float("nan"), "seeds": 0}
    estimate = float(statistic(finite))
    if finite.size == 1:
        return {"estimate": estimate, "low": estimate, "high": estimate, "seeds": 1}
    ci = stratified_bootstrap_ci(finite, statistic=statistic)
    return {"estimate": estimate, "low": ci.low, "high": ci.high, "seeds": int(finite.size)}
