"""The scripted Intersection driver (envs.intersection_driver), the yardstick of the Intersection
results: it follows every route alone without leaving the road, it gives way to the car that reaches
a crossing point first and only to that one, its caution is what keeps the 8-car evaluation nearly
free of collisions, and controller.py scores it."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from train_support import load_script

import envs
from envs import intersection_geometry as geo
from envs.intersection_driver import DEFAULT_SETTINGS, DriverSettings, scripted_action, scripted_actions
from envs.intersection_rules import observe
from envs.intersection_state import ODOMETRY_DIM
from xrl_jax.evaluation import scripted_driver_evaluation

controller_cli = load_script("controller", "controller_cli")

ENV, PARAMS = envs.make("intersection")
TOP_SPEED = PARAMS.vehicle.top_speed
NAV_SCALE = np.sqrt(2.0) * PARAMS.nav_spacing * PARAMS.nav_points


def observation(speed, others=()):
    """One agent's observation on a straight route (nav points along its own axis) at ``speed`` m/s;
    ``others`` = ((x, y), (heading_cos, heading_sin), speed) in the ego frame, metres and m/s."""
    state = np.zeros(ODOMETRY_DIM + 2 * PARAMS.nav_points, np.float32)
    state[0] = speed / TOP_SPEED
    nav = np.stack([np.arange(PARAMS.nav_points) * PARAMS.nav_spacing, np.zeros(PARAMS.nav_points)], -1)
    state[ODOMETRY_DIM:] = (nav / NAV_SCALE).reshape(-1)
    rows = np.zeros((8, 7), np.float32)
    for row, ((x, y), (c, s), v) in enumerate(others):
        rows[row] = (1.0, x / 30, y / 30, v * c / (2 * TOP_SPEED), v * s / (2 * TOP_SPEED), c, s)
    return {"state": jnp.asarray(state), "vehicles_set": jnp.asarray(rows)}


def pedals(obs, settings=DEFAULT_SETTINGS):
    steer, throttle, brake = np.asarray(scripted_action(obs, PARAMS, settings))
    assert steer == pytest.approx(0.0, abs=1e-6)  # a straight route: no steering
    return throttle, brake


def test_it_cruises_on_an_empty_road_and_brakes_above_its_cruise_speed():
    assert pedals(observation(5.0)) == (1.0, -1.0)
    assert pedals(observation(DriverSettings().cruise_speed + 2.0)) == (-1.0, 1.0)


def test_it_gives_way_to_the_car_that_reaches_the_crossing_first_and_only_to_it():
    # A car from the right (local +y is the driver's right) heading across the ego's path at 10 m/s.
    # From (12, 8) it reaches the path 8 m on (0.8 s) while the ego, at 9 m/s, needs 1.3 s: give way.
    first = ((12.0, 8.0), (0.0, -1.0), 10.0)
    assert pedals(observation(9.0, [first])) == (-1.0, 1.0)
    # From (8, 12) it needs 1.2 s and the ego 0.9 s: the ego goes on.
    second = ((8.0, 12.0), (0.0, -1.0), 10.0)
    assert pedals(observation(9.0, [second])) == (1.0, -1.0)
    # Without caution, or with the conflict beyond the horizon, the ego ignores the first car too.
    assert pedals(observation(9.0, [first]), DriverSettings(caution=False)) == (1.0, -1.0)
    far = ((40.0, 29.0), (0.0, -1.0), 10.0)  # the ego would reach the crossing in 4.4 s
    assert pedals(observation(9.0, [far])) == (1.0, -1.0)
    # An oncoming car in its own lane (3 m to the ego's left) never crosses a straight route.
    oncoming = ((15.0, -3.0), (-1.0, 0.0), 10.0)
    assert pedals(observation(9.0, [oncoming])) == (1.0, -1.0)


def test_it_follows_a_slower_car_ahead_in_its_lane():
    ahead = ((10.0, 0.0), (1.0, 0.0), 2.0)
    assert pedals(observation(9.0, [ahead])) == (-1.0, 1.0)
    behind = ((-10.0, 0.0), (1.0, 0.0), 12.0)  # a faster car behind is its own problem
    assert pedals(observation(9.0, [behind])) == (1.0, -1.0)


@pytest.mark.parametrize("kind", geo.ROUTE_KINDS)
def test_alone_it_completes_every_kind_of_route_without_leaving_the_road(kind):
    """One car (max_vehicles 1) from several approaches: it completes its route, straight or turning,
    and never leaves the road; 300 steps (30 s) are enough for the 98 m of a route at 6-10 m/s. The
    car's route is switched to the wanted kind of its approach right after the reset (the three
    routes of an approach share their first 45 m, so the tracker's state stays valid)."""
    params = PARAMS.replace(max_vehicles=1)
    kind_index = geo.ROUTE_KINDS.index(kind)

    @jax.jit
    def drive(key):
        _, state = ENV.reset(key, params)
        state = state.replace(route=state.route - state.route % 3 + kind_index)
        obs = observe(params, state)

        def body(carry, t):
            obs, state = carry
            action = scripted_actions(obs, params)
            obs, state, _, _, _, info = ENV.step(jax.random.fold_in(key, t), state, action, params)
            return (obs, state), (info["trips_completed"], info["come_off_vehicles"])

        return jax.lax.scan(body, (obs, state), jnp.arange(300))[1]

    for seed in range(4):
        trips, off_road = drive(jax.random.PRNGKey(seed))
        assert int(np.asarray(off_road)[-1]) == 0, (kind, seed)
        assert int(np.asarray(trips)[-1]) >= 1, (kind, seed)


def test_caution_keeps_the_eight_car_evaluation_nearly_free_of_collisions():
    """The agents' evaluation protocol (8 cars, 60 s) on 3 episodes. Over 20 episodes (measured) the
    driver completes 26.2 trips per episode with 2.4 collided cars, and without caution 30.0 trips
    with 27.8 collided cars: the margins below are wide of both."""
    score = scripted_driver_evaluation(3)
    careful, blind = score(), score(caution=False)
    assert careful["target_speed"] == DriverSettings().cruise_speed == score(10.0)["target_speed"]
    assert careful["avg_trips_completed"] >= 15 and careful["avg_early_terminations"] <= 8
    assert blind["avg_early_terminations"] >= 15
    assert careful["avg_come_off_vehicles"] == blind["avg_come_off_vehicles"] == 0


def test_controller_cli_scores_the_driver_on_the_intersection(tmp_path, capsys):
    path = tmp_path / "driver.json"
    code = controller_cli.main(
        ["--env", "intersection", "--episodes", "2", "--speeds", "8", "--json", str(path)]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "| cruise speed (m/s) | return | completed trips |" in out
    document = json.loads(path.read_text())
    assert document["env"] == "intersection" and document["episodes"] == 2
    (result,) = document["results"]
    assert result["target_speed"] == 8.0 and len(result["episode_returns"]) == 2
    assert result["avg_early_terminations"] == pytest.approx(
        result["avg_come_off_vehicles"] + result["avg_collided_vehicles"]
    )
