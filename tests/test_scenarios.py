"""Country Road / Tracking scenarios: golden replays of the original, endings, cones, API invariants."""

from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import track_reference

import envs
from envs import racing, ring_geometry
from envs.racing import IDLING, LEFT_TRACK, MAX_TIME, stack_tracks
from envs.vehicle import body_velocity

DATA = Path(__file__).parent / "data"
GOLDEN = {
    "tracking": "episode_tracking_public.npz",
    "country_road": "episode_country_road_public.npz",
}
STILL = np.array([0.0, -1.0, -1.0], np.float32)  # no steering, both pedals released
FULL_THROTTLE = np.array([0.0, 1.0, -1.0], np.float32)


def load(name):
    with np.load(DATA / GOLDEN[name]) as data:
        return {k: data[k] for k in data.files}


def golden_track(data, cones=None):
    cone_xy, cone_type = (data["cone_pos"], data["cone_type"]) if cones is None else cones
    pose = data["start_pose"]
    return envs.track_from_arrays(data["track_centerline"], pose[:2], pose[2], cone_xy, cone_type)


def rollout(env, params, state, actions):
    """Scan ``env.step`` over ``actions``; returns per-step outputs and the final state."""

    def body(state, action):
        obs, state, reward, terminated, truncated, info = env.step(
            jax.random.PRNGKey(0), state, action, params
        )
        out = dict(obs=obs, reward=reward, terminated=terminated, truncated=truncated, info=info)
        out["vehicle"] = state.vehicle.to_vector()
        out["v_body"] = jnp.stack(body_velocity(state.vehicle))
        out["cone_alive"] = state.cone_alive
        return state, out

    return jax.lax.scan(body, state, actions)


_rollout = jax.jit(rollout, static_argnums=0)


# ----------------------------------------------------------------------------------------------
# Golden replays (float64, tests/data/README.md §3 / §4)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["tracking", "country_road"])
def replay(request):
    name = request.param
    data = load(name)
    with jax.enable_x64(True):
        env, params = envs.make(name, track=golden_track(data))
        obs0, state0 = env.reset(jax.random.PRNGKey(0), params)
        _, out = _rollout(env, params, state0, jnp.asarray(data["actions_raw"]))
        out = jax.tree.map(np.asarray, out)
        obs0 = jax.tree.map(np.asarray, obs0)
        s0 = float(state0.prev_s)
    return name, data, obs0, s0, out


