"""Measured set occupancy (xrl_jax.benchmarks.occupancy and its set_occupancy.json) and the costs
counted from it."""

import fnmatch
import itertools
from pathlib import Path

import numpy as np
import pytest
from network_support import action_size

import xrl_jax
from envs.intersection import CURRICULUM, CURRICULUM_PROBS
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
    assert 20 < table["country_road"]["mean"] < 40
    intersection, random = table["intersection"], table["intersection"]["random_actions"]
    # Drivers that keep their cars on the road see more of the others than random ones, which leave
    # the road within seconds (docs/performance.md, "How full the sets are").
    assert 1.0 < intersection["mean"] < 2.0 and 0.2 < random["mean"] < 0.6
    assert intersection["weightings"]["per_observation"] == pytest.approx(intersection["mean"], abs=1e-3)
    # Acting vehicles per env step: at most the caps' curriculum mean, 32/15, reached when every
    # episode stays full; the random drivers' 8-car episodes are not.
    full = sum(cap * p for cap, p in zip(CURRICULUM, CURRICULUM_PROBS, strict=True))
    assert full == pytest.approx(32 / 15)
    for entry in (intersection, random):
        acting = entry["acting_vehicles_per_env_step"]
        assert 1.5 < acting <= full
        assert all(0 < v["acting_vehicles_per_env_step"] <= int(cap) for cap, v in entry["by_cap"].items())
    assert random["acting_vehicles_per_env_step"] < intersection["acting_vehicles_per_env_step"]


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


def test_stored_counts_weigh_each_acting_vehicle_once():
    """Two env steps of 2 envs with 3 vehicle slots of 4 rows: the trainer stores one observation per
    slot that acted, so the mean it learns from weighs a crowded step by its vehicles; counted by hand.
    Slots that did not act hold rows (a removed car's last view) that must not count."""
    present = np.zeros((2, 2, 3, 4), bool)
    acted = np.zeros((2, 2, 3), bool)
    present[0, 0, 0, :2] = present[0, 0, 1, :2] = present[0, 0, 2, 0] = True  # 3 cars see 2, 2, 1
    acted[0, 0] = True
    acted[0, 1, 0] = True  # a lone car; slot 1 did not act but holds 3 rows
    present[0, 1, 1, :3] = True
    present[1, 0, 0, 0] = True  # nobody acted in env 0 at step 1
    present[1, 1, 0, 0] = present[1, 1, 1, 0] = True  # 2 cars see each other
    acted[1, 1, :2] = True
    np.testing.assert_array_equal(occupancy.stored_counts(present, acted), [2, 2, 1, 0, 1, 1])
    weightings = occupancy.occupancy_weightings(present, acted)
    assert weightings["per_observation"] == pytest.approx(7 / 6)  # 7 others in 6 stored observations
    assert weightings["per_env_step"] == pytest.approx((5 / 3 + 0 + 2 / 2) / 3)  # 3 steps with a car
    assert weightings["per_slot"] == pytest.approx(7 / 12)  # over all 2 x 2 x 3 slots
    with pytest.raises(ValueError, match="disagree on the slots"):
        occupancy.stored_counts(present, acted[..., :2])


def test_curriculum_envs_take_the_curriculums_shares():
    envs_at = occupancy.curriculum_envs(30)
    assert envs_at == {1: 16, 2: 8, 4: 4, 8: 2}
    shares = np.asarray(list(envs_at.values())) / 30
    np.testing.assert_allclose(shares, CURRICULUM_PROBS, rtol=1e-12)  # p ∝ 1/n, exact fractions
    for bad in (0, 16):
        with pytest.raises(ValueError, match="multiple of 15"):
            occupancy.curriculum_envs(bad)


@pytest.mark.parametrize("policy", [pytest.param("scripted", marks=pytest.mark.slow), "random"])  # ~15 s each
def test_intersection_rollout_keeps_the_observations_of_vehicles_that_acted(policy):
    out = occupancy.rollout_observations("intersection", num_envs=15, steps=40, policy=policy)
    objects = out["observations"]["vehicles_set"]
    assert objects.shape[1:] == (8, 7) and out["observations"]["state"].shape == (objects.shape[0], 66)
    # 8 envs of 1 car, 4 of 2, 2 of 4, 1 of 8: at most 32 acting per env step
    assert 0 < objects.shape[0] <= 40 * 32
    assert objects.shape[0] == round(out["acting_vehicles_per_env_step"] * 15 * 40)
    summary = occupancy.summarise("intersection", out)
    assert sum(summary["histogram"]) == objects.shape[0] and summary["max"] <= 7
    assert summary["by_cap"]["1"]["mean"] == 0.0  # a lone car sees nobody
    assert summary["weightings"]["per_observation"] == pytest.approx(summary["mean"], abs=1e-3)


def test_rollout_settings_are_checked():
    with pytest.raises(ValueError, match="unknown setting"):
        occupancy.rollout_observations("intersection", num_tracks=3)
    with pytest.raises(ValueError, match="unknown scenario"):
        occupancy.rollout_observations("highway")
    with pytest.raises(ValueError, match="unknown policy 'trained'"):
        occupancy.rollout_observations("intersection", num_envs=15, steps=2, policy="trained")
    with pytest.raises(ValueError, match="multiple of 15"):
        occupancy.rollout_observations("intersection", num_envs=2, steps=2)
