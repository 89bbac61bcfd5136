"""The hand-written centre-line driver of docs/carenv-single-agent.md §8.3: a reference score.

An agent that cannot beat a three-line controller has not learned to drive, so the results put this
controller's score beside the agents' on the same evaluation tracks. §8.3 defines it on the
Tracking observation (the 4th and 10th lookahead points, 8 m and 20 m ahead); here it reads those
points from the track's centre line in the env state instead, so the same driver runs on Country
Road, whose observation holds only cones. On Tracking both readings give the same action (a test
checks it): the observation's points are these points, scaled.

Steering: ``clip(2·atan2(y₈, x₈) / 0.52, −1, 1)`` towards the point 8 m ahead. Speed: a target V,
lowered to 0.6·V when the point 20 m ahead lies ≥ 0.2 rad off the car's axis; full throttle below
the target, full brake above target + 2 m/s, coasting between. The action is the continuous
(steer, throttle pedal, brake pedal) of §4.1, whichever action space the agents use.
"""

from __future__ import annotations

import jax.numpy as jnp

from envs.racing import RacingEnv, RacingParams, RacingState
from envs.ring_geometry import points_at_arclength
from envs.vehicle_state import body_velocity, world_to_body

STEER_POINT = 4  # lookahead index (× lookahead_spacing = 8 m ahead) the car steers towards
CURVE_POINT = 10  # lookahead index (20 m ahead) that tells a bend is coming
STEER_GAIN = 2.0 / 0.52  # twice the heading error, over the 0.52 rad the full steering command means
CURVE_ANGLE = 0.2  # rad: a bend ahead at least this sharp ...
CURVE_SLOWDOWN = 0.6  # ... lowers the target speed to this fraction
BRAKE_MARGIN = 2.0  # m/s above the target before braking
DEFAULT_TARGET_SPEED = 8.0  # m/s; §8.3 measured 36.5 (8), 23.4 (12), 10.9 (16) on Tracking


def lookahead_angles(env: RacingEnv, state: RacingState, params: RacingParams):
    """Angles (rad, car frame) of the centre-line points STEER_POINT and CURVE_POINT ahead."""
    view = env._view(state, params)
    ahead = jnp.asarray([STEER_POINT, CURVE_POINT], state.prev_s.dtype) * params.lookahead_spacing
    # The travel direction runs against the stored order (as in the Tracking sensor).
    px, py = points_at_arclength(view, state.prev_s - ahead)
    v = state.vehicle
    bx, by = world_to_body(px, py, v.x, v.y, v.theta)
    angles = jnp.arctan2(by, bx)
    return angles[0], angles[1]


def centre_line_action(
    env: RacingEnv, state: RacingState, params: RacingParams, target_speed: float = DEFAULT_TARGET_SPEED
):
    """The §8.3 controller's continuous action ``(3,)`` for one (un-batched) racing state."""
    steer_angle, curve_angle = lookahead_angles(env, state, params)
    steer = jnp.clip(STEER_GAIN * steer_angle, -1.0, 1.0)
    target = jnp.where(jnp.abs(curve_angle) >= CURVE_ANGLE, CURVE_SLOWDOWN * target_speed, target_speed)
    speed = body_velocity(state.vehicle)[0]
    throttle = jnp.where(speed < target, 1.0, -1.0)
    brake = jnp.where(speed > target + BRAKE_MARGIN, 1.0, -1.0)
    return jnp.stack([steer, throttle, brake]).astype(jnp.float32)