def test_golden_replay_vehicle_and_rewards(replay):
    _, data, _, _, out = replay
    assert data["valid_steps"] == len(data["reward"])  # the whole file is well conditioned
    np.testing.assert_allclose(out["vehicle"], data["state"][1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(out["v_body"], data["v_body"][1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(out["reward"], data["reward"], rtol=0, atol=1e-9)
    assert out["reward"].sum() == pytest.approx(float(data["episode_return"]), abs=1e-8)


def test_golden_replay_observations(replay):
    name, data, obs0, _, out = replay
    np.testing.assert_allclose(obs0["state"], data["obs_state"][0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(out["obs"]["state"], data["obs_state"][1:], rtol=0, atol=1e-6)
    if name == "tracking":
        np.testing.assert_allclose(obs0["trajectory_set"], data["obs_trajectory_set"][0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            out["obs"]["trajectory_set"], data["obs_trajectory_set"][1:], rtol=0, atol=1e-9
        )
    else:
        expected = data["obs_cones_set"]
        np.testing.assert_allclose(obs0["cones_set"], expected[0], rtol=0, atol=1e-6)
        np.testing.assert_allclose(out["obs"]["cones_set"], expected[1:], rtol=0, atol=1e-6)
        exact = [0, 3, 4]  # present flag and one-hot type columns
        np.testing.assert_array_equal(out["obs"]["cones_set"][..., exact], expected[1:][..., exact])


def test_golden_replay_flags_metrics_and_geometry(replay):
    name, data, _, s0, out = replay
    info = out["info"]
    np.testing.assert_array_equal(out["terminated"], data["terminated"])
    np.testing.assert_array_equal(out["truncated"], data["truncated"])
    np.testing.assert_array_equal(info["done_reason"], data["info_done_reason"])
    np.testing.assert_array_equal(info["time_limit_truncated"], data["info_time_limit_truncated"])
    np.testing.assert_allclose(
        info["avg_track_velocity"], data["info_avg_track_velocity"][1:], rtol=0, atol=1e-8
    )
    length = float(data["track_length"])

    def mod_diff(a, b):
        return np.abs((a - b + length / 2) % length - length / 2)

    assert mod_diff(s0, data["proj_s"][0]) < 1e-6
    assert np.max(mod_diff(info["proj_s"], data["proj_s"][1:])) < 1e-6
    np.testing.assert_allclose(info["dist_center"], data["dist_center"][1:], rtol=0, atol=1e-6)
    if name == "country_road":
        np.testing.assert_array_equal(info["cones_hit"], data["info_cones_hit"])
        count = data["cone_alive"].shape[1]
        np.testing.assert_array_equal(out["cone_alive"][:, :count], data["cone_alive"][1:])
        assert not out["cone_alive"][:, count:].any()
        assert info["cones_hit"][-1] == 2
    else:
        assert not info["cones_hit"].any()


# ----------------------------------------------------------------------------------------------
# Float32 scenarios on the golden track (shared envs, one compile per scenario)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def track32():
    return golden_track(load("country_road"))


@pytest.fixture(scope="module")
def road(track32):
    return envs.make("country_road", track=track32)


@pytest.fixture(scope="module")
def tracking(track32):
    return envs.make("tracking", track=track32)


HORIZON = 601  # one rollout length for every float32 test: one compile per env


def run(env_params, actions, params=None, **overrides):
    """Roll out ``actions`` (padded with the last one to HORIZON steps); outputs cut to len(actions)."""
    env, default = env_params
    params = (default if params is None else params).replace(**overrides)
    obs0, state = env.reset(jax.random.PRNGKey(0), params)
    actions = np.asarray(actions, np.float32)
    padded = np.concatenate([actions, np.repeat(actions[-1:], HORIZON - len(actions), axis=0)])
    final, out = _rollout(env, params, state, jnp.asarray(padded))
    return obs0, final, jax.tree.map(lambda x: np.asarray(x)[: len(actions)], out)


def first_done(out):
    done = out["terminated"] | out["truncated"]
    assert done.any(), "episode did not end"
    return int(np.argmax(done))


def test_standstill_is_truncated_for_idling_at_step_51_with_zero_return(road):
    _, _, out = run(road, np.tile(STILL, (60, 1)))
    k = first_done(out)
    assert k + 1 == 51
    assert out["truncated"][k] and not out["terminated"][k]
    assert out["info"]["done_reason"][k] == IDLING and out["info"]["time_limit_truncated"][k]
    assert not out["info"]["done_reason"][:k].any()
    assert out["reward"][: k + 1].sum() == 0.0
    np.testing.assert_array_equal(out["vehicle"][k, 3:], 0.0)  # never moved


def test_time_limit_truncates_at_step_600_and_beats_idling(tracking):
    _, _, out = run(tracking, np.tile(STILL, (601, 1)), max_idle_steps=10**6)
    k = first_done(out)
    assert k + 1 == 600
    assert out["truncated"][k] and not out["terminated"][k]
    assert out["info"]["done_reason"][k] == MAX_TIME
    # Both limits on the same step: MaxTime has priority (docs/carenv-single-agent.md §3.3).
    _, _, out = run(tracking, np.tile(STILL, (60, 1)), max_steps=51)
    k = first_done(out)
    assert k + 1 == 51 and out["info"]["done_reason"][k] == MAX_TIME


def test_full_throttle_leaves_track_with_reward_minus_one(road):
    _, _, out = run(road, np.tile(FULL_THROTTLE, (80, 1)))
    k = first_done(out)
    info = out["info"]
    assert out["terminated"][k] and not out["truncated"][k]
    assert out["reward"][k] == -1.0  # overwrite: no progress term, no cone penalty
    assert info["done_reason"][k] == LEFT_TRACK
    assert info["dist_center"][k] > 4.0 and np.all(info["dist_center"][:k] <= 4.0)
    # §8.3: straight at full throttle leaves after 31-46 steps on seeds 0-2, hitting cones.
    assert 31 <= k + 1 <= 46
    assert info["cones_hit"][k] >= 1
    assert np.all(out["reward"][:k] > -1.0)


def test_cone_hit_costs_0_2_once_and_removes_the_cone(track32, road, tracking):
    data = load("country_road")
    x, y, theta = data["start_pose"]
    ahead = np.array([[x + 8.0 * np.cos(theta), y + 8.0 * np.sin(theta)], [x - 30.0, y - 30.0]])
    _, lone = envs.make("country_road", track=golden_track(data, cones=(ahead, np.array([2, 1]))))
    actions = np.tile(FULL_THROTTLE, (25, 1))
    _, _, out = run(road, actions, params=lone)
    _, _, ref = run(tracking, actions)  # same car, no cones
    hits = np.diff(np.concatenate([[0], out["info"]["cones_hit"]]))
    assert hits.sum() == 1
    k = int(np.argmax(hits))
    np.testing.assert_allclose(out["reward"][k], ref["reward"][k] - 0.2, atol=1e-6)
    others = np.arange(len(hits)) != k
    np.testing.assert_allclose(out["reward"][others], ref["reward"][others], atol=1e-6)
    assert out["cone_alive"][k - 1, 0] and not out["cone_alive"][k:, 0].any()
    assert out["cone_alive"][:, 1].all()
    cones = out["obs"]["cones_set"]
    assert (cones[k - 1, :, 4] == 1).any()  # the yellow cone was visible before the hit ...
    assert not (cones[k:, :, 4] == 1).any()  # ... and is gone afterwards


def test_cone_collision_shape_is_strict_rounded_rectangle():
    a, b, r = 1.905, 0.74, 0.3
    x = jnp.array([a + r - 1e-6, a + r, 0.0, 0.0, a + 0.2, a + 0.22, a + 0.29, 0.0, -a - r + 1e-3])
    y = jnp.array([0.0, 0.0, b + r - 1e-6, b + r, b + 0.2, b + 0.22, 0.0, 0.0, 0.1])
    expected = [True, False, True, False, True, False, True, True, True]
    np.testing.assert_array_equal(np.asarray(ring_geometry.cone_hits(x, y)), expected)


def test_action_spaces_are_known_by_name_without_building_params():
    """What a run's config.json and an agent need, without generating a track."""
    for name in envs.ENV_NAMES:
        size = envs.action_size(envs.action_space(name))
        assert size == (12 if name.endswith("_discrete") else 3), name
    with pytest.raises(ValueError, match="unknown env name"):
        envs.action_space("racing")


def test_discrete_table_maps_through_the_shared_control_path():
    env, continuous = envs.CountryRoad(discrete=True), envs.CountryRoad()
    assert env.action_space().n == 12 and continuous.action_space().shape == (3,)
    table = np.array([[s, t, b] for s in (-1, 0, 1) for t in (-1, 1) for b in (-1, 1)], np.float32)
    for index, raw in enumerate(table):
        np.testing.assert_array_equal(np.asarray(env._control(index)), np.asarray(continuous._control(raw)))
    np.testing.assert_array_equal(np.asarray(env._control(6)), [0.0, 1.0, 0.0])  # straight, full throttle


# ----------------------------------------------------------------------------------------------
# API: determinism, batching, auto-reset, spaces, make()
# ----------------------------------------------------------------------------------------------


def mirrored(track):
    """The same track mirrored at the x axis (a different but valid track for a 2-track bank)."""
    flip = lambda xy: xy * jnp.array([1.0, -1.0], xy.dtype)
    return track.replace(
        centerline=flip(track.centerline),
        start_xy=flip(track.start_xy),
        start_theta=-track.start_theta,
        cone_xy=flip(track.cone_xy),
        cone_type=jnp.where(track.cone_present, 3 - track.cone_type, 0),
    )


@pytest.fixture(scope="module")
def batched(track32):
    env, params = envs.make("tracking", track=stack_tracks([track32, mirrored(track32)]))
    venv = envs.vmap_env(env, 1024)
    reset = jax.jit(venv.reset)

    @jax.jit
    def steps(key, state, params):
        def body(state, key):
            action = venv.sample_actions(key, params)
            obs, state, reward, terminated, truncated, info = venv.step(key, state, action, params)
            return state, (obs, reward, terminated, truncated, info)

        return jax.lax.scan(body, state, jax.random.split(key, 3))

    return env, params, venv, reset, steps


def test_jit_vmap_1024_envs_with_auto_reset(batched):
    _, params, _, reset, steps = batched
    obs, state = reset(jax.random.PRNGKey(1), params)
    assert obs["state"].shape == (1024, 6) and obs["trajectory_set"].shape == (1024, 25, 4)
    assert set(np.unique(np.asarray(state.track_index))) == {0, 1}
    state, (obs, reward, terminated, truncated, info) = steps(jax.random.PRNGKey(2), state, params)
    assert reward.shape == (3, 1024) and reward.dtype == jnp.float32
    assert info["final_obs"]["trajectory_set"].shape == (3, 1024, 25, 4)
    assert np.all(np.asarray(state.step_count) == 3)
    assert not np.asarray(terminated | truncated).any()
    np.testing.assert_array_equal(np.asarray(info["final_obs"]["state"]), np.asarray(obs["state"]))


def test_auto_reset_keeps_final_obs_and_restarts(batched):
    _, params, _, reset, steps = batched
    params = params.replace(max_steps=2)  # a traced leaf: same compiled function
    state, (obs, _, terminated, truncated, info) = steps(
        jax.random.PRNGKey(3), reset(jax.random.PRNGKey(2), params)[1], params
    )
    assert not np.asarray(truncated[0]).any() and np.asarray(truncated[1]).all()
    assert not np.asarray(terminated).any() and np.all(np.asarray(info["done_reason"][1]) == MAX_TIME)
    assert np.all(np.asarray(state.step_count) == 1)
    # On the ending step obs is the new episode's first observation (car at rest, a bank track's
    # precomputed reset view) and final_obs the ending one .
    np.testing.assert_array_equal(np.asarray(obs["state"][1]), 0.0)
    reset_views = np.asarray(params.reset_obs["trajectory_set"])
    got = np.asarray(obs["trajectory_set"][1])
    assert all(any(np.array_equal(g, r) for r in reset_views) for g in got[:16])
    ended = np.asarray(info["final_obs"]["trajectory_set"][1])
    assert np.mean(np.any(ended != got, axis=(-2, -1))) > 0.5  # most cars had moved off the start
    np.testing.assert_array_equal(np.asarray(info["final_obs"]["state"][0]), np.asarray(obs["state"][0]))


def test_same_key_same_trajectory_different_keys_different_tracks(batched):
    env, params, _, reset, steps = batched
    out_a = steps(jax.random.PRNGKey(7), reset(jax.random.PRNGKey(6), params)[1], params)
    out_b = steps(jax.random.PRNGKey(7), reset(jax.random.PRNGKey(6), params)[1], params)
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), out_a, out_b)
    indices = {int(env.reset(jax.random.PRNGKey(k), params)[1].track_index) for k in range(16)}
    assert indices == {0, 1}


def test_observations_stay_in_bounds_under_random_driving(batched, road):
    env, params, _, reset, steps = batched
    _, (obs, *_rest) = steps(jax.random.PRNGKey(11), reset(jax.random.PRNGKey(10), params)[1], params)
    space = env.observation_space(params)
    for key in ("state", "trajectory_set"):
        values = np.asarray(obs[key])
        assert np.all(np.abs(values) <= 1.0) and np.all(np.isfinite(values))
    np.testing.assert_allclose(
        np.asarray(obs["trajectory_set"])[0, 0, :, 1], 2 * np.arange(25) / 25 - 1, atol=1e-6
    )
    assert bool(space.contains(jax.tree.map(lambda x: x[0, 0], obs)))

    env, params = road
    rng = np.random.default_rng(0)
    actions = np.clip(rng.normal([0.0, 0.5, -0.8], 0.5, (120, 3)), -1, 1).astype(np.float32)
    obs0, _, out = run(road, actions)
    cones = np.concatenate([np.asarray(obs0["cones_set"])[None], out["obs"]["cones_set"]])
    present = cones[..., 0]
    assert np.all(np.isin(present, [0.0, 1.0]))
    assert np.all(np.diff(present, axis=-1) <= 0), "present rows must come first"
    assert np.all(cones[..., 3] + cones[..., 4] == present)
    assert np.all((cones[..., 1] > -1 / 3) & (cones[..., 1] < 1) | (present == 0))
    assert np.all((np.abs(cones[..., 2]) < 2 / 3) | (present == 0))
    assert np.all(cones[present == 0] == 0)
    assert np.all(np.abs(out["obs"]["state"]) <= 1.0)
    assert 20 <= present[0].sum() <= 60


def test_spaces_sample_and_contains(road):
    env, params = road
    key = jax.random.PRNGKey(0)
    action_space = env.action_space(params)
    action = action_space.sample(key)
    assert action.shape == (3,) and bool(action_space.contains(action))
    assert not bool(action_space.contains(jnp.array([0.0, 2.0, 0.0])))
    assert not bool(action_space.contains(jnp.array([0.0, jnp.nan, 0.0])))
    obs_space = env.observation_space(params)
    assert set(obs_space.spaces) == {"state", "cones_set"}
    assert bool(obs_space.contains(obs_space.sample(key)))
    discrete = envs.Discrete(12)
    assert bool(discrete.contains(discrete.sample(key))) and not bool(discrete.contains(jnp.int32(12)))


def test_make_rejects_unknown_names_and_overrides(track32):
    with pytest.raises(ValueError, match="valid names: country_road, country_road_discrete, tracking"):
        envs.make("moon")
    with pytest.raises(ValueError, match=r"unknown override\(s\) \['k_forward'\].*k_forwards"):
        envs.make("tracking", k_forward=1.0)
    with pytest.raises(ValueError, match="lookahead_points"):
        envs.make("country_road", lookahead_points=10)
    with pytest.raises(ValueError, match="track_source"):
        envs.make("tracking", track_source="moon", track=track32)
    with pytest.raises(ValueError, match="Track"):
        envs.make("tracking", track=np.zeros((10, 2)))
    env, params = envs.make("tracking_discrete", track=track32, lookahead_points=10, k_forwards=0.5)
    assert env.observation_space(params)["trajectory_set"].shape == (10, 4)
    assert params.k_forwards == 0.5 and env.discrete


def test_projection_is_global_and_agrees_with_the_reference():
    """Branch-and-bound projection == brute force over all segments == track_reference.project (float64),
    for points near the track (incl. off-track ones) and far away (where many chunks tie closely)."""
    with jax.enable_x64(True):
        track = golden_track(load("tracking"))
        view = ring_geometry.TrackView(
            ring_geometry.ring_tables(track), None, track.length, track.num_points, track.cone_type
        )
        rng = np.random.default_rng(0)
        anchors = np.asarray(track.centerline)[rng.integers(0, 320, 400)]
        near = anchors + rng.uniform(-6, 6, anchors.shape)
        vertices = anchors[:50] + 1e-3 * rng.normal(size=(50, 2))
        far = rng.uniform(-400, 400, (100, 2))
        points = jnp.asarray(np.concatenate([near, vertices, far, np.asarray(track.centerline)[:320:7]]))
        arcs = jnp.asarray(rng.uniform(-50, 600, 200))

        @jax.jit
        def compute(view, track, points, arcs):
            fast = jax.vmap(lambda p: ring_geometry.project_point(view, p[0], p[1]))(points)
            brute = jax.vmap(lambda p: track_reference.project_point_global(view, p[0], p[1]))(points)
            s_ref, d_ref = jax.vmap(lambda p: track_reference.project(track, p))(points)
            tangent_ref = jax.vmap(lambda s: track_reference.travel_tangent(track, s))(s_ref)
            ours = jnp.stack(ring_geometry.points_at_arclength(view, arcs), -1)
            theirs = track_reference.point_at_arclength(track, arcs)
            return fast, brute, (s_ref, d_ref, tangent_ref), ours, theirs

        fast, brute, reference, ours, theirs = jax.tree.map(np.asarray, compute(view, track, points, arcs))
    for a, b in zip(fast, brute, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    for a, b, tol in zip(fast, reference, (1e-9, 1e-9, 1e-12), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=tol)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-9)


def controller(obs, target_speed=8.0):
    """The hand-written driver of §8.3 (raw continuous action from the tracking observation)."""
    traj = obs["trajectory_set"]
    steer = jnp.clip(2.0 * jnp.arctan2(traj[4, 3], traj[4, 2]) / 0.52, -1.0, 1.0)
    target = jnp.where(
        jnp.abs(jnp.arctan2(traj[10, 3], traj[10, 2])) >= 0.2, 0.6 * target_speed, target_speed
    )
    speed = obs["state"][0] * 51.86737451785755
    throttle = jnp.where(speed < target, 1.0, -1.0)
    brake = jnp.where(speed > target + 2.0, 1.0, -1.0)
    return jnp.stack([steer, throttle, brake])


@pytest.mark.slow
def test_scripted_controller_return_matches_the_original_distribution():
    """§8.3: V = 8 m/s on 20 tracks gave mean return 36.5 (min 12.6, max 41.9), 18x MaxTime."""
    env, params = envs.make("tracking", track_bank_size=20, track_seed=0)
    singles = [racing.with_track(params, jax.tree.map(lambda x, i=i: x[i], params.tracks)) for i in range(20)]
    singles = [env.prepare(p) for p in singles]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *singles)
    axes = jax.tree.map(lambda _: 0, stacked).replace(vehicle=None)
    stacked = stacked.replace(vehicle=params.vehicle)

    @jax.jit
    def episodes(p):
        def one(p):
            obs, state = env.reset(jax.random.PRNGKey(0), p)

            def body(carry, _):
                obs, state, alive, total, length, reason = carry
                obs, state, reward, terminated, truncated, info = env.step(
                    jax.random.PRNGKey(0), state, controller(obs), p
                )
                total = total + jnp.where(alive, reward, 0.0)
                length = length + alive
                reason = jnp.where(alive & (terminated | truncated), info["done_reason"], reason)
                return (obs, state, alive & ~(terminated | truncated), total, length, reason), None

            init = (
                obs,
                state,
                jnp.array(True),
                jnp.zeros(()),
                jnp.zeros((), jnp.int32),
                jnp.zeros((), jnp.int32),
            )
            return jax.lax.scan(body, init, None, length=600)[0][3:]

        return jax.vmap(one, in_axes=(axes,))(p)

    total, length, reason = (np.asarray(x) for x in episodes(stacked))
    print(
        f"returns: mean {total.mean():.2f} std {total.std():.2f} min {total.min():.2f} max {total.max():.2f}"
    )
    endings = f"MaxTime {np.sum(reason == MAX_TIME)}, LeftTrack {np.sum(reason == LEFT_TRACK)}"
    print(f"length mean {length.mean():.1f}; {endings}")
    assert np.all(reason != 0)  # every episode ends within 600 steps
    assert 28.0 <= total.mean() <= 44.0
    assert np.sum(reason == MAX_TIME) >= 14


@pytest.mark.slow
def test_generate_mode_builds_a_fresh_track_per_reset():
    env, params = envs.make("country_road", track_source="generate")
    assert params.tracks is None
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    obs_a, state_a = reset(jax.random.PRNGKey(0), params)
    _, state_b = reset(jax.random.PRNGKey(1), params)
    assert float(state_a.track.length) != float(state_b.track.length)
    assert 20 <= float(obs_a["cones_set"][:, 0].sum()) <= 60
    _, state, reward, terminated, truncated, info = step(
        jax.random.PRNGKey(2), state_a, FULL_THROTTLE, params
    )
    assert int(state.step_count) == 1 and not bool(terminated | truncated)
    assert float(info["dist_center"]) < 0.5 and float(reward) >= 0.0


# ----------------------------------------------------------------------------------------------
# Conventions: default params, the reset cache, jit and eager agree
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", envs.ENV_NAMES)
def test_default_params_work_for_every_env(name):
    """gymnax's convention: ``env.reset(key)`` without params uses ``env.default_params``, which
    for the racing envs is ``envs.make``'s default (the cached default bank)."""
    env, params = envs.make(name)
    key = jax.random.PRNGKey(5)
    chex.assert_trees_all_equal(env.reset(key)[0], env.reset(key, params)[0])


def test_reset_cache_cannot_go_stale(tracking, track32):
    env, params = tracking
    assert params.reset_cache_for == env._config()
    assert params.replace(max_steps=5).reset_obs is not None  # rewards and endings: cache kept
    spaced = params.replace(lookahead_spacing=3.0)
    assert spaced.reset_obs is None and spaced.start_s is None
    fresh = env.prepare(spaced)
    first = jax.tree.map(lambda leaf: leaf[0], fresh.reset_obs)  # a one-track bank
    chex.assert_trees_all_close(env.reset(jax.random.PRNGKey(0), spaced)[0], first, atol=1e-6)
    # A cache built for another configuration of the same sensor is not used.
    short, _ = envs.make("tracking", track=track32, lookahead_points=10)
    obs, _ = short.reset(jax.random.PRNGKey(0), params)
    chex.assert_shape(obs["trajectory_set"], (10, 4))


class EagerAndJitAgree(chex.TestCase):
    """A reset and a few steps of Tracking on the golden track, jitted and not (chex variants)."""

    @chex.variants(with_jit=True, without_jit=True)
    def test_reset_and_step(self):
        env, params = envs.make("tracking", track=golden_track(load("country_road")))

        @self.variant
        def reset_and_step(key, action):
            obs, state = env.reset(key, params)
            return obs, env.step(key, state, action, params)

        obs, (obs1, _, reward, terminated, truncated, info) = reset_and_step(
            jax.random.PRNGKey(0), jnp.asarray([0.1, 0.5, -1.0])
        )
        chex.assert_trees_all_close(obs, jax.tree.map(lambda leaf: leaf[0], params.reset_obs))
        chex.assert_shape([obs1["state"], obs1["trajectory_set"]], [(6,), (25, 4)])
        chex.assert_rank([reward, terminated, truncated, info["done_reason"]], 0)
        assert not bool(terminated | truncated)


def test_the_scenario_table_describes_each_envs_observation(road, tracking):
    """xrl_jax.config.SCENARIOS is what the networks and readers use instead of asking the env: its
    set key, slot count, features and state size must be the env's own observation space's."""
    from xrl_jax.config import SCENARIOS

    intersection = envs.make("intersection")
    for name, (env, params) in {
        "country_road": road,
        "tracking": tracking,
        "intersection": intersection,
    }.items():
        facts, space = SCENARIOS[name], env.observation_space(params)
        assert set(space.spaces) == {"state", facts.set_key}, name
        assert space[facts.set_key].shape == (facts.num_objects, facts.object_features), name
        assert space["state"].shape == (facts.state_dim,), name
        assert facts.agent_slots == getattr(env, "num_agents", 1), name
