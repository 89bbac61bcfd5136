"""Explanation figures: glyph contents are the policy's distributions, sizes follow the weights,
light objects stay unmarked, objects sit where the env put them, and episode frames are deterministic."""

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.patches import Rectangle

import envs
from envs.racing import with_bank
from envs.render import Pose, render_frame
from envs.track import Track
from xrl_jax.agents import make_agent
from xrl_jax.config import preset
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture
from xrl_jax.explain import Explanation, make_episode_rollout, single_track_params
from xrl_jax.explain.figures import (
    GLYPH_Z,
    EpisodeFigures,
    ObjectSet,
    component_density_images,
    discrete_matrix,
    draw_explanation,
    explained_frame,
    intersection_objects,
    mixture_image,
    scene_for,
    scene_objects,
    step_explanation,
)

DATA = Path(__file__).parent / "data"


def load_bank(seed: int = 1) -> Track:
    with np.load(DATA / f"tracks_seed{seed}_size3.npz") as data:
        return Track(**{f.name: jnp.asarray(data[f.name]) for f in dataclasses.fields(Track)})


def discrete_explanation(weights, seed=0) -> Explanation:
    """One step of a categorical mixture with the given object weights and random per-object logits."""
    weights = jnp.asarray(weights, jnp.float32)
    logits = jax.random.normal(jax.random.PRNGKey(seed), (weights.shape[0], 12)) * 2
    present = weights > 0
    policy = CategoricalMixture.create(logits, jnp.log(jnp.where(present, weights, 1.0)), present)
    return Explanation(weights=policy.weights, present=present, policy=policy, is_mixture=True)


def draw(step, objects, **options):
    """Draw the overlay into a real frame; return the glyphs and the rectangles added at glyph depth."""
    captured = {}

    def overlay(ax, to_view):
        before = len(ax.patches)
        captured["glyphs"] = draw_explanation(ax, to_view, step, objects, **options)
        captured["patches"] = list(ax.patches)[before:]

    frame = render_frame(Pose(0.0, 0.0, 0.3), width=320, height=180, overlay=overlay, hud=False)
    assert frame.shape == (180, 320, 3)
    return captured["glyphs"], captured["patches"]


def intersection_frame(state, params, obs, explanation, ego_slot, mirrored=False, **options):
    """One intersection frame following ``ego_slot`` with that car's explanation (neutral object
    first, then the observed vehicles) drawn on it, and the glyphs drawn."""
    step = step_explanation(explanation, mirrored)
    objects = intersection_objects(state, obs, ego_slot, True, step.is_mixture)
    return explained_frame(
        "intersection", state, params, None, step, objects, ego_slot=ego_slot, mirrored=mirrored, **options
    )


def objects_ahead(count):
    """Objects spread in front of the car (world = view up to the rotation), all present."""
    xy = np.stack([np.linspace(5, 40, count), np.linspace(-8, 8, count)], -1)
    return ObjectSet(
        xy, np.ones(count, bool), tuple({"type": "cone"} for _ in range(count)), np.ones(count), 0.3
    )


def test_discrete_matrix_layout_follows_the_action_index():
    probs = np.arange(12.0)
    matrix = discrete_matrix(probs, mirrored=True)  # the paper's column order: steer -1, 0, +1
    assert matrix.shape == (4, 3)
    # top row throttle only (j = 2), then coast (0), both (3), brake only (1); index 4*i_s + j
    np.testing.assert_array_equal(matrix[:, 0], [2, 0, 3, 1])
    np.testing.assert_array_equal(matrix[0], [2, 6, 10])
    np.testing.assert_array_equal(discrete_matrix(probs)[:, ::-1], matrix)  # correct view: +1 on the left
    with pytest.raises(ValueError, match="12"):
        discrete_matrix(np.ones(9))


