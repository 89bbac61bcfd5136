"""The hand controller of docs/carenv-single-agent.md §8.3 (envs.hand_controller): on Tracking it
acts as §8.3's observation-based definition does; it drives Country Road exactly as Tracking
(same tracks, same physics; only the cone penalties differ); its CLI and one-line errors."""

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from train_support import call, load_script, one_line_error, production_compile_environ

import envs
from envs import hand_controller
from envs.vehicle import body_velocity

controller_cli = load_script("controller", "controller_cli")
ROOT = Path(__file__).resolve().parents[1]

SPEED_SCALE = 51.86737451785755  # the odometry observation's velocity normaliser (top speed, m/s)


def documented_action(obs, target_speed):
    """§8.3 as written, from the Tracking observation: lookahead rows 4 and 10, de-normalised speed."""
    traj = obs["trajectory_set"]
    steer = jnp.clip(2.0 * jnp.arctan2(traj[4, 3], traj[4, 2]) / 0.52, -1.0, 1.0)
    curve = jnp.arctan2(traj[10, 3], traj[10, 2])
    target = jnp.where(jnp.abs(curve) >= 0.2, 0.6 * target_speed, target_speed)
    speed = obs["state"][0] * SPEED_SCALE
    throttle = jnp.where(speed < target, 1.0, -1.0)
    brake = jnp.where(speed > target + 2.0, 1.0, -1.0)
    return jnp.stack([steer, throttle, brake]), speed, curve, target


def test_on_tracking_the_state_reading_equals_the_documented_observation_reading():
    env, params = envs.make("tracking", track_bank_size=2, track_seed=3)
    speed = 10.0

    @jax.jit
    def rollout(key):
        obs, state = env.reset(key, params)

        def body(carry, _):
            obs, state = carry
            ours = hand_controller.centre_line_action(env, state, params, speed)
            theirs, obs_speed, curve, target = documented_action(obs, speed)
            true_speed = body_velocity(state.vehicle)[0]
            obs, state, *_ = env.step(key, state, ours, params)  # auto-resets: several episodes
            return (obs, state), (ours, theirs, true_speed, obs_speed, curve, target)

        return jax.lax.scan(body, (obs, state), None, length=400)[1]

    ours, theirs, true_speed, obs_speed, curve, target = jax.tree.map(
        np.asarray, rollout(jax.random.PRNGKey(0))
    )
    # Steering: both are atan2 of the same body-frame point, the observation's divided by its scale
    # and rounded to float32 (relative error ~1e-7 of an angle below π), times the gain 2/0.52 ≈ 3.8.
    np.testing.assert_allclose(ours[:, 0], theirs[:, 0], rtol=0, atol=1e-5)
    # Pedals: equal wherever neither reading sits on a threshold within the observation's float32
    # rounding of the speed (top speed × 2⁻²⁴ ≈ 3e-6 m/s) or of the bend angle.
    assert np.all(np.abs(true_speed - obs_speed) < 1e-4)
    clear = (
        (np.abs(true_speed - target) > 1e-3)
        & (np.abs(true_speed - target - 2.0) > 1e-3)
        & (np.abs(np.abs(curve) - 0.2) > 1e-4)
    )
    assert clear.mean() > 0.95
    np.testing.assert_array_equal(ours[clear, 1:], theirs[clear, 1:])
    assert len(np.unique(ours[:, 1])) == 2 and np.any(ours[:, 2] > 0)  # it accelerates and brakes


@pytest.mark.slow  # ~20 s: the controller's CLI end to end over a bank
def test_it_drives_country_road_as_tracking_and_the_cli_writes_the_scores(tmp_path):
    """The CLI runs in a child process compiled as a user's run is (tests/conftest.py compiles the
    tests' programs another way): "the same drive" in two separately compiled programs rests on both
    rounding alike where the closed loop switches its throttle, which the tests' compile does not
    (its drives part after a switch: a return 0.12 apart)."""
    scores = {}
    for scenario in ("tracking", "country_road"):
        out = tmp_path / f"{scenario}.json"
        args = ["--env", scenario, "--episodes", "3", "--speeds", "8", "12", "--json", str(out)]
        script = [sys.executable, str(ROOT / "experiments" / "controller.py"), *args]
        done = subprocess.run(script, cwd=ROOT, env=production_compile_environ(), capture_output=True,
                              text=True, timeout=600)  # fmt: skip
        assert done.returncode == 0 and "| 8 |" in done.stdout, done.stderr[-3000:]
        document = json.loads(out.read_text())
        assert (document["env"], document["episodes"], document["eval_track_seed"]) == (scenario, 3, 1)
        assert [r["target_speed"] for r in document["results"]] == [8.0, 12.0]
        scores[scenario] = document["results"]
    for tracking, road in zip(scores["tracking"], scores["country_road"], strict=True):
        # The same tracks and physics: cones do not push the car, so the episodes are the same drive.
        # The vehicle runs the same code in two programs, which XLA may fuse (and round) differently;
        # the closed loop steers back to the line, so such last-bit differences do not grow.
        assert tracking["avg_episode_length"] == road["avg_episode_length"]
        assert tracking["avg_track_velocity"] == pytest.approx(road["avg_track_velocity"], rel=1e-4)
        assert tracking["avg_cones_hit"] == 0
        # Country Road costs 0.2 per cone hit; a hit on the step that leaves the track is not charged
        # (that step's reward is overwritten with -1). Sums of ~600 float32 rewards of magnitude <= 1
        # round to within 600 · 2⁻²⁴ · 40 ≈ 1.5e-3.
        penalty = tracking["avg_return"] - road["avg_return"]
        assert -2e-3 <= penalty <= 0.2 * road["avg_cones_hit"] + 2e-3
        if road["avg_etr"] == 0:
            assert abs(penalty - 0.2 * road["avg_cones_hit"]) < 2e-3


def test_bad_input_gets_one_line(capsys):
    for argv, fragment in (
        (["--env", "tracking", "--speeds", "0"], "positive, finite speed"),
        (["--env", "tracking", "--speeds", "nan"], "positive, finite speed"),
        (["--env", "tracking", "--speeds", "fast"], "expected a speed"),
        (["--env", "moon"], "invalid choice"),
        (["--env", "tracking", "--episodes", "0"], "positive integer"),
    ):
        one_line_error(*call(controller_cli, capsys, *argv)[::2], "controller.py: error:", fragment)


def test_the_command_lines_default_to_the_reference_speed():
    """experiments/ parse arguments without importing jax, so they spell the default speeds out;
    report.py --controller without a speed leaves each driver at its own."""
    from envs.intersection_driver import DriverSettings

    assert {
        "tracking": hand_controller.DEFAULT_TARGET_SPEED,
        "country_road": hand_controller.DEFAULT_TARGET_SPEED,
        "intersection": DriverSettings().cruise_speed,
    } == controller_cli.DEFAULT_SPEEDS
    assert controller_cli.build_parser().parse_args(["--env", "tracking"]).speeds is None  # the table's
    report_cli = load_script("report", "report_cli_for_speed")
    parse = report_cli.build_parser().parse_args
    assert parse(["run", "--out", "o", "--controller"]).controller == report_cli.DRIVERS_DEFAULT
    assert parse(["run", "--out", "o", "--controller", "9"]).controller == 9.0
    assert parse(["run", "--out", "o"]).controller is None
