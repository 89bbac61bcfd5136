"""Measured set occupancy (xrl_jax.benchmarks.occupancy and its set_occupancy.json) and the costs
counted from it."""

import fnmatch
import itertools
from pathlib import Path

import numpy as np
import pytest
from network_support import action_size

import xrl_jax
from xrl_jax.agents import make_agent
from xrl_jax.benchmarks import occupancy
from xrl_jax.config import preset
from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation


def test_the_measured_table_is_complete_and_consistent():
    table = occupancy.load_occupancy()
    for scenario in occupancy.SCENARIOS:
        entry = table[scenario]
        counts = np.asarray(entry["histogram"])
        assert entry["slots"] == ENV_OBSERVATIONS[scenario].num_objects
        assert counts.sum() == entry["observations"] > 1000
        values = np.repeat(np.arange(counts.size), counts)
        assert entry["mean"] == pytest.approx(values.mean(), abs=1e-3)  # stored rounded to 3 decimals
        assert (entry["p50"], entry["p99"], entry["max"]) == (
            int(np.percentile(values, 50)),
            int(np.percentile(values, 99)),
            int(values.max()),
        )
    assert table["tracking"]["histogram"][-1] == table["tracking"]["observations"]  # always full
    assert 0.3 < table["intersection"]["mean"] < 0.7 and 20 < table["country_road"]["mean"] < 40
    assert 1.0 < table["intersection"]["acting_vehicles_per_env_step"] < 8.0


def test_the_table_ships_inside_the_package():
    """An installed package has no docs/ folder: the table the cost estimates read lies inside the
    package, and pyproject.toml declares it as package data, so a wheel carries it."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    package = Path(xrl_jax.__file__).resolve().parent
    path = occupancy.OCCUPANCY_FILE
    assert path.is_relative_to(package) and path.is_file()
    pyproject = tomllib.loads((package.parent / "pyproject.toml").read_text())
    declared = pyproject["tool"]["setuptools"]["package-data"]
    owner = ".".join(path.parent.relative_to(package.parent).parts)
    assert any(fnmatch.fnmatch(path.name, pattern) for pattern in declared.get(owner, ()))


def test_overflow_probability_counts_what_it_says():
    histogram = [2, 5, 3]  # a set holds 0, 1 or 2 objects with probabilities 0.2, 0.5, 0.3
    probs = np.asarray(histogram) / 10
    for sets, capacity in [(1, 1), (2, 2), (3, 4)]:
        exact = sum(
            np.prod(probs[list(c)]) for c in itertools.product(range(3), repeat=sets) if sum(c) > capacity
        )
        assert occupancy.overflow_probability(histogram, sets, capacity) == pytest.approx(exact, abs=1e-12)
    # an always-present extra row per set, and independent calls
    assert occupancy.overflow_probability(histogram, 1, 2, extra_rows=1) == pytest.approx(0.3)
    assert occupancy.overflow_probability(histogram, 1, 1, calls=2) == pytest.approx(1 - 0.7**2)
    # Many sets: the normal approximation against a Monte-Carlo count (10⁵ batches: ±0.005 at 3σ).
    rng = np.random.default_rng(0)
    totals = rng.choice(3, size=(100_000, 64), p=probs).sum(1)
    capacity = 72
    assert occupancy.overflow_probability(histogram, 64, capacity) == pytest.approx(
        np.mean(totals > capacity), abs=0.01
    )


def test_update_cost_counts_the_packed_update_and_its_fallback():
    shape = ENV_OBSERVATIONS["country_road"]
    for algo in ("xdsac", "sac"):
        agent = make_agent(preset("smoke", "country_road", algo), dummy_observation(shape), action_size(algo))
        cost = occupancy.update_cost(agent, 16)
        assert cost["packed"] < 0.6 * cost["dense"]  # 512 of 1,600 slot rows per batch
        # A batch of 16 sets averages 462 cones, sd 22 (set_occupancy.json): 512 rows are 2.3 sd
        # above it, so a few per cent of updates fall back; the training batch of 128 almost never does.
        assert 0.001 < cost["fallback_probability"] < 0.1
        assert 0 < occupancy.fallback_probability(agent, 128) < 1e-6
        assert cost["packed"] < cost["expected"] < cost["dense"]
    tracking_example = dummy_observation(ENV_OBSERVATIONS["tracking"])
    tracking = make_agent(preset("smoke", "tracking", "xsac"), tracking_example, 3)
    cost = occupancy.update_cost(tracking, 16)
    assert cost["packed"] is None and cost["expected"] == cost["dense"]


def test_intersection_rollout_keeps_the_observations_of_vehicles_that_acted():
    out = occupancy.rollout_observations("intersection", num_envs=2, steps=40)
    objects = out["observations"]["vehicles_set"]
    assert objects.shape[1:] == (8, 7) and out["observations"]["state"].shape == (objects.shape[0], 66)
    assert 0 < objects.shape[0] <= 2 * 40 * 8
    assert objects.shape[0] == round(out["acting_vehicles_per_env_step"] * 2 * 40)
    summary = occupancy.summarise("intersection", out)
    assert sum(summary["histogram"]) == objects.shape[0] and summary["max"] <= 7
    with pytest.raises(ValueError, match="unknown setting"):
        occupancy.rollout_observations("intersection", num_tracks=3)
    with pytest.raises(ValueError, match="unknown scenario"):
        occupancy.rollout_observations("highway")