def test_glyph_sizes_are_ordered_like_the_weights_and_light_objects_are_unmarked():
    weights = [0.5, 0.04, 0.3, 0.16, 0.0]
    step = step_explanation(discrete_explanation(weights))
    glyphs, patches = draw(step, objects_ahead(5), threshold=0.05)
    boxes = [g for g in glyphs if g.index >= 0]
    assert sorted(g.index for g in boxes) == [0, 2, 3]  # 0.04 and the absent slot are unmarked
    by_weight = sorted(boxes, key=lambda g: g.weight)
    assert [g.index for g in sorted(boxes, key=lambda g: g.width)] == [g.index for g in by_weight]
    for g in boxes:  # area proportional to weight
        np.testing.assert_allclose(
            g.width * g.height / (boxes[0].width * boxes[0].height), g.weight / boxes[0].weight, rtol=1e-9
        )
    # The artists: 12 cells + 1 frame per glyph, plus the inset's; cell sizes follow the weights too.
    cells = [
        p for p in patches
        if isinstance(p, Rectangle) and p.get_zorder() == GLYPH_Z and p.get_facecolor()[3] > 0
    ]  # fmt: skip
    assert len(cells) == 12 * len(boxes)
    widths = sorted({round(p.get_width(), 9) for p in cells})
    assert len(widths) == 3
    np.testing.assert_allclose(sorted(g.width / 3 for g in boxes), widths)
    inset = [g for g in glyphs if g.index == -1]
    assert len(inset) == 1
    # Heavier glyphs are drawn first, so the lighter ones stay visible where they overlap.
    assert [g.index for g in boxes] == [0, 2, 3]


def test_discrete_glyph_values_are_the_component_probabilities_and_sum_to_the_policy():
    explanation = discrete_explanation([0.6, 0.3, 0.1], seed=3)
    step = step_explanation(explanation)
    glyphs, _ = draw(step, objects_ahead(3), threshold=0.0)
    probs = np.asarray(explanation.policy.component_probs())
    for g in glyphs:
        if g.index >= 0:
            np.testing.assert_allclose(g.values, discrete_matrix(probs[g.index]), rtol=1e-6)
    inset = next(g for g in glyphs if g.index == -1)
    np.testing.assert_allclose(
        inset.values, discrete_matrix(np.asarray(explanation.policy.probs())), atol=1e-6
    )


def test_continuous_image_of_a_sharp_component_lands_in_the_right_cell():
    # steer tanh(u) = 0.5, throttle fully pressed, brake released -> l = +1 (top row)
    loc = np.array([[np.arctanh(0.5), 3.0, -3.0]])
    image = component_density_images(loc, np.full((1, 3), -6.0))[0]
    assert image.shape == (21, 21)
    np.testing.assert_allclose(image.sum(), 1.0, atol=1e-9)
    row, col = np.unravel_index(np.argmax(image), image.shape)
    assert row == 0 and image[row, col] > 0.99
    assert col == 20 - 15  # steer bin 15 of 21 over [-1, 1]; left of the glyph = steer +1
    mirrored = component_density_images(loc, np.full((1, 3), -6.0), mirrored=True)[0]
    assert np.unravel_index(np.argmax(mirrored), mirrored.shape) == (0, 15)


