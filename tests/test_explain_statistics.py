"""The explanation statistics on toy steps whose answers are worked out by hand."""

from types import SimpleNamespace

import numpy as np
import pytest

from xrl_jax.explain.evaluation_steps import join_steps
from xrl_jax.explain.statistics import (
    Binned,
    binned_mean,
    binned_weight,
    explanation_size,
    seed_agreement,
    weight_by_kind,
    weight_change,
    weight_map,
)

# Two steps, three slots; slot 2 of step 1 is absent (weight 0).
WEIGHTS = np.array([[0.5, 0.3, 0.2], [0.75, 0.25, 0.0]])
PRESENT = np.array([[True, True, True], [True, True, False]])


def test_weight_map_sums_each_cell_and_counts_its_objects():
    xy = np.array([[[5.0, 1.0], [5.0, -1.0], [15.0, 1.0]], [[5.0, 1.0], [np.nan, np.nan], [5.0, 1.0]]])
    binned = weight_map(xy, WEIGHTS, PRESENT, x_edges=[0, 10, 20], y_edges=[-2, 0, 2])
    # cell (x 0-10, y 0-2): step 0 slot 0 (0.5) + step 1 slot 0 (0.75); the absent slot is left out
    # even though it sits there, and the NaN place (a neutral component) falls in no cell;
    # cell (x 0-10, y -2-0): step 0 slot 1 (0.3); cell (x 10-20, y 0-2): step 0 slot 2 (0.2).
    np.testing.assert_allclose(binned.mass, [[0.3, 1.25], [0.0, 0.2]])
    np.testing.assert_array_equal(binned.count, [[1, 2], [0, 1]])
    np.testing.assert_allclose(binned.mean_weight(), [[0.3, 0.625], [np.nan, 0.2]])


def test_weight_map_leaves_out_the_neutral_component_but_not_its_mass_elsewhere():
    xy = np.array([[[0.0, 0.0], [5.0, 1.0], [5.0, -1.0]], [[0.0, 0.0], [5.0, 1.0], [5.0, -1.0]]])
    xy[:, 0] = np.nan  # slot 0: the neutral component, no place
    binned = weight_map(xy, WEIGHTS, PRESENT, x_edges=[0, 10], y_edges=[-2, 0, 2])
    np.testing.assert_allclose(binned.mass, [[0.2, 0.3 + 0.25]])


def test_binned_weight_by_distance_and_the_sum_of_two_seeds():
    distance = np.array([[1.0, 6.0, 30.0], [2.0, 9.0, 1.0]])
    binned = binned_weight(distance, WEIGHTS, PRESENT, edges=[0, 5, 10, 20])
    # 30 m is beyond the last edge; the absent slot's 1 m does not count.
    np.testing.assert_allclose(binned.mass, [1.25, 0.55, 0.0])
    np.testing.assert_array_equal(binned.count, [2, 2, 0])
    both = binned + binned
    assert isinstance(both, Binned)
    np.testing.assert_allclose(both.mass, [2.5, 1.1, 0.0])
    np.testing.assert_array_equal(both.count, [4, 4, 0])


def test_weight_by_kind_and_its_range_check():
    kinds = np.array([[0, 1, 1], [1, 0, 2]])
    binned = weight_by_kind(kinds, WEIGHTS, PRESENT, num_kinds=3)
    np.testing.assert_allclose(binned.mass, [0.5 + 0.25, 0.3 + 0.2 + 0.75, 0.0])
    np.testing.assert_array_equal(binned.count, [2, 3, 0])
    with pytest.raises(ValueError, match=r"0\.\.0, got 0\.\.1"):  # the absent slot's kind 2 is not looked at
        weight_by_kind(kinds, WEIGHTS, PRESENT, num_kinds=1)


def test_explanation_size_counts_the_heaviest_objects_to_the_share():
    weights = np.array(
        [
            [0.05, 0.5, 0.15, 0.3],  # sorted 0.5, 0.3, 0.15: 0.8 < 0.9 <= 0.95 -> 3
            [0.95, 0.05, 0.0, 0.0],  # one object covers 0.95 -> 1
            [0.25, 0.25, 0.25, 0.25],  # 0.75 < 0.9 -> all 4
            [0.0, 0.0, 0.0, 0.0],  # no weight: an empty explanation
        ]
    )
    np.testing.assert_array_equal(explanation_size(weights), [3, 1, 4, 0])
    np.testing.assert_array_equal(explanation_size(weights, share=0.5), [1, 1, 2, 0])
    # 0.9 reached exactly (0.6 + 0.3) counts as reached although float32 weights sum to 1 only
    # within their rounding.
    exact = np.array([[0.6, 0.3, 0.1]], np.float32)
    assert explanation_size(exact)[0] == 2
    with pytest.raises(ValueError, match="share"):
        explanation_size(weights, share=0.0)


