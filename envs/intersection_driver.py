"""A scripted Intersection driver: the yardstick the learned policies are compared with.

The racing scenarios have the centre-line controller of :mod:`envs.hand_controller`; this is its
Intersection counterpart. It reads only an agent's own observation (docs/carenv-intersection.md §7),
so it drives every slot of the multi-agent env the way a policy does, with continuous actions:

* **Route.** Pure pursuit on the navigation points (point ``j`` lies ``j`` metres along the car's
  route): steer towards the point ``lookahead`` metres ahead, with the steering angle that puts a
  car of the model's wheelbase on the circle through it.
* **Speed.** A cruise speed, lowered to a turn speed while the route ahead bends (the point
  ``turn_lookahead`` metres ahead lies more than 0.3 rad off the car's axis): the 4.5 m turns
  cannot be taken at cruise speed. Full throttle below the target, full brake well above it.
* **Caution** (``caution=True``). Each other car in view is taken to drive straight on at its
  current speed and heading. Where that line comes within ``clearance`` metres of a point of the
  ego's route, the two paths cross; each car's time to that point is its distance over its speed
  (at least ``creep_speed``, so stopped cars still get an order). The ego brakes to a stop for a car
  that gets there first, if the ego itself would get there within ``horizon`` seconds; a car ahead
  in its own lane counts (its path crosses the route at its own position), a car behind does not.
  Two cars waiting for each other cannot both yield: the one nearer the crossing goes.

The other car's speed is read as the norm of its observed velocity, which the original's frame bug
(§9 Q2 there) rotates but does not scale; its heading comes from the (cos, sin) columns.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from envs.intersection_state import ODOMETRY_DIM, IntersectionParams

TURN_ANGLE = 0.3  # rad: the route point turn_lookahead ahead this far off the axis means a turn
BRAKE_MARGIN = 1.0  # m/s above the target before braking
STOP_SPEED = 0.3  # m/s: below this a yielding car releases the brake (it has stopped)


class DriverSettings(NamedTuple):
    """The driver's knobs (traced: several settings share one compiled evaluation)."""

    cruise_speed: float = 10.0  # m/s on straights
    turn_speed: float = 6.0  # m/s while the route ahead bends
    lookahead: float = 7.0  # m: pure-pursuit target along the route
    turn_lookahead: float = 20.0  # m: how far ahead a turn is noticed
    caution: bool = True  # yield to cars whose predicted path comes too close
    horizon: float = 3.0  # s: conflicts the ego would reach later are ignored for now
    clearance: float = 2.5  # m: another car's path this close to a route point crosses the route
    creep_speed: float = 3.0  # m/s: slower cars are timed as if moving this fast


def _route_point(nav, distance):
    """The navigation point ``distance`` samples ahead (linear in between; clamped to the last)."""
    last = nav.shape[-2] - 1
    distance = jnp.clip(distance, 0.0, last)
    low = jnp.floor(distance).astype(jnp.int32)
    high = jnp.minimum(low + 1, last)
    frac = (distance - low)[..., None]
    take = lambda i: jnp.take_along_axis(nav, i[..., None, None], axis=-2)[..., 0, :]
    return (1.0 - frac) * take(low) + frac * take(high)


DEFAULT_SETTINGS = DriverSettings()


def scripted_action(obs, params: IntersectionParams, settings: DriverSettings = DEFAULT_SETTINGS):
    """The driver's continuous action ``(3,)`` (steer, throttle pedal, brake pedal) for one agent's
    observation ``{"state": (66,), "vehicles_set": (8, 7)}``; ``jax.vmap`` it over agents."""
    vehicle = params.vehicle
    state = obs["state"]
    speed = state[0] * vehicle.top_speed
    nav_scale = jnp.sqrt(2.0) * params.nav_spacing * params.nav_points  # §7.2's normaliser
    nav = state[ODOMETRY_DIM:].reshape(-1, 2) * nav_scale  # metres, ego frame, nav_spacing apart

    # Route: pure pursuit towards the point `lookahead` ahead.
    target = _route_point(nav, settings.lookahead / params.nav_spacing)
    alpha = jnp.arctan2(target[1], target[0])
    distance = jnp.maximum(jnp.hypot(target[0], target[1]), 1e-3)
    steer_angle = jnp.arctan(2.0 * vehicle.wheelbase * jnp.sin(alpha) / distance)
    steer = jnp.clip(steer_angle / vehicle.max_steer, -1.0, 1.0)

    ahead = _route_point(nav, settings.turn_lookahead / params.nav_spacing)
    bend = jnp.arctan2(ahead[1], ahead[0])
    turning = jnp.abs(bend) > TURN_ANGLE
    target_speed = jnp.where(turning, settings.turn_speed, settings.cruise_speed)

    # Caution: where does each other car's straight-line path cross the ego's route, and who is first?
    others = obs["vehicles_set"]
    present = others[:, 0] > 0.5
    position = others[:, 1:3] * params.sensor_range  # (O, 2) metres, ego frame
    other_speed = jnp.hypot(others[:, 3], others[:, 4]) * 2.0 * vehicle.top_speed
    direction = others[:, 5:7]  # (O, 2) unit heading, ego frame
    offset = nav[None, :, :] - position[:, None, :]  # (O, P, 2): route points seen from each car
    along = jnp.clip(jnp.sum(offset * direction[:, None, :], axis=-1), 0.0, None)  # (O, P)
    lateral = jnp.hypot(*jnp.moveaxis(offset - along[..., None] * direction[:, None, :], -1, 0))
    crosses = lateral < settings.clearance  # (O, P)
    first = jnp.argmax(crosses, axis=1)  # the first route point the other car's path comes near
    ego_distance = first * params.nav_spacing
    other_distance = jnp.take_along_axis(along, first[:, None], axis=1)[:, 0]
    ego_time = ego_distance / jnp.maximum(speed, settings.creep_speed)
    other_time = other_distance / jnp.maximum(other_speed, settings.creep_speed)
    give_way = present & jnp.any(crosses, axis=1) & (ego_time < settings.horizon) & (other_time < ego_time)
    yielding = settings.caution & jnp.any(give_way)
    target_speed = jnp.where(yielding, 0.0, target_speed)

    throttle = jnp.where(speed < target_speed, 1.0, -1.0)
    brake_above = jnp.where(yielding, STOP_SPEED, target_speed + BRAKE_MARGIN)
    brake = jnp.where(speed > brake_above, 1.0, -1.0)
    return jnp.stack([steer, throttle, brake]).astype(jnp.float32)


def scripted_actions(obs, params: IntersectionParams, settings: DriverSettings = DEFAULT_SETTINGS):
    """:func:`scripted_action` for every agent slot: ``obs`` leaves carry a leading agent axis."""
    return jax.vmap(scripted_action, in_axes=(0, None, None))(obs, params, settings)