def test_continuous_image_matches_monte_carlo_and_mixes_linearly():
    rng = np.random.default_rng(0)
    loc, log_scale = np.array([[0.3, 0.2, -0.4]]), np.array([[-0.5, -0.3, 0.0]])
    image = component_density_images(loc, log_scale, mirrored=True)[0]
    u = loc[0] + np.exp(log_scale[0]) * rng.standard_normal((200_000, 3))
    a = np.tanh(u)
    pedals = np.clip(a[:, 1:] / 1.8 + 0.5, 0, 1)
    level = np.rint(pedals * 10).astype(int)
    longitudinal = 10 - (level[:, 0] - level[:, 1])  # row 0 = l = +1
    steer_bin = np.minimum(((a[:, 0] + 1) / 2 * 21).astype(int), 20)
    histogram = np.zeros((21, 21))
    np.add.at(histogram, (longitudinal, steer_bin), 1.0 / len(a))
    np.testing.assert_allclose(image, histogram, atol=4e-3)
    # The combined image of a mixture is the weighted sum of its components' images.
    locs = rng.normal(size=(4, 3))
    images = component_density_images(locs, np.full((4, 3), -0.7))
    w = np.array([0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(mixture_image(images, w), np.tensordot(w, images, 1))


def test_continuous_step_explanation_is_faithful():
    key = jax.random.PRNGKey(5)
    loc = jax.random.normal(key, (6, 2, 3))
    log_scale = jnp.full((6, 2, 3), -0.5)
    logits = jax.random.normal(jax.random.PRNGKey(6), (6,))
    present = jnp.arange(6) < 4
    policy = SquashedGaussianMixture.from_objects(loc, log_scale, logits, present)
    weights = policy.weights.reshape(6, 2).sum(-1)
    step = step_explanation(Explanation(weights, present, policy, True))
    assert step.kind == "continuous" and step.object_values.shape == (6, 21, 21)
    np.testing.assert_allclose(
        np.einsum("o,ols->ls", step.weights, step.object_values), step.combined, atol=1e-12
    )
    np.testing.assert_allclose(step.combined.sum(), 1.0, atol=1e-9)
    glyphs, _ = draw(step, objects_ahead(6), threshold=0.0)
    assert sorted(g.index for g in glyphs if g.index >= 0) == [i for i in range(4) if step.weights[i] > 0]


def test_baselines_draw_only_the_inset():
    policy = CategoricalMixture.create(jax.random.normal(jax.random.PRNGKey(0), (1, 12)))
    step = step_explanation(Explanation(policy.weights, policy.present, policy, False))
    objects = scene_objects(scene_for("tracking"), {}, (0, 0, 0), None, None, is_mixture=False)
    glyphs, _ = draw(step, objects, threshold=0.0)
    assert [g.index for g in glyphs] == [-1]


def test_cone_objects_are_placed_on_the_tracks_cones():
    bank = load_bank()
    env, params = envs.make("country_road", track=jax.tree.map(lambda x: x[0], bank))
    params = single_track_params(with_bank(params, bank), 1)
    obs, state = jax.jit(env.reset_env)(jax.random.PRNGKey(0), params)
    vehicle = state.vehicle
    objects = scene_objects(
        scene_for("country_road"), jax.device_get(obs), (vehicle.x, vehicle.y, vehicle.theta), env, params
    )
    assert objects.present.sum() > 5
    cones = np.asarray(params.tracks.cone_xy[0])
    for xy, label in zip(
        objects.world_xy[objects.present], np.array(objects.labels)[objects.present], strict=True
    ):
        distance = np.linalg.norm(cones - xy, axis=-1)
        nearest = int(np.argmin(distance))
        assert distance[nearest] < 1e-3
        assert label["colour"] == ("blue" if int(params.tracks.cone_type[0][nearest]) == 1 else "yellow")
    # Glyphs go off the road: yellow (left-boundary) cones' to the screen's left, blue ones' to the right.
    weights = objects.present / objects.present.sum()
    step = step_explanation(discrete_explanation(weights))
    pose = Pose(float(vehicle.x), float(vehicle.y), float(vehicle.theta))
    captured = {}
    render_frame(
        pose,
        width=160,
        height=90,
        hud=False,
        overlay=lambda ax, to_view: captured.setdefault(
            "g", draw_explanation(ax, to_view, step, objects, threshold=0.0)
        ),
    )
    boxes = [g for g in captured["g"] if g.index >= 0]
    assert len(boxes) == objects.present.sum()
    for g in boxes:
        shift = g.centre[0] - g.anchor[0]
        assert shift < 0 if objects.labels[g.index]["colour"] == "yellow" else shift > 0
        np.testing.assert_allclose(g.centre[1], g.anchor[1], atol=1e-9)


def test_neutral_object_sits_at_the_ego_vehicle():
    rows = np.zeros((8, 7))
    rows[0, :3] = (1, 0.5, -0.2)
    objects = scene_objects(
        scene_for("intersection"), {"vehicles_set": rows}, (10.0, 5.0, np.pi / 2), None, None, neutral=True
    )
    assert (
        objects.labels[0] == {"type": "neutral"}
        and objects.present[:2].all()
        and not objects.present[2:].any()
    )
    np.testing.assert_allclose(objects.world_xy[0], [10.0, 5.0])
    np.testing.assert_allclose(
        objects.world_xy[1], [10.0 + 6.0, 5.0 + 15.0], atol=1e-12
    )  # ego x forward = +y


@pytest.fixture(scope="module")
def tracking_episode():
    bank = load_bank()
    env, params = envs.make("tracking_discrete", track=jax.tree.map(lambda x: x[0], bank))
    params = single_track_params(with_bank(params, bank), 0)
    obs, _ = env.reset(jax.random.PRNGKey(0), params)
    agent = make_agent(preset("smoke", "tracking", "xdsac"), obs, 12)
    agent_state = jax.jit(agent.init)(jax.random.PRNGKey(1), obs)
    rollout = make_episode_rollout(env, agent, 4, mode="train")
    return env, params, agent_state, rollout


def test_episode_frames_are_identical_under_the_same_key(tracking_episode):
    env, params, agent_state, rollout = tracking_episode
    movies = []
    for _ in range(2):
        record = jax.device_get(rollout(jax.random.PRNGKey(7), params, agent_state))
        figures = EpisodeFigures("tracking_discrete", env, params, record)
        assert figures.length == 4
        movies.append(figures.frames(width=160, height=90, threshold=0.0))
    assert len(movies[0]) == 4
    for a, b in zip(*movies, strict=True):
        np.testing.assert_array_equal(a, b)
    rows = figures.attributions()
    assert [r["step"] for r in rows] == [0, 1, 2, 3]
    for row in rows:
        np.testing.assert_allclose(sum(o["weight"] for o in row["objects"]), 1.0, rtol=1e-5)
        assert {o["trajectory_index"] for o in row["objects"]} == set(range(25))
    with pytest.raises(ValueError, match="beyond the episode"):
        figures.frame(4)


def test_intersection_frame_draws_the_neutral_component_at_the_ego_and_others_at_their_vehicles():
    from xrl_jax.explain import explain
    from xrl_jax.explain.figures import slot_pose

    env, params = envs.make("intersection_discrete", max_vehicles=8)
    obs, state = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    alive = np.asarray(state.alive)
    ego = int(np.flatnonzero(alive)[0])
    ego_obs = jax.tree.map(lambda x: x[ego], obs)
    agent = make_agent(preset("smoke", "intersection", "xdsac"), ego_obs, 12)
    assert agent.config.neutral_object
    agent_state = jax.jit(agent.init)(jax.random.PRNGKey(1), ego_obs)
    explanation = jax.jit(explain, static_argnums=0)(agent, agent_state, ego_obs)
    frame, glyphs = intersection_frame(
        state, params, obs, explanation, ego, threshold=0.0, width=320, height=180
    )
    assert frame.shape == (180, 320, 3)
    boxes = {g.index: g for g in glyphs if g.index >= 0}
    seen = int(np.asarray(obs["vehicles_set"])[ego, :, 0].sum())
    assert sorted(boxes) == list(range(1 + seen))  # neutral (0) + every observed vehicle
    np.testing.assert_allclose(boxes[0].anchor, [0.0, 0.0], atol=1e-9)
    assert boxes[0].centre[0] > 0 and boxes[0].centre[1] > 0  # offset up and to the right
    ex, ey, et = slot_pose(state, ego)
    rel = [
        (np.cos(et) * (x - ex) + np.sin(et) * (y - ey), -np.sin(et) * (x - ex) + np.cos(et) * (y - ey))
        for x, y, _ in (slot_pose(state, s) for s in np.flatnonzero(alive) if s != ego)
    ]
    distances = sorted(np.hypot(rx, ry) for rx, ry in rel if abs(rx) < 30 and abs(ry) < 30)
    np.testing.assert_allclose(
        sorted(np.linalg.norm(boxes[i].anchor) for i in boxes if i > 0), distances, atol=1e-3
    )


def test_intersection_objects_name_the_observed_cars_and_put_the_neutral_one_at_the_ego():
    from envs.intersection import observe, place_vehicles

    _, params = envs.make("intersection_discrete", max_vehicles=8)
    # ego in slot 1 (spawned third); a car ahead (slot 0, spawned last) and one behind (slot 2,
    # spawned first); slot 3 far away (outside the ±30 m sensor box)
    poses = [(-1.5, -20.0, np.pi / 2), (-1.5, -30.0, np.pi / 2), (-1.5, -40.0, np.pi / 2), (40.0, 1.5, 0.0)]
    state = place_vehicles(params, poses, routes=[0, 0, 0, 6], spawn_seq=[9, 7, 2, 3])
    obs = jax.device_get(jax.jit(observe)(params, state))
    objects = intersection_objects(state, obs, 1, neutral=True)
    assert objects.labels[0] == {"type": "neutral"}
    np.testing.assert_allclose(objects.world_xy[0], [-1.5, -30.0], atol=1e-5)
    assert objects.present[:3].all() and not objects.present[3:].any()
    # rows in spawn order: row 0 = the car spawned first (slot 2), row 1 = slot 0
    assert objects.labels[1] == {"type": "vehicle", "row": 0, "slot": 2, "car": 2}
    assert objects.labels[2] == {"type": "vehicle", "row": 1, "slot": 0, "car": 9}
    np.testing.assert_allclose(objects.world_xy[1:3], [[-1.5, -40.0], [-1.5, -20.0]], atol=1e-4)
    baseline = intersection_objects(state, obs, 1, neutral=True, is_mixture=False)
    assert baseline.labels == ({"type": "whole_observation"},)


def test_evaluation_episode_keys_follow_the_evaluation_protocol():
    from xrl_jax.evaluation import EVAL_ENV_SEED, evaluation_episode_keys

    reset_keys, stream_keys = evaluation_episode_keys(jnp.arange(3))
    for j in range(3):
        expected = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(EVAL_ENV_SEED), j))
        np.testing.assert_array_equal(reset_keys[j], expected[0])
        np.testing.assert_array_equal(stream_keys[j], expected[1])
    one_reset, one_stream = evaluation_episode_keys(2)
    np.testing.assert_array_equal(one_reset, reset_keys[2])
    np.testing.assert_array_equal(one_stream, stream_keys[2])