def test_binned_mean_of_sizes_by_speed():
    sizes = np.array([1, 3, 2, 4, 6])
    speed = np.array([2.0, 4.0, 12.0, 14.0, 40.0])
    means, count = binned_mean(sizes, speed, edges=[0, 10, 20, 30])
    np.testing.assert_allclose(means, [2.0, 3.0, np.nan])
    np.testing.assert_array_equal(count, [2, 2, 0])


def test_weight_change_follows_objects_by_identity():
    # Step a: cones at x = 10, 20, 30 (identity: world place); step b: the first cone has gone out
    # of view, the others moved up a slot, a new cone at x = 40 appeared.
    places_a = np.array([[[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]]])
    places_b = np.array([[[20.0, 0.0], [30.0, 0.0], [40.0, 0.0]]])
    weights_a = np.array([[0.2, 0.5, 0.3]])
    weights_b = np.array([[0.4, 0.4, 0.2]])
    # Shared: cone 20 min(0.5, 0.4) = 0.4, cone 30 min(0.3, 0.4) = 0.3 -> TV = 1 - 0.7.
    np.testing.assert_allclose(weight_change(weights_a, places_a, weights_b, places_b, 0.01), [0.3])
    # By slot instead of by object the same numbers would read 0.5 * (0.2 + 0.1 + 0.1) = 0.2:
    # following the objects is what makes it a statement about attention.
    slots = np.arange(3.0)[None, :, None]
    np.testing.assert_allclose(weight_change(weights_a, slots, weights_b, slots, 0.5), [0.2])
    # The same weights on the same objects do not change; disjoint objects change completely.
    np.testing.assert_allclose(weight_change(weights_a, places_a, weights_a, places_a, 0.01), [0.0])
    np.testing.assert_allclose(weight_change(weights_a, places_a, weights_b, places_a + 100, 0.01), [1.0])


def test_weight_change_never_matches_nan_identities_and_checks_shapes():
    nowhere = np.full((1, 2, 2), np.nan)
    weights = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(weight_change(weights, nowhere, weights, nowhere, 1.0), [1.0])
    with pytest.raises(ValueError, match="must agree"):
        weight_change(weights, nowhere, weights[:, :1], nowhere, 1.0)


def test_weight_change_in_blocks_equals_one_block():
    rng = np.random.default_rng(0)
    weights_a = rng.dirichlet(np.ones(4), size=600)
    weights_b = rng.dirichlet(np.ones(4), size=600)
    ids_a = rng.integers(0, 6, size=(600, 4, 1)).astype(float)
    ids_a = np.sort(ids_a, axis=1) + np.arange(4)[None, :, None] * 10  # unique within a step
    ids_b = ids_a + rng.integers(0, 2, size=(600, 4, 1)) * 10  # some objects keep their identity
    whole = weight_change(weights_a, ids_a, weights_b, ids_b, 0.5)
    for n in (1, 255, 256, 257):
        np.testing.assert_allclose(
            weight_change(weights_a[:n], ids_a[:n], weights_b[:n], ids_b[:n], 0.5), whole[:n]
        )


def test_seed_agreement_of_three_seeds():
    weights = np.array(
        [
            [[1.0, 0.0], [0.5, 0.5]],
            [[1.0, 0.0], [0.5, 0.5]],  # seed 1 = seed 0
            [[0.0, 1.0], [0.3, 0.7]],  # seed 2: TV 1 and 0.2 to the others
        ]
    )
    similarity, same_top = seed_agreement(weights)
    expected = 1 - np.array([[0, 0, 0.6], [0, 0, 0.6], [0.6, 0.6, 0]])
    np.testing.assert_allclose(similarity, expected)
    # Heaviest objects: seed 0/1: slot 0 then (a tie, argmax) slot 0; seed 2: slot 1 twice.
    np.testing.assert_allclose(same_top, [[1, 1, 0], [1, 1, 0], [0, 0, 1]])
    with pytest.raises(ValueError, match="seeds, steps, objects"):
        seed_agreement(weights[0])


