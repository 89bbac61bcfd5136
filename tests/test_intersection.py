"""Multi-agent Intersection env: docs/carenv-intersection.md §3-§8 rules and the §10 reference numbers."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import actions as actions_mod
from envs import intersection as ix
from envs import intersection_geometry as geo
from envs import intersection_rules as rules
from envs import intersection_traffic as traffic
from envs.core import VmapWrapper

PARAMS8 = ix.IntersectionParams(max_vehicles=8)
ENV = ix.IntersectionEnv()
COAST = np.tile([0.0, -1.0, -1.0], (8, 1)).astype(np.float32)  # no pedals, straight
THROTTLE = np.tile([0.0, 1.0, -1.0], (8, 1)).astype(np.float32)
BRAKE = np.tile([0.0, -1.0, 1.0], (8, 1)).astype(np.float32)
N_STRAIGHT = geo.route_index("N", "straight")  # N->S along x = -1.5, heading +pi/2
UP = math.pi / 2

# §10 reference values, per approach N, S, W, E.
SPAWN_POINTS = {0: (-1.5, -46.5, UP), 1: (1.5, 46.5, -UP), 2: (-46.5, 1.5, 0.0), 3: (46.5, -1.5, math.pi)}
SPAWN_AREAS = {
    0: (-2.5, -0.5, -50.0, -43.0),
    1: (0.5, 2.5, 43.0, 50.0),
    2: (-50.0, -43.0, 0.5, 2.5),
    3: (43.0, 50.0, -2.5, -0.5),
}


BATCH = 256  # every step in this file runs through ONE compiled vmap over 256 envs (compile once)


@pytest.fixture(scope="module")
def batched_step():
    venv = VmapWrapper(ENV, BATCH)
    return jax.jit(lambda key, state, action: venv.step(key, state, action, PARAMS8))


@pytest.fixture(scope="module")
def step(batched_step):
    """Single-env step with PARAMS8, run as env 0 of a batch of identical copies."""

    def single(key, state, action, params):
        assert params is PARAMS8, "tests share one compiled step"
        copies = jax.tree.map(lambda x: jnp.broadcast_to(x, (BATCH, *jnp.shape(x))), (state, action))
        out = batched_step(key, *copies)
        return jax.tree.map(lambda x: x[0], out)

    return single


@pytest.fixture(scope="module")
def resets():
    """6000 curriculum resets (one compile), as numpy."""
    keys = jax.random.split(jax.random.PRNGKey(1), 6000)
    out = jax.jit(jax.vmap(ENV.reset_env, in_axes=(0, None)))(keys, ix.IntersectionParams())
    return jax.tree.map(np.asarray, out)


def run_steps(batched_step, state, key, steps, keep=4):
    """``steps`` random-action steps of the shared batched step; per-step outputs of the first
    ``keep`` envs, stacked on a leading time axis (numpy)."""
    take = jax.jit(lambda tree: jax.tree.map(lambda x: x[:keep], tree))
    key_act, key_step = jax.random.split(key)
    actions = jax.random.uniform(key_act, (steps, BATCH, 8, 3), minval=-1.0, maxval=1.0)
    keys = jax.random.split(key_step, steps)
    kept = []
    for t in range(steps):
        obs, state, reward, terminated, truncated, info = batched_step(keys[t], state, actions[t])
        kept.append(take((obs, state, reward, terminated, truncated, info)))
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *kept)


@pytest.fixture(scope="module")
def episode(batched_step, resets):
    """The last 150 steps of an episode of 256 envs from curriculum resets, with the clock set to
    step 450 (the first 4 envs kept; the 598 -> 600 restart test covers the exact count)."""
    state = jax.tree.map(lambda x: jnp.asarray(x[:BATCH]), resets[1])
    state = state.replace(step=jnp.full(BATCH, 450, jnp.int32))
    return run_steps(batched_step, state, jax.random.PRNGKey(18), 150)


def place(poses, routes=N_STRAIGHT, speeds=0.0, params=PARAMS8, **kwargs):
    return ix.place_vehicles(params, poses, routes, speeds, **kwargs)


# ----------------------------------------------------------------------------------------------
# Reset, spawning, curriculum
# ----------------------------------------------------------------------------------------------


def test_reset_spawns_on_distinct_approaches_at_reference_points(resets):
    all_obs, all_state = resets
    for cap, expected in ((1, 1), (2, 2), (4, 4), (8, 4)):
        pick = np.flatnonzero(all_state.max_vehicles == cap)[:64]
        obs, state = jax.tree.map(lambda x, pick=pick: x[pick], (all_obs, all_state))
        alive = np.asarray(state.alive)
        assert np.all(alive.sum(1) == expected) and np.all(alive[:, :expected])
        route = np.asarray(state.route)[:, :expected]
        approach = route // 3
        assert all(len(set(row)) == expected for row in approach)  # distinct approaches
        x, y, theta = (np.asarray(getattr(state.vehicle, f))[:, :expected] for f in ("x", "y", "theta"))
        ref = np.array([[SPAWN_POINTS[a] for a in row] for row in approach])
        assert np.all(np.abs(x - ref[..., 0]) <= 0.2 + 1e-6) and np.all(np.abs(y - ref[..., 1]) <= 0.2 + 1e-6)
        np.testing.assert_allclose(np.cos(theta), np.cos(ref[..., 2]), atol=1e-6)
        np.testing.assert_allclose(np.sin(theta), np.sin(ref[..., 2]), atol=1e-6)
        # Collision box inside the approach's spawn area (§2.3), seq = slot, timers set for spawners used.
        hl, hw = 1.905, 0.74
        ext_x = hl * np.abs(np.cos(theta)) + hw * np.abs(np.sin(theta))
        ext_y = hl * np.abs(np.sin(theta)) + hw * np.abs(np.cos(theta))
        box = np.array([[SPAWN_AREAS[a] for a in row] for row in approach])
        assert np.all(x - ext_x >= box[..., 0] - 1e-5) and np.all(x + ext_x <= box[..., 1] + 1e-5)
        assert np.all(y - ext_y >= box[..., 2] - 1e-5) and np.all(y + ext_y <= box[..., 3] + 1e-5)
        assert np.all(np.asarray(state.spawn_seq)[:, :expected] == np.arange(expected)[None])
        spawner_set = np.asarray(state.spawner_set)
        assert np.all(spawner_set.sum(1) == expected)
        # Speed init (§3.3): body velocity (v0, 0), axle speeds v0 / 0.3; odometry of §7.3.
        vx, vy = np.asarray(state.vehicle.vx)[:, :expected], np.asarray(state.vehicle.vy)[:, :expected]
        v0 = np.hypot(vx, vy)
        assert np.all((v0 >= 5.55 - 1e-5) & (v0 <= 8.33 + 1e-5))
        np.testing.assert_allclose(np.asarray(state.vehicle.omega_rear)[:, :expected], v0 / 0.3, rtol=1e-6)
        odo = np.asarray(obs["state"])[:, :expected, :6]
        np.testing.assert_allclose(odo[..., 0], v0 / 51.86737451785755, rtol=1e-5)
        np.testing.assert_allclose(odo[..., 1:4], 0.0, atol=1e-6)
        np.testing.assert_allclose(odo[..., 4], (v0 / 0.3) / 190.18037323214438, rtol=1e-5)
        assert np.all(np.asarray(obs["state"])[:, expected:] == 0)
        assert np.all(np.asarray(obs["vehicles_set"]) == 0)  # approaches are > 30 m apart


def test_curriculum_probabilities_are_one_over_n(resets):
    _, state = resets
    count = state.max_vehicles.shape[0]
    caps = np.asarray(state.max_vehicles)
    expected = np.array([0.533333, 0.266667, 0.133333, 0.066667])
    np.testing.assert_allclose(ix.CURRICULUM_PROBS, expected, atol=1e-6)
    freq = np.array([np.mean(caps == n) for n in (1, 2, 4, 8)])
    assert np.isclose(freq.sum(), 1.0)
    sigma = np.sqrt(expected * (1 - expected) / count)
    assert np.all(np.abs(freq - expected) < 4.5 * sigma), freq


def test_first_respawn_at_step_15(step):
    _, state = ENV.reset_env(jax.random.PRNGKey(2), PARAMS8)
    key = jax.random.PRNGKey(3)
    for k in range(1, 16):
        key, sub = jax.random.split(key)
        _, state, reward, terminated, _, info = step(sub, state, THROTTLE, PARAMS8)
        alive = np.asarray(info["alive"])
        if k < 15:
            assert alive.sum() == 4, k
        else:
            assert alive.sum() == 8
            np.testing.assert_array_equal(np.asarray(state.spawn_seq)[4:], [4, 5, 6, 7])
            assert not np.any(np.asarray(info["acted"])[4:])
            assert np.all(np.asarray(reward)[4:] == 0) and not np.any(np.asarray(terminated))
            spawn_time = np.asarray(state.spawner_last)
            assert np.all(np.abs(spawn_time - 1.5) < 1.5)  # t + N(0, 0.2)


def test_spawn_area_blocking_counts_terminating_agents(step):
    # Slot 0 parked in the N spawn area; slot 1 across the W lane, off-road (terminates this step).
    state = place(
        [(-1.5, -46.5, UP), (-46.5, 2.5, UP)], [N_STRAIGHT, geo.route_index("W", "straight")], max_vehicles=8
    )
    _, state, reward, terminated, _, info = step(jax.random.PRNGKey(4), state, BRAKE, PARAMS8)
    assert bool(terminated[1]) and int(info["done_reason"][1]) == ix.LEFT_ROAD and float(reward[1]) == -1.0
    alive = np.asarray(info["alive"])
    np.testing.assert_array_equal(alive, [True, False, True, True, False, False, False, False])
    approaches = sorted(int(r) // 3 for r in np.asarray(state.route)[2:4])
    assert approaches == [1, 3]  # only S and E were free
    # Removal timing: the freed slot 1 was not reused in the same step, the next step reuses it.
    _, state, *_, info = step(jax.random.PRNGKey(5), state, BRAKE, PARAMS8)
    assert bool(info["alive"][1]) and int(state.route[1]) // 3 == 2  # W is free again


def test_stale_spawn_timers_flag():
    results = {}
    for stale in (True, False):
        params = ix.IntersectionParams(max_vehicles=2, stale_spawn_timers=stale)
        restart = ENV.restart if stale else jax.jit(ENV.restart)  # eager: one compile fewer
        state = place([(-1.5, -20.0, UP)], speeds=7.0, params=params, step=600, max_vehicles=2)
        state = state.replace(spawner_last=jnp.full(4, 59.5), spawner_set=jnp.ones(4, bool))
        _, state = restart(jax.random.PRNGKey(6), state, params)
        assert int(state.step) == 0
        fresh = np.asarray(state.spawner_set)
        last = np.asarray(state.spawner_last)
        spawned_now = np.zeros(4, bool)
        spawned_now[np.asarray(state.route)[np.asarray(state.alive)] // 3] = True
        assert spawned_now.sum() == 2
        np.testing.assert_array_equal(last[spawned_now], 0.0)
        if stale:
            assert np.all(fresh) and np.all(last[~spawned_now] == 59.5)
        else:
            assert not np.any(fresh[~spawned_now])
        # Behaviour: with room for 2 more, only spawners without a timer may spawn at t = 0.1.
        roomy = state.replace(max_vehicles=jnp.int32(4))
        _, new = traffic.spawn_vehicles(jax.random.PRNGKey(7), params, roomy, roomy.alive, 0.1)
        results[stale] = int(np.sum(new))
    assert results == {True: 0, False: 2}


# ----------------------------------------------------------------------------------------------
# Reward terms
# ----------------------------------------------------------------------------------------------


def test_tracking_reward_reference_examples():
    route = jnp.asarray(N_STRAIGHT)
    for lateral, expected in ((0.0, 0.035), (0.5, 0.02975)):
        prev = jnp.array([-1.5 + lateral, -20.0])
        prev_s = -20.0 + 51.5
        reward, _, moved, goal = rules.route_tracker(
            PARAMS8, route, prev, prev_s, prev + jnp.array([0.0, 0.7])
        )
        np.testing.assert_allclose(float(reward), expected, atol=2e-6)
        np.testing.assert_allclose(float(moved), 0.7, atol=1e-6)
        assert not bool(goal)
    # Goal thresholds of §10.
    for kind, threshold in (("straight", 98.0), ("right", 93.05376199450839), ("left", 99.05376199450839)):
        r = geo.route_index("S", kind)
        tail = geo.ROUTE_XY[r][-1]
        _, _, _, goal = rules.route_tracker(
            PARAMS8, jnp.asarray(r), jnp.asarray(tail), 0.0, jnp.asarray(tail)
        )
        assert bool(goal)
        np.testing.assert_allclose(float(geo.ROUTE_LENGTH[r]) - 5.0, threshold, atol=1e-9)


def test_step_reward_is_tracker_minus_slip(step):
    state = place([(-1.5, -20.0, UP)], speeds=7.0)
    _, new, reward, terminated, truncated, info = step(jax.random.PRNGKey(8), state, COAST, PARAMS8)
    xy = jnp.stack([new.vehicle.x, new.vehicle.y], -1)
    track, *_ = rules.route_tracker(PARAMS8, state.route, state.prev_xy, state.prev_s, xy)
    slip = rules.slip_penalty(PARAMS8, new.vehicle)
    np.testing.assert_allclose(float(reward[0]), float(track[0] - 0.1 * slip[0]), atol=1e-6)
    assert 0.03 < float(reward[0]) < 0.036 and not bool(terminated[0]) and not bool(truncated[0])
    moved = float(jnp.hypot(new.vehicle.x[0] + 1.5, new.vehicle.y[0] + 20.0))
    np.testing.assert_allclose(float(info["mean_velocity"]), moved / 0.1, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(info["acted"]), [True] + [False] * 7)


def test_slip_penalty_closed_form():
    vehicle = place([(0.0, 0.0, 0.0)] * 3, speeds=0.0).vehicle
    # Body velocities: forward only; sideways slip of 14 deg at the rear axle; reversing.
    vx = jnp.array([5.0, 5.0, -5.0] + [0.0] * 5)
    vy = jnp.array([0.0, 5.0 * math.tan(math.radians(14.0)), 0.0] + [0.0] * 5)
    penalty = rules.slip_penalty(PARAMS8, vehicle.replace(vx=vx, vy=vy))
    np.testing.assert_allclose(np.asarray(penalty)[:3], [0.0, 0.5, 1.0], atol=1e-5)


def test_goal_sets_plus_one(step):
    state = place([(-1.5, 46.4, UP)], speeds=7.0)  # s = 97.9, goal at s > 98
    _, _, reward, terminated, _, info = step(jax.random.PRNGKey(9), state, COAST, PARAMS8)
    assert (
        float(reward[0]) == 1.0 and bool(terminated[0]) and int(info["done_reason"][0]) == ix.COMPLETED_ROUTE
    )
    assert int(info["trips_completed"]) == 1 and not bool(info["alive"][0])


def test_off_road_overrides_goal(step):
    state = place([(3.5, 46.4, UP)], speeds=7.0)  # projection on N->S past the goal, box beyond x = 4
    _, _, reward, terminated, _, info = step(jax.random.PRNGKey(10), state, COAST, PARAMS8)
    assert float(reward[0]) == -1.0 and bool(terminated[0]) and int(info["done_reason"][0]) == ix.LEFT_ROAD
    assert int(info["trips_completed"]) == 1 and int(info["come_off_vehicles"]) == 1


def test_collision_stationary_zero_moving_minus_one_and_removal_timing(step):
    # Slot 0 stands (braking), slot 1 runs into it from behind, slot 2 watches from 10 m behind slot 1.
    state = place([(-1.5, -20.0, UP), (-1.5, -23.0, UP), (-1.5, -33.0, UP)], speeds=[0.0, 7.0, 7.0])
    action = np.concatenate([BRAKE[:1], COAST[1:]])
    _, state, reward, terminated, _, info = step(jax.random.PRNGKey(11), state, action, PARAMS8)
    np.testing.assert_allclose(np.asarray(reward)[:2], [0.0, -1.0])
    np.testing.assert_array_equal(np.asarray(terminated)[:3], [True, True, False])
    np.testing.assert_array_equal(np.asarray(info["done_reason"])[:3], [ix.COLLIDED, ix.COLLIDED, 0])
    assert int(info["collided_vehicles"]) == 2
    # The terminating cars are still in this step's observations (ahead of slot 2, agent order).
    seen = np.asarray(info["final_obs"]["vehicles_set"])[2]
    assert seen[:2, 0].tolist() == [1.0, 1.0] and seen[2, 0] == 0.0
    np.testing.assert_allclose(seen[:2, 1] * 30, [13.0, 10.0], atol=1.5)
    assert np.asarray(info["final_obs"]["state"])[0].any()  # final observation of a terminating car
    np.testing.assert_array_equal(np.asarray(info["alive"])[:3], [False, False, True])
    _, state, reward, terminated, _, info = step(jax.random.PRNGKey(12), state, COAST, PARAMS8)
    seen = np.asarray(info["final_obs"]["vehicles_set"])[2]
    assert not np.any((seen[:, 0] == 1) & (seen[:, 1] > 0))  # gone next step (only a new car behind)
    assert not np.any(np.asarray(info["acted"])[:2]) and np.all(np.asarray(reward)[:2] == 0)


def test_soft_collision_penalty(step):
    # Side by side, 0.3 m apart: soft rectangles (0.25 m pads) overlap, hard ones do not.
    state = place([(-1.5, -20.0, UP), (-1.5 + 1.48 + 0.3, -20.0, UP)], speeds=7.0)
    _, new, reward, terminated, *_ = step(jax.random.PRNGKey(13), state, COAST, PARAMS8)
    assert not np.any(np.asarray(terminated))
    xy = jnp.stack([new.vehicle.x, new.vehicle.y], -1)
    track, *_ = rules.route_tracker(PARAMS8, state.route, state.prev_xy, state.prev_s, xy)
    plain = track - 0.1 * rules.slip_penalty(PARAMS8, new.vehicle)
    np.testing.assert_allclose(np.asarray(reward)[:2], np.asarray(plain)[:2] - 0.05, atol=1e-6)
    # Without soft collisions the pair costs nothing; the hard test alone decides.
    poses = rules.vehicle_poses(new.vehicle)
    speed = jnp.full(8, 7.0)
    for soft, expected in ((True, -0.05), (False, 0.0)):
        params = ix.IntersectionParams(soft_collisions=soft)
        out, hit, pairs = rules.collision_rewards(
            params, poses, speed, new.alive, new.spawn_seq, jnp.zeros(8)
        )
        np.testing.assert_allclose(np.asarray(out)[:2], expected, atol=1e-7)
        assert not np.any(np.asarray(hit)) and int(pairs) == 0


@pytest.mark.parametrize(
    "seq, expected_hard",
    [
        ((0, 1, 2), (-1.05, -1.05)),  # the soft partner (seq 2) comes after the hard one: -0.05 added
        ((1, 2, 0), (-1.0, -1.0)),
    ],  # the soft partner (seq 0) comes first: the hard "set" wipes it
)
def test_soft_penalty_after_last_hard_partner(step, seq, expected_hard):
    # Slots 0 and 1 overlap (hard), slot 2 runs beside both (soft only).
    poses = [(-1.5, -20.0, UP), (-1.5, -17.0, UP), (-1.5 + 1.48 + 0.3, -18.5, UP)]
    state = place(poses, speeds=7.0, spawn_seq=seq)
    _, _, reward, terminated, _, info = step(jax.random.PRNGKey(14), state, COAST, PARAMS8)
    np.testing.assert_allclose(np.asarray(reward)[:2], expected_hard, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(terminated)[:3], [True, True, False])
    free = state.replace(alive=jnp.arange(8) == 2)
    _, _, alone, *_ = step(jax.random.PRNGKey(14), free, COAST, PARAMS8)
    np.testing.assert_allclose(float(reward[2]), float(alone[2]) - 0.10, atol=1e-6)
    assert int(info["collided_vehicles"]) == 2


# ----------------------------------------------------------------------------------------------
# Observations
# ----------------------------------------------------------------------------------------------


def test_vehicles_set_reference_row_and_velocity_frame_flag():
    expected = {
        True: [1, 0.333333, 0, 0, -0.067480, 1, 0],
        False: [1, 0.333333, 0, 0.067480, 0, 1, 0],
    }
    for bug, row in expected.items():
        params = ix.IntersectionParams(max_vehicles=8, body_velocity_frame_bug=bug)
        state = place([(-1.5, -20.0, UP), (-1.5, -10.0, UP)], speeds=[0.0, 7.0], params=params)
        obs = ix.observe(params, state)
        ego = np.asarray(obs["vehicles_set"])[0]
        np.testing.assert_allclose(ego[0], row, atol=2e-6)
        assert np.all(ego[1:] == 0)
        assert obs["vehicles_set"].dtype == jnp.float32 and obs["state"].dtype == jnp.float32


def test_vehicles_set_box_is_strict_and_rows_follow_agent_order():
    # Ego in slot 3; others at 29.9 m (kept), exactly 30 m (dropped), 5 m behind; seq order differs.
    poses = [(-1.5, 9.9, UP), (-1.5, 10.0, UP), (-1.5, -25.0, UP), (-1.5, -20.0, UP)]
    state = place(poses, spawn_seq=(5, 1, 0, 2))
    obs = np.asarray(ix.observe(PARAMS8, state)["vehicles_set"])[3]
    np.testing.assert_allclose(obs[:, 0], [1, 1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(obs[0, 1:3] * 30, [-5.0, 0.0], atol=1e-4)  # seq 0 first
    np.testing.assert_allclose(obs[1, 1:3] * 30, [29.9, 0.0], atol=1e-4)  # then seq 5


def test_navigation_points():
    state = place([(-1.5, -20.5, UP)])  # on N->S, 0.5 m ... offset 0
    obs = np.asarray(ix.observe(PARAMS8, state)["state"])[0]
    nav = obs[6:].reshape(30, 2) * 42.42640687119285
    np.testing.assert_allclose(nav[:, 0], np.arange(30), atol=1e-4)
    np.testing.assert_allclose(nav[:, 1], 0.0, atol=1e-4)
    # Clamped at the route end: a car 10 m before the end sees 10 distinct points, then repeats.
    state = place([(-1.5, 41.5, UP)])
    nav = np.asarray(ix.observe(PARAMS8, state)["state"])[0, 6:].reshape(30, 2) * 42.42640687119285
    np.testing.assert_allclose(nav[10:, 0], 10.0, atol=1e-4)


# ----------------------------------------------------------------------------------------------
# Episodes, restart, determinism, batching
# ----------------------------------------------------------------------------------------------


def test_restart_after_episode_steps_with_truncation(step):
    state = place([(-1.5, -20.0, UP), (-1.5, 45.7, UP)], speeds=7.0, step=598)
    _, state, _, _, truncated, info = step(jax.random.PRNGKey(15), state, COAST, PARAMS8)
    assert not bool(info["episode_end"]) and not np.any(np.asarray(truncated))
    obs, new, reward, terminated, truncated, info = step(jax.random.PRNGKey(16), state, COAST, PARAMS8)
    assert bool(info["episode_end"]) and int(info["episode_step"]) == 600 and int(new.step) == 0
    # Slot 0 survives the time limit (truncated), slot 1 reached its goal in the last step (terminated).
    np.testing.assert_array_equal(np.asarray(truncated)[:2], [True, False])
    np.testing.assert_array_equal(np.asarray(terminated)[:2], [False, True])
    assert float(reward[1]) == 1.0 and int(info["trips_completed"]) == 1 and int(new.trips_completed) == 0
    # final_obs: the ending step's observations; obs/state/alive: the new episode's (4 fresh cars).
    final = np.asarray(info["final_obs"]["state"])
    assert final[0, 0] > 0.1 and np.all(final[2:] == 0)
    np.testing.assert_array_equal(np.asarray(info["alive"]), np.asarray(new.alive))
    assert int(np.sum(new.alive)) == 4 and int(new.next_seq) == 4
    reference = ix.observe(PARAMS8, new)
    np.testing.assert_allclose(np.asarray(obs["state"]), np.asarray(reference["state"]), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(obs["vehicles_set"]), np.asarray(reference["vehicles_set"]))


def test_episode_end_random_actions(episode):
    obs, states, reward, terminated, truncated, info = episode
    end = np.asarray(info["episode_end"])
    assert np.all(end.sum(0) == 1) and np.all(end[-1])  # (time, env)
    assert np.asarray(truncated)[:-1].sum() == 0
    np.testing.assert_array_equal(
        np.asarray(truncated)[-1], np.asarray(info["acted"])[-1] & ~np.asarray(terminated)[-1]
    )
    for tree in (obs, info["final_obs"]):
        for value in jax.tree.leaves(tree):
            value = np.asarray(value)
            assert np.all(np.isfinite(value)) and np.all(np.abs(value) <= 1.0)
    alive, acted = np.asarray(info["alive"]), np.asarray(info["acted"])
    vs = np.asarray(info["final_obs"]["vehicles_set"])
    absent = ~(alive | acted)[:-1]  # neither acting, terminating nor new (the last step restarts)
    assert np.all(vs[:-1][absent] == 0) and np.all(np.asarray(info["final_obs"]["state"])[:-1][absent] == 0)
    assert np.all(np.asarray(obs["state"])[-1][~alive[-1]] == 0)  # the new episode's observations
    np.testing.assert_array_equal(np.asarray(obs["state"])[:-1], np.asarray(info["final_obs"]["state"])[:-1])
    present = vs[..., 0]
    assert np.all(np.diff(present, axis=-1) <= 0)  # rows contiguous from row 0
    now = (alive | acted)[:-1]
    assert np.all(present[:-1].sum(-1) <= np.maximum(now.sum(-1, keepdims=True) - 1, 0))
    assert np.all(np.asarray(reward)[~np.asarray(info["acted"])] == 0)
    assert np.all(np.asarray(info["episode_step"]) == np.arange(451, 601)[:, None])
    # Alive count never exceeds the cap; collided vehicles come in pairs.
    assert np.all(alive.sum(-1)[:-1] <= np.asarray(states.max_vehicles)[:-1])
    assert np.all(np.asarray(info["collided_vehicles"]) % 2 == 0)


def test_determinism_under_fixed_key(batched_step, resets):
    state = jax.tree.map(lambda x: jnp.asarray(x[:BATCH]), resets[1])
    a = run_steps(batched_step, state, jax.random.PRNGKey(20), 20)
    b = run_steps(batched_step, state, jax.random.PRNGKey(20), 20)
    c = run_steps(batched_step, state, jax.random.PRNGKey(21), 20)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[1].vehicle.x, c[1].vehicle.x)


def test_vmap_over_256_envs(batched_step, resets):
    _, state = resets
    state = jax.tree.map(lambda x: jnp.asarray(x[:BATCH]), state)  # curriculum-drawn caps
    key = jax.random.PRNGKey(22)
    for _ in range(3):
        key, key_act, key_step = jax.random.split(key, 3)
        action = jax.vmap(ENV.sample_actions, (0, None))(jax.random.split(key_act, BATCH), PARAMS8)
        obs, state, reward, _, _, info = batched_step(key_step, state, action)
    assert obs["vehicles_set"].shape == (BATCH, 8, 8, 7) and obs["state"].shape == (BATCH, 8, 66)
    assert (
        reward.shape == (BATCH, 8) and state.alive.shape == (BATCH, 8) and info["acted"].shape == (BATCH, 8)
    )
    assert np.all(np.isfinite(np.asarray(reward))) and np.all(np.abs(np.asarray(obs["state"])) <= 1)
    caps = np.asarray(state.max_vehicles)
    assert len(set(caps.tolist())) == 4 and np.all(np.asarray(state.alive).sum(1) <= caps)


def test_discrete_variant_registry_and_input_checks():
    env, params = envs.make("intersection_discrete", max_vehicles=2)
    assert isinstance(env, ix.IntersectionEnv) and env.discrete and params.max_vehicles == 2
    assert env.action_space(params).n == 12 and ENV.action_space(params).shape == (3,)
    assert env.observation_space(params)["state"].shape == (66,)
    assert env.observation_space(params)["vehicles_set"].shape == (8, 7)
    index = jnp.arange(8, dtype=jnp.int32) + 4
    alive = jnp.arange(8) < 6
    control = np.asarray(env._control(index, alive))
    table = np.asarray(actions_mod.continuous_to_control(actions_mod.DISCRETE_ACTIONS))
    np.testing.assert_array_equal(control[:6], table[4:10])
    state = place([(-1.5, -20.0, UP)])
    with pytest.raises(ValueError, match="shape"):
        env.step(jax.random.PRNGKey(0), state, jnp.zeros((8, 3)), params)
    with pytest.raises(ValueError, match="shape"):
        ENV.step(jax.random.PRNGKey(0), state, jnp.zeros(8), params)
    with pytest.raises(ValueError, match="unknown override"):
        envs.make("intersection", track_width=3.0)
    with pytest.raises(ValueError, match="max_vehicles"):
        ix.IntersectionParams(max_vehicles=9)
    assert "intersection" in envs.ENV_NAMES and "intersection_discrete" in envs.ENV_NAMES


@pytest.mark.slow
def test_discrete_step_matches_continuous_table():
    env, params = envs.make("intersection_discrete", max_vehicles=8)
    state = place([(-1.5, -20.0, UP), (-20.0, -1.5, math.pi)], speeds=7.0)
    index = jnp.array([11, 6, 0, 0, 0, 0, 0, 0], jnp.int32)
    out_d = jax.jit(env.step)(jax.random.PRNGKey(1), state, index, params)
    action = jnp.asarray(actions_mod.DISCRETE_ACTIONS)[index]
    out_c = jax.jit(ENV.step)(jax.random.PRNGKey(1), state, action, params)
    for x, y in zip(jax.tree.leaves(out_d), jax.tree.leaves(out_c), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_route_points_match_geometry():
    route = jnp.arange(12, dtype=jnp.int32)
    s = jnp.linspace(-3.0, 110.0, 57)[None, :] + jnp.zeros((12, 1))
    ours = np.asarray(rules.route_points(route, s))
    for r in range(12):
        ref = np.asarray(
            geo.route_point_at(
                jnp.asarray(geo.ROUTE_XY[r], jnp.float32), jnp.asarray(geo.ROUTE_CUMLEN[r], jnp.float32), s[r]
            )
        )
        np.testing.assert_allclose(ours[r], ref, atol=2e-4)


def test_render_frames():
    from envs.render import render_intersection_episode, render_intersection_state

    state = place([(-1.5, -20.0, UP), (-1.5, -12.0, UP), (-20.0, -1.5, math.pi)], speeds=7.0)
    top = render_intersection_state(state, PARAMS8, width=160, height=120)
    ego = render_intersection_state(state, PARAMS8, ego_slot=1, width=160, height=120)
    for frame in (top, ego):
        assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
        assert frame.reshape(-1, 3).std(axis=0).max() > 5  # not blank
    assert not np.array_equal(top, ego)
    stacked = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    frames = render_intersection_episode(stacked, PARAMS8, ego_slot=0, width=64, height=48)
    assert len(frames) == 2 and frames[0].shape == (48, 64, 3)