@pytest.mark.slow
def test_multiagent_rollout_replays_the_evaluation_episode():
    """The recorded episode j is evaluation episode j: same summed return and end-of-episode metrics."""
    from xrl_jax.evaluation import make_evaluate_multiagent
    from xrl_jax.explain import make_multiagent_episode_rollout

    env, params = envs.make("intersection_discrete", max_vehicles=8)
    params = params.replace(episode_steps=12)
    obs, _ = jax.jit(env.reset)(jax.random.PRNGKey(0), params)
    ego_obs = jax.tree.map(lambda x: x[0], obs)
    agent = make_agent(preset("smoke", "intersection", "xdsac"), ego_obs, 12)
    agent_state = jax.jit(agent.init)(jax.random.PRNGKey(1), ego_obs)
    evaluation = jax.device_get(
        jax.jit(make_evaluate_multiagent(env, params, agent, 2))(jax.random.PRNGKey(5), agent_state)
    )
    rollout = make_multiagent_episode_rollout(env, agent, 12)
    for j in range(2):
        record = jax.device_get(rollout(j, jax.random.PRNGKey(5), params, agent_state))
        total = np.sum(np.where(record.acted, record.rewards, 0.0))
        np.testing.assert_allclose(total, evaluation["return"][j], rtol=1e-5, atol=1e-6)
        assert np.asarray(record.explanations.weights).shape == (12, 8, 9)
        present = np.asarray(record.explanations.present)[np.asarray(record.acted)]
        weights = np.asarray(record.explanations.weights)[np.asarray(record.acted)]
        np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-5)
        assert present[:, 0].all()  # the neutral component is always there