# ------------------------------------------------------------------------------------------------
# From recorded episodes to explained steps: hand-built records of known geometry
# ------------------------------------------------------------------------------------------------


def vehicles(x, y, theta, vx, vy):
    return SimpleNamespace(**{k: np.asarray(v, np.float64) for k, v in locals().items()})


def test_racing_steps_place_kind_contact_and_identity_of_cones():
    from xrl_jax.explain.evaluation_steps import _racing_steps

    # One episode of 3 steps, the last one padding. The car at (100, 50 + t) heads north (θ = π/2)
    # at 10 m/s; a blue cone at world (100, 70) is 20 m ahead at step 0 and 19 m at step 1 (closing
    # at 10 m/s: 2 s and 1.9 s to contact); a yellow cone 5 m to the left is passed at right angles
    # at step 0 (closing speed 0) and left behind at step 1, 1 m back (closing at -10/sqrt(26) m/s:
    # never reached). Cone rows: (present, x / n, y / n, blue, yellow), n = 50 m.
    n = 50.0
    rows = np.zeros((1, 3, 3, 5))
    rows[0, 0, 0] = rows[0, 2, 0] = [1, 20 / n, 0, 1, 0]
    rows[0, 1, 0] = [1, 19 / n, 0, 1, 0]
    rows[0, 0, 1] = [1, 0, 5 / n, 0, 1]
    rows[0, 1:, 1] = [1, -1 / n, 5 / n, 0, 1]
    record = SimpleNamespace(
        obs={"cones_set": rows, "state": np.zeros((1, 3, 6))},
        valid=np.array([[True, True, False]]),
        states=SimpleNamespace(
            vehicle=vehicles([[100, 100, 100]], [[50, 51, 51]], [[np.pi / 2] * 3], [[0] * 3], [[10] * 3])
        ),
        explanations=SimpleNamespace(weights=np.array([[[0.8, 0.2, 0], [0.6, 0.4, 0], [0.6, 0.4, 0]]])),
        rewards=np.array([[1.0, 2.0, 5.0]]),
        terminated=np.array([[False, True, True]]),  # its second step left the track (padding repeats)
    )
    trainer = SimpleNamespace(env=None, eval_params=SimpleNamespace(cone_normaliser=n))
    flat = _racing_steps("country_road", trainer, record)
    assert flat["kinds"] == ("blue cone", "yellow cone")
    np.testing.assert_array_equal(flat["present"], [[True, True, False]] * 2)
    np.testing.assert_array_equal(flat["kind"][:, :2], [[0, 1], [0, 1]])
    np.testing.assert_allclose(flat["xy"][:, :2], [[[20, 0], [0, 5]], [[19, 0], [-1, 5]]], atol=1e-12)
    np.testing.assert_allclose(flat["closing"][:, :2], [[10, 0], [10, -10 / np.sqrt(26)]], atol=1e-12)
    np.testing.assert_allclose(flat["speed"], [10, 10])
    np.testing.assert_array_equal(flat["follows"], [False, True])
    np.testing.assert_allclose(flat["returns"], [3.0])  # the padding step's reward is not the episode's
    np.testing.assert_array_equal(flat["steps_to_early_end"], [1, 0])
    record.terminated[0, 1] = False  # the time limit instead: no early end
    np.testing.assert_array_equal(
        _racing_steps("country_road", trainer, record)["steps_to_early_end"], [np.inf] * 2
    )
    record.terminated[0, 1] = True
    # Each cone keeps its world place (its identity) while its ego-frame place moves.
    np.testing.assert_allclose(flat["identity"][:, :2], [[[100, 70], [95, 50]]] * 2, atol=1e-9)
    steps = join_steps([flat])
    np.testing.assert_allclose(steps.time_to_contact[:, :2], [[2.0, np.inf], [1.9, np.inf]])
    change = weight_change(
        steps.weights[:1], steps.identity[:1], steps.weights[1:], steps.identity[1:], steps.identity_tolerance
    )
    np.testing.assert_allclose(change, [0.2])  # 1 - (min(0.8, 0.6) + min(0.2, 0.4))


