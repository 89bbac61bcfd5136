"""Vehicle model: docs/carenv-single-agent.md §2.7 reference values, golden replay (float64), special
cases, jit/vmap, float32."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.vehicle import (
    VehicleParams,
    VehicleState,
    body_velocity,
    odometry_observation,
    steering_actuator,
    tyre_force,
    vehicle_step,
    vehicle_step_with_diagnostics,
)

PARAMS = VehicleParams()
DATA = Path(__file__).parent / "data"
GOLDEN = DATA / "vehicle_public.npz"
# The episode recordings drive the same vehicle (cones do not act on it), so their states replay here too.
EPISODES = ["episode_tracking_public", "episode_country_road_public"]
# Positions, angles and speeds in SI; wheel speeds scaled by r_w so all columns are metres-like.
STATE_SCALE = np.array([1, 1, 1, 1, 1, 1, 0.3, 0.3, 1])


def _rollout(initial_vector, controls):
    """Scan ``vehicle_step_with_diagnostics``; returns per-step state vectors, diagnostics, observations."""

    def step(state, control):
        new_state, diag = vehicle_step_with_diagnostics(PARAMS, state, control)
        extras = (diag, odometry_observation(PARAMS, new_state), jnp.stack(body_velocity(new_state), -1))
        return new_state, (new_state.to_vector(), *extras)

    return jax.lax.scan(step, VehicleState.from_vector(initial_vector), controls)[1]


ROLLOUT_STEPS = 300  # every rollout is padded to this length, so the scan compiles once per dtype


@pytest.fixture(scope="module")
def rollout():
    jitted = jax.jit(_rollout)

    def run(v0, controls):
        steps = len(controls)
        assert steps <= ROLLOUT_STEPS
        padded = np.zeros((ROLLOUT_STEPS, 3))
        padded[:steps] = controls
        return jax.tree.map(lambda a: np.asarray(a)[:steps], jitted(v0, padded))

    return run


@pytest.fixture(scope="module")
def step():
    """Jitted single env step (any batch shape; compiled once per shape and dtype)."""
    return jax.jit(lambda state, control: vehicle_step(PARAMS, state, control))


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as data:
        return {key: data[key] for key in data.files}


def _constant_controls(control, steps):
    return np.tile(np.asarray(control, dtype=np.float64), (steps, 1))


def _initial(x=0.0, y=0.0, theta=0.0, speed=0.0, omega=None):
    omega = speed / 0.3 if omega is None else omega
    return np.array([x, y, theta, speed * math.cos(theta), speed * math.sin(theta), 0, omega, omega, 0])


def _check_rows(actual, expected_rows, columns, decimals):
    """Compare against a table printed with ``decimals`` digits (half a unit of the last digit)."""
    for step, expected in expected_rows.items():
        got = actual[step - 1, columns]
        np.testing.assert_allclose(got, expected, rtol=0, atol=0.51 * 10.0**-decimals, err_msg=f"step {step}")


# ---------------------------------------------------------------------------------------------------
# §2.7 reference values (float64)


def test_tv1_full_throttle_from_rest(rollout):
    with jax.enable_x64(True):
        states, diag, obs, _ = rollout(_initial(), _constant_controls([0, 1, 0], 300))
    _check_rows(
        states, {1: [0.021928, 0.459313], 2: [0.091372, 0.926541], 10: [2.305852, 4.605017]}, [0, 3], 6
    )
    _check_rows(states, {1: [7.23185, 0.01903], 2: [11.97146, 1.05778], 10: [50.98591, 14.41648]}, [6, 7], 5)
    np.testing.assert_allclose(
        obs[9], [0.08878446, 0, 0, 0, 0.26809236, 0.07580424], rtol=0, atol=1e-7, err_msg="obs after step 10"
    )
    # Longer straight run: v_x at 2, 3, 5, 10, 15, 20, 30 s, and x at 30 s.
    speeds = states[[19, 29, 49, 99, 149, 199, 299], 3]
    np.testing.assert_allclose(speeds, [9.14, 13.46, 20.59, 31.48, 37.85, 41.89, 46.27], rtol=0, atol=0.0051)
    assert abs(states[299, 0] - 1006.5) < 0.051
    assert np.all(states[:, [1, 2, 4, 5]] == 0.0), "driving straight must stay exactly straight"
    # The front wheels spin (slipping flag) until step 31 and not after.
    front_slipping = diag.slipping[:, 0]
    assert front_slipping[:31].all() and not front_slipping[31:].any()


def test_tv2_steering_delay_and_left_turn(rollout):
    with jax.enable_x64(True):
        states, _, obs, _ = rollout(_initial(10.0, -5.0, math.pi / 2, 15.0), _constant_controls([1, 0, 0], 5))
    expected_pose = {
        1: [10.000000, -3.501268, 1.570796, 0.000000, 14.974981, 0.000000],
        2: [9.979936, -2.006853, 1.589668, -0.388635, 14.914594, 0.326922],
        3: [9.910473, -0.521648, 1.637419, -0.994518, 14.786999, 0.582979],
        5: [9.557138, 2.386616, 1.779729, -2.524612, 14.242438, 0.789328],
    }
    expected_wheels = {
        1: [49.84948, 49.86068],
        2: [49.57946, 49.68188],
        3: [48.80307, 49.36549],
        5: [45.07943, 48.18192],
    }
    _check_rows(states, expected_pose, slice(0, 6), 6)
    _check_rows(states, expected_wheels, [6, 7], 5)
    np.testing.assert_allclose(states[:, 8], [0.1, 0.2, 0.3, 0.4, 0.5], rtol=0, atol=1e-12)
    assert abs(states[0, 5]) < 1e-12, "steering command must act only from the next step on"
    np.testing.assert_allclose(
        obs[4], [0.2787176, -0.00933913, 0.12568922, 0.96153843, 0.23703511, 0.25334856], rtol=0, atol=1e-7
    )


def test_tv3_full_brake_locks_wheels(rollout):
    with jax.enable_x64(True):
        states, diag, _, _ = rollout(_initial(speed=20.0), _constant_controls([0, 0, 1], 5))
    _check_rows(
        states, {1: [1.959382, 19.150548], 2: [3.823157, 18.169964], 3: [5.587960, 17.174635]}, [0, 3], 6
    )
    _check_rows(states, {5: [8.818676, 15.183534]}, [0, 3], 6)
    _check_rows(states, {1: [36.74940, 38.00436], 2: [14.65341, 16.50780]}, [6, 7], 5)
    # Locked wheels are EXACTLY zero (Coulomb lock writes zeros), and stay so.
    assert np.all(states[2:, 6:8] == 0.0)
    assert diag.slipping.all()
    assert diag.braking.all()


def test_tv4_throttle_and_right_turn(rollout):
    with jax.enable_x64(True):
        states, _, _, _ = rollout(_initial(speed=10.0), _constant_controls([-1, 0.5, 0], 5))
    expected = {
        1: [1.010674, 0.000000, 0.000000, 10.216664, 0.000000, 0.000000],
        3: [3.091061, -0.079111, -0.059011, 10.551020, -0.879782, -0.535294],
        5: [5.203066, -0.404178, -0.203587, 10.508970, -2.390757, -0.860795],
    }
    _check_rows(states, expected, slice(0, 6), 6)


def test_full_brake_from_top_run_stops_in_46_steps(rollout):
    """§2.7: from 46.3 m/s (end of the 30 s full-throttle run) full brake stops the car after 46 steps."""
    with jax.enable_x64(True):
        run_up, _, _, _ = rollout(_initial(), _constant_controls([0, 1, 0], 300))
        braking, _, _, _ = rollout(run_up[-1], _constant_controls([0, 0, 1], 60))
    stopped = np.all(braking[:, [3, 4, 5, 6, 7]] == 0.0, axis=1)
    assert stopped[45] and not stopped[44], "standstill must be reached exactly at step 46"
    assert stopped[45:].all(), "a stopped car under brake stays exactly at rest"
    assert abs((braking[45, 0] - run_up[-1, 0]) - 105.0) < 1.0
    assert np.all(braking[45:, 0] == braking[45, 0])


@pytest.mark.parametrize(
    ("c_sigma", "sigma", "w", "expected", "slipping"),
    [
        (10.0, 0.05, (10.0, 0.0), (1751.7857, 0.0), False),
        (10.0, -1.0, (10.0, 0.0), (-3659.8964, 0.0), True),
        (12.0, 0.0, (10.0, -1.0), (0.0, 3017.6401), False),
        (10.0, 0.1, (10.0, 0.5), (2562.6453, -1281.1945), False),
        (12.0, 0.01, (0.0, 0.0), (437.0792, 0.0), False),
    ],
)
def test_tyre_spot_values(c_sigma, sigma, w, expected, slipping):
    with jax.enable_x64(True):
        fx, fy, slip = tyre_force(c_sigma, c_sigma, sigma, w[0], w[1], 1.05, 3678.75)
        np.testing.assert_allclose([float(fx), float(fy)], expected, rtol=0, atol=5.1e-5)
        assert bool(slip) is slipping


def test_tyre_saturates_towards_mu_fz():
    """When saturated (lambda < 1) |F| = mu*F_z*(1 - lambda/2); the linear branch holds at lambda >= 1."""
    with jax.enable_x64(True):
        mu_fz = 1.05 * 3678.75
        sigma = jnp.linspace(-1.0, 1.0, 41)
        fx, fy, _ = tyre_force(10.0, 10.0, sigma, 10.0, 3.0, 1.05, 3678.75)
        magnitude = np.hypot(fx, fy)
        assert np.all(magnitude <= mu_fz + 1e-9)
        fx_small, _, slip_small = tyre_force(10.0, 10.0, 1e-4, 10.0, 0.0, 1.05, 3678.75)
        np.testing.assert_allclose(float(fx_small), 10.0 * 1e-4 / (1 + 1e-4) * 3678.75, rtol=1e-14)
        assert not bool(slip_small)


def test_steering_sequence():
    commands = [1, 1, 1, 1, 1, 1, 1, 0, 0, -0.5, -0.5, -0.5, -0.5, -0.5, 0.03]
    expected = [0.1, 0.2, 0.3, 0.4, 0.5, 0.52, 0.52, 0.42, 0.32, 0.22, 0.12, 0.02, -0.08, -0.18, -0.08]
    with jax.enable_x64(True):
        steer = jnp.float64(0.0)
        angles = []
        for command in commands:
            steer = steering_actuator(PARAMS, steer, command)
            angles.append(float(steer))
    np.testing.assert_allclose(angles, expected, rtol=0, atol=1e-12)
    # Reaching the target exactly (no overshoot, then no chatter).
    assert float(steering_actuator(PARAMS, 0.0, 0.1)) == pytest.approx(0.052)
    assert float(steering_actuator(PARAMS, 0.052, 0.1)) == pytest.approx(0.052)


# ---------------------------------------------------------------------------------------------------
# Golden replay


def _check_golden_run(golden, run, states, diag, obs, v_body):
    np.testing.assert_allclose(states, golden["state"][run, 1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(v_body, golden["v_body"][run, 1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(obs, golden["obs_state"][run, 1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(diag.slip_ratio, golden["slip_ratio"][run], rtol=0, atol=1e-6)
    np.testing.assert_allclose(diag.force_front_body, golden["force_front_body"][run], rtol=0, atol=1e-3)
    np.testing.assert_allclose(diag.force_rear_body, golden["force_rear_body"][run], rtol=0, atol=1e-3)
    np.testing.assert_array_equal(diag.slipping, golden["slipping"][run])
    np.testing.assert_array_equal(diag.braking, golden["braking"][run])


@pytest.mark.parametrize("run", [0, 1])
def test_golden_replay_float64(rollout, golden, run):
    assert int(golden["n_substeps"]) == PARAMS.physics_substeps and float(golden["dt"]) == PARAMS.dt
    assert golden["valid_steps"][run] == golden["controls"].shape[1]
    with jax.enable_x64(True):
        states, diag, obs, v_body = rollout(golden["initial_state"][run], golden["controls"][run])
    assert states.dtype == np.float64
    _check_golden_run(golden, run, states, diag, obs, v_body)
    # Far tighter than the tolerance: the port follows the original operation by operation.
    assert np.abs(states - golden["state"][run, 1:]).max() < 1e-9


def test_golden_runs_exercise_special_cases(golden):
    """Sanity on the data itself: the replay above covers wheel lock (exact zeros) and wheel spin."""
    locked = golden["state"][0, 1:, 6:8] == 0.0
    moving = np.hypot(golden["state"][0, 1:, 3], golden["state"][0, 1:, 4]) > 1.0
    assert (locked[:, 0] & moving).sum() == 12 and (locked[:, 1] & moving).sum() == 13


def _load_episode(name):
    path = DATA / f"{name}.npz"
    if not path.exists():
        pytest.skip(f"{path.name} not in tests/data")
    with np.load(path) as data:
        return {key: data[key] for key in ("controls", "state", "obs_state", "v_body", "slipping", "braking")}


@pytest.mark.parametrize("name", EPISODES)
def test_episode_vehicle_states_float64(rollout, name):
    episode = _load_episode(name)
    with jax.enable_x64(True):
        states, diag, obs, v_body = rollout(episode["state"][0], episode["controls"])
    np.testing.assert_allclose(states, episode["state"][1:], rtol=0, atol=1e-6)
    assert np.abs(states - episode["state"][1:]).max() < 1e-9
    np.testing.assert_allclose(v_body, episode["v_body"][1:], rtol=0, atol=1e-6)
    np.testing.assert_allclose(obs, episode["obs_state"][1:], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(diag.slipping, episode["slipping"])
    np.testing.assert_array_equal(diag.braking, episode["braking"])


@pytest.fixture(scope="module")
def rollout_float32():
    @jax.jit
    def run(initial, controls):
        def step(state, control):
            state = vehicle_step(PARAMS, state, control)
            return state, state.to_vector()

        return jax.lax.scan(step, VehicleState.from_vector(initial), controls)[1]

    return lambda v0, controls: np.asarray(
        run(jnp.asarray(v0, jnp.float32), jnp.asarray(controls, jnp.float32))
    )


@pytest.mark.parametrize("run", [0, 1])
def test_float32_stays_close_to_float64_on_golden_runs(golden, rollout_float32, run):
    """Default dtype: finite, float32, and within 1e-3 (m, rad, m/s, r_w*omega) of the recording."""
    states = rollout_float32(golden["initial_state"][run], golden["controls"][run])
    assert states.dtype == np.float32 and np.isfinite(states).all()
    deviation = np.abs(states - golden["state"][run, 1:]) * STATE_SCALE
    assert deviation.max() < 1e-3, f"max float32 deviation {deviation.max():.2e}"  # measured 2.9e-4


@pytest.mark.parametrize("name", EPISODES)
def test_float32_stays_close_to_float64_on_episodes(rollout_float32, name):
    """~8 m/s with rolling wheels: the wheel speeds are stiff here, so they get a looser bound."""
    episode = _load_episode(name)
    states = rollout_float32(episode["state"][0], episode["controls"])
    assert np.isfinite(states).all()
    deviation = np.abs(states - episode["state"][1:]) * STATE_SCALE
    assert deviation[:, :6].max() < 1e-3, f"{deviation[:, :6].max():.2e}"  # measured 4.5e-4
    assert deviation[:, 6:8].max() < 3e-3, f"{deviation[:, 6:8].max():.2e}"  # measured 1.1e-3


# ---------------------------------------------------------------------------------------------------
# Special cases


def test_no_input_from_rest_stays_exactly_at_rest(rollout):
    with jax.enable_x64(True):
        for control in ([0, 0, 0], [0, 0, 1], [0, 0, 0.3]):
            states, _, obs, _ = rollout(_initial(3.0, -2.0, 0.7), _constant_controls(control, 60))
            np.testing.assert_array_equal(states[:, :8], np.tile([3.0, -2.0, 0.7, 0, 0, 0, 0, 0], (60, 1)))
            assert np.all(obs == 0.0)


def test_steering_at_rest_moves_only_the_actuator(rollout):
    with jax.enable_x64(True):
        states, _, _, _ = rollout(_initial(), _constant_controls([1, 0, 0], 8))
    assert np.all(states[:, :8] == 0.0)
    np.testing.assert_allclose(states[:, 8], [0.1, 0.2, 0.3, 0.4, 0.5, 0.52, 0.52, 0.52], atol=1e-12)


def test_standstill_snap_zeroes_velocity_and_yaw_rate(step):
    """Slow car, stopped wheels, full brake: one step snaps v and r to exact zeros (§2.5 item 31)."""
    with jax.enable_x64(True):
        state = VehicleState.from_vector(jnp.array([1.0, 2.0, 0.3, 0.05, -0.03, 0.01, 0.0, 0.0, 0.0]))
        new = step(state, jnp.array([0.0, 0.0, 1.0]))
        assert float(new.vx) == 0.0 and float(new.vy) == 0.0 and float(new.yaw_rate) == 0.0
        assert float(new.omega_front) == 0.0 and float(new.omega_rear) == 0.0
        # Snapped in the first sub-step: the position only ever saw v = 0, while the heading took
        # one sub-step with the pre-snap yaw rate (|r'| < 0.05), as in the original's order.
        assert float(new.x) == 1.0 and float(new.y) == 2.0
        assert 0.0 < float(new.theta) - 0.3 < 0.005 * 0.05


def test_wheel_lock_with_brake_dominating(step):
    """A braked wheel that would reverse is held at exactly zero; a braked spinning wheel keeps turning."""
    with jax.enable_x64(True):
        slow_wheels = VehicleState.from_vector(jnp.array([0, 0, 0, 8.0, 0, 0, 1.0, 1.0, 0]))
        new = step(slow_wheels, jnp.array([0.0, 0.0, 1.0]))
        assert float(new.omega_front) == 0.0 and float(new.omega_rear) == 0.0
        assert 7.0 < float(new.vx) < 8.0
        # A weak brake does not dominate the tyre's reaction moment: both wheels are dragged up to speed.
        new = step(slow_wheels, jnp.array([0.0, 1.0, 0.2]))
        assert float(new.omega_front) > 20.0 and float(new.omega_rear) > 20.0


# ---------------------------------------------------------------------------------------------------
# API: shapes, dtypes, jit, vmap


def test_state_helpers():
    state = VehicleState.at_pose(1.0, 2.0, 0.5)
    np.testing.assert_array_equal(state.to_vector(), [1.0, 2.0, 0.5, 0, 0, 0, 0, 0, 0])
    assert state.x.dtype == jnp.float32
    vector = jnp.arange(18.0).reshape(2, 9)
    np.testing.assert_array_equal(VehicleState.from_vector(vector).to_vector(), vector)
    with pytest.raises(ValueError, match=r"\(\.\.\., 9\)"):
        VehicleState.from_vector(jnp.zeros(8))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        vehicle_step(PARAMS, state, jnp.zeros(2))
    with pytest.raises(ValueError, match="physics_substeps"):
        VehicleParams(physics_substeps=0)
    with jax.enable_x64(True):
        assert VehicleState.at_pose(0.0, 0.0, 0.0).x.dtype == jnp.float64
    u_x, u_y = body_velocity(VehicleState.from_vector(jnp.array([0, 0, math.pi / 2, 0, 3.0, 0, 0, 0, 0])))
    np.testing.assert_allclose([u_x, u_y], [3.0, 0.0], atol=1e-6)


def test_derived_constants():
    with jax.enable_x64(True):
        assert PARAMS.axle_load == pytest.approx(3678.75, rel=1e-15)
        assert PARAMS.rolling_moment == pytest.approx(16.554375, rel=1e-15)
        assert PARAMS.top_speed == pytest.approx(51.86737451785755, rel=1e-14)
        assert 1.1 * PARAMS.max_wheel_speed == pytest.approx(190.18037323214435, rel=1e-14)


def test_jit_vmap_batch_of_1024_matches_golden(golden):
    """1024 vehicles (the two golden runs, 512 copies each) stepped by vmap inside jit, in float64."""
    batch = 1024
    runs = np.arange(batch) % 2

    @jax.jit
    def batched(initial, controls):
        def step(state, control):
            state = jax.vmap(lambda s, c: vehicle_step(PARAMS, s, c))(state, control)
            return state, state.to_vector()

        return jax.lax.scan(step, VehicleState.from_vector(initial), jnp.swapaxes(controls, 0, 1))[1]

    with jax.enable_x64(True):
        states = np.asarray(batched(golden["initial_state"][runs], golden["controls"][runs]))
    assert states.shape == (200, batch, 9)
    for r in range(2):
        np.testing.assert_allclose(
            states[:, runs == r], np.broadcast_to(golden["state"][r, 1:, None], (200, 512, 9)), atol=1e-6
        )


def test_batched_fields_without_vmap_equal_vmap(step):
    """The step is elementwise: batched state fields work without vmap and agree with vmap."""
    rng = np.random.default_rng(0)
    vectors = np.zeros((64, 9), np.float32)
    vectors[:, :3] = rng.normal(size=(64, 3))
    vectors[:, 3:5] = [12.0, 0.5]
    vectors[:, 6:8] = 40.0
    controls = np.stack([rng.uniform(-1, 1, 64), np.full(64, 0.5), rng.uniform(0, 1, 64)], axis=1)
    states = VehicleState.from_vector(vectors)
    direct = step(states, controls)
    mapped = jax.jit(jax.vmap(step))(states, controls)
    np.testing.assert_allclose(direct.to_vector(), mapped.to_vector(), rtol=1e-6, atol=1e-5)
    assert direct.x.shape == (64,) and direct.x.dtype == jnp.float32


def test_params_are_traceable_pytree_leaves():
    """Params leaves can be traced (e.g. a vmapped sweep over friction); static fields stay static."""
    assert len(jax.tree.leaves(PARAMS)) == 21
    state = VehicleState.from_vector(jnp.array([0, 0, 0, 15.0, 0, 0, 50.0, 50.0, 0.3]))

    def lateral_speed(mu):
        params = PARAMS.replace(mu_front=mu, mu_rear=mu)
        return vehicle_step(params, state, jnp.array([1.0, 0.0, 0.0])).yaw_rate

    yaw = jax.jit(jax.vmap(lateral_speed))(jnp.array([0.3, 1.05]))
    assert yaw[0] < yaw[1], "less grip turns less"