def test_intersection_figures_follow_the_slot_and_name_a_new_car():
    from types import SimpleNamespace

    from xrl_jax.explain.figures import IntersectionEpisodeFigures, first_alive_slot

    acted = np.zeros((6, 8), bool)
    acted[[0, 1, 4, 5], 2] = True  # slot 2: car 3 for two steps, empty, then car 11
    acted[:, 5] = True
    seq = np.zeros((6, 8), np.int32)
    seq[:, 2] = [3, 3, 3, 3, 11, 11]
    seq[:, 5] = 5
    record = SimpleNamespace(acted=acted, valid=np.ones(6, bool), states=SimpleNamespace(spawn_seq=seq))
    assert first_alive_slot(record) == 2
    figures = IntersectionEpisodeFigures(None, record, 2)
    assert [figures.car(t) for t in range(6)] == [3, 3, None, None, 11, 11]
    assert [figures.new_car(t) for t in range(6)] == [False, False, False, False, True, False]
    assert figures.title(0, "x") == "x step 0\nslot 2 car 3"
    assert figures.title(2) == "step 2\nslot 2 empty"
    assert figures.title(4) == "step 4\nslot 2 car 11 (new car)"
    with pytest.raises(ValueError, match="slot 8 out of range"):
        IntersectionEpisodeFigures(None, record, 8)
    with pytest.raises(ValueError, match="beyond the episode"):
        figures.step(6)