def test_intersection_steps_name_each_car_by_how_its_approach_meets_the_own():
    from xrl_jax.explain.evaluation_steps import INTERSECTION_KINDS, _intersection_steps

    # Slot 0 (approach N, route 0) at (0, -20) heading north at 10 m/s. Others: slot 1 from S
    # (route 3) at (0, 0) heading south at 5 m/s: oncoming, 20 m ahead, closing at 15 m/s;
    # slot 2 from W (route 6) at (-10, -20) heading east at 3 m/s: crossing, 10 m to the left,
    # closing at 3 m/s; slot 3 from N too (route 1) at (0, -35) at 12 m/s: the same approach, 15 m
    # behind, closing at 2 m/s. Slot 3 holds a new car at step 1 (spawn number 13, then 14).
    x, y = [0, 0, -10, 0] + [500] * 4, [-20, 0, -20, -35] + [500] * 4
    theta = [np.pi / 2, -np.pi / 2, 0, np.pi / 2] + [0] * 4
    vx, vy = [0, 0, 3, 0] + [0] * 4, [10, -5, 0, 12] + [0] * 4
    twice = lambda values: np.array([values, values], np.float64)
    rows = np.zeros((2, 8, 8, 7))
    rows[:, 0, :3, 0] = 1  # slot 0 sees the three others, in slot order; the others see nothing
    rows[:, 0, :3, 1:3] = np.array([[20, 0], [0, 10], [-15, 0]]) / 30
    weights = np.zeros((2, 8, 9))
    weights[:, :, 0] = 1.0  # the neutral component (index 0), all of it for slots 1-3
    weights[:, 0, :4] = [0.1, 0.5, 0.3, 0.1]
    acted = np.zeros((2, 8), bool)
    acted[:, :4] = True
    record = SimpleNamespace(
        acted=acted,
        obs={"vehicles_set": rows, "state": np.zeros((2, 8, 66))},
        states=SimpleNamespace(
            vehicle=vehicles(twice(x), twice(y), twice(theta), twice(vx), twice(vy)),
            route=np.array([[0, 3, 6, 1, 0, 0, 0, 0]] * 2),
            spawn_seq=np.array([[10, 11, 12, 13, 0, 0, 0, 0], [10, 11, 12, 14, 0, 0, 0, 0]]),
        ),
        explanations=SimpleNamespace(weights=weights),
        rewards=np.ones((2, 8)),
        done_reason=np.array([[0, 0, 3, 2, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0]]),
    )
    flat = _intersection_steps(record)
    # Slot by slot: slot 0's two steps come first.
    np.testing.assert_array_equal(flat["follows"], [False, True, False, True, False, True, False, False])
    ego = {k: flat[k][0] for k in ("kind", "xy", "closing", "identity", "present")}
    names = [INTERSECTION_KINDS[k] for k in ego["kind"][:4]]
    assert names == ["neutral", "oncoming", "crossing", "same approach"]
    np.testing.assert_array_equal(ego["present"], [True, True, True, True, False, False, False, False, False])
    np.testing.assert_allclose(ego["xy"][1:4], [[20, 0], [0, 10], [-15, 0]], atol=1e-9)
    np.testing.assert_allclose(ego["closing"][1:4], [15, 3, 2], atol=1e-9)
    assert np.isnan(ego["closing"][0]) and np.all(np.isnan(ego["xy"][0]))
    np.testing.assert_array_equal(ego["identity"][:4, 0], [-1, 11, 12, 13])
    np.testing.assert_allclose(flat["speed"][:2], [10, 10])
    np.testing.assert_allclose(flat["returns"], [8.0])  # every car's reward of the episode
    # Slot 2's car collides at step 0 (the record is hand-built: it goes on acting); slot 3's car
    # leaves the road at step 0 and a new car takes the slot at step 1, whose end is not its own.
    np.testing.assert_array_equal(flat["steps_to_early_end"], [np.inf] * 4 + [0, np.inf, 0, np.inf])


def test_a_figure_interrupted_before_its_rename_leaves_the_previous_one(tmp_path, monkeypatch):
    """kill -9 mid-write: the figure goes to a temporary file first, so the old one stays whole."""
    import os

    from xrl_jax.explain import statistics_figures

    point = {"estimate": 0.0, "low": 0.0, "high": 0.0}
    deletion = {
        "ks": [0, 1],
        "metrics": ["tv"],
        "rankers": {"random": {"tv": {"over_seeds": [point, point]}}},
    }
    path = tmp_path / "deletion.png"
    path.write_bytes(b"the previous figure")

    def killed(*args):
        raise KeyboardInterrupt  # the process dies between writing and renaming

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        statistics_figures.draw_deletion(deletion, path)
    assert path.read_bytes() == b"the previous figure"
    monkeypatch.undo()
    statistics_figures.draw_deletion(deletion, path)
    assert path.read_bytes().startswith(b"\x89PNG")
