"""Per-step rules of the Intersection scenario: route tracking and rewards (§6), collisions (§5.4) and
observations (§7), as pure functions of the slot arrays (docs/carenv-intersection.md).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from envs import intersection_geometry as geo
from envs.intersection_state import (
    VEHICLES_SET_ROWS,
    IntersectionParams,
    IntersectionState,
)
from envs.vehicle_state import VehicleState, body_velocity, odometry_observation, world_to_body


def _route_tables(route, dtype):
    """Route polylines, cumulative lengths and lengths of the given route indices (gathered)."""
    xy = jnp.asarray(geo.ROUTE_XY, dtype)[route]
    cumlen = jnp.asarray(geo.ROUTE_CUMLEN, dtype)[route]
    length = jnp.asarray(geo.ROUTE_LENGTH, dtype)[route]
    return xy, cumlen, length


def project_on_routes(route, xy, dtype):
    """Arc length and distance of points (8, 2) on the slots' routes (global nearest point, Q12)."""
    route_xy, cumlen, _ = _route_tables(route, dtype)
    return jax.vmap(geo.route_project)(route_xy, cumlen, xy)


def route_points(route, s):
    """Points at arc lengths ``s`` (n, P) on routes ``route`` (n,), clamped to [0, L] -> (n, P, 2).

    Same values as ``geo.route_point_at`` (tests compare them), written without gathers, which XLA
    on CPU runs slowly under vmap: the point at s is the route start plus every segment vector
    weighted by the clipped fraction of it that lies before s.
    """
    dtype = jnp.result_type(s, float)
    xy, cumlen, _ = _route_tables(route, dtype)  # (n, V, 2), (n, V)
    start, edge = xy[:, :-1], xy[:, 1:] - xy[:, :-1]  # (n, V-1, 2)
    span = cumlen[:, 1:] - cumlen[:, :-1]
    safe = jnp.where(span > 0, span, 1.0)
    fraction = jnp.clip((s[:, :, None] - cumlen[:, None, :-1]) / safe[:, None, :], 0.0, 1.0)
    fraction = jnp.where(span[:, None, :] > 0, fraction, 0.0)  # (n, P, V-1)
    x = start[:, None, 0, 0] + jnp.sum(fraction * edge[:, None, :, 0], axis=-1)
    y = start[:, None, 0, 1] + jnp.sum(fraction * edge[:, None, :, 1], axis=-1)
    return jnp.stack([x, y], axis=-1)


def to_ego(points, x, y, theta):
    """World points (..., 2) into the ego frame of pose (x, y, theta): R(-theta)(p - (x, y))."""
    return jnp.stack(world_to_body(points[..., 0], points[..., 1], x, y, theta), axis=-1)


def vehicle_poses(vehicle: VehicleState):
    return jnp.stack([vehicle.x, vehicle.y, vehicle.theta], axis=-1)


def route_tracker(params: IntersectionParams, route, prev_xy, prev_s, xy):
    """Route tracker of §6.1 for positions (..., 2) on routes (...).

    Returns (r_track, s, moved, goal): r_track = k_forwards x (s - prev_s) - k_tracking x dist x moved
    with s, dist the global nearest point of the route (Q12), moved = |xy - prev_xy|, and
    goal = s > L - goal_margin.
    """
    dtype = jnp.result_type(xy, float)
    route_xy, cumlen, length = _route_tables(route, dtype)
    project = geo.route_project
    for _ in range(jnp.ndim(route)):
        project = jax.vmap(project)
    s, distance = project(route_xy, cumlen, xy)
    moved = jnp.sqrt(jnp.sum((xy - prev_xy) ** 2, axis=-1))
    reward = params.k_forwards * (s - prev_s) - params.k_tracking * distance * moved
    return reward, s, moved, s > length - params.goal_margin


def slip_penalty(params: IntersectionParams, vehicle: VehicleState):
    """Rear-axle slip penalty in [0, 1] per car (§6.2), before the multiplication by dt."""
    u_x, u_y = body_velocity(vehicle)
    vx_r = u_x
    vy_r = u_y - vehicle.yaw_rate * (params.vehicle.wheelbase / 2.0)
    magnitude = jnp.maximum(0.1, jnp.abs(vx_r))
    safe_vx = jnp.where(vx_r < 0, -magnitude, magnitude)
    beta_deg = jnp.abs(jnp.arctan2(vy_r, safe_vx)) * (180.0 / math.pi)
    return jnp.minimum(1.0, jnp.maximum(0.0, beta_deg - params.slip_start_deg) / params.slip_scale_deg)


def collision_rewards(params: IntersectionParams, poses, speed, alive, spawn_seq, reward):
    """Pairwise collisions of §5.4 as (8, 8) arrays; returns (reward, hard_hit, hard_pairs x 2).

    ``reward`` is the pending reward before the collision pass. Closed form of the original's
    sequential add/set: with a hard collision, agent a gets base(a) - penalty x (soft partners after
    its last hard partner in agent order), base = 0 if a is stationary else -1; without one, its
    pending reward minus penalty x (soft partners).
    """
    dtype = reward.dtype
    n = alive.shape[0]
    pair = alive[:, None] & alive[None, :] & ~jnp.eye(n, dtype=bool)

    def grid(half_length, half_width):
        test = lambda a, b: geo.rectangles_intersect(a, b, half_length, half_width)
        return jax.vmap(jax.vmap(test, (None, 0)), (0, None))(poses, poses)

    hard_shape = grid(geo.VEHICLE_HALF_LENGTH, geo.VEHICLE_HALF_WIDTH)
    if params.soft_collisions:
        soft = pair & grid(
            geo.VEHICLE_HALF_LENGTH + params.soft_pad_long, geo.VEHICLE_HALF_WIDTH + params.soft_pad_lat
        )
        hard = soft & hard_shape
        penalty = params.k_soft_collision * params.dt
    else:
        soft = jnp.zeros_like(pair)
        hard = pair & hard_shape
        penalty = 0.0
    hit = jnp.any(hard, axis=1)
    last_hard_seq = jnp.max(jnp.where(hard, spawn_seq[None, :], -1), axis=1)
    soft_after = jnp.sum(soft & (spawn_seq[None, :] > last_hard_seq[:, None]), axis=1)
    base = jnp.where(speed < params.stationary_speed, 0.0, -1.0).astype(dtype)
    collided = base - penalty * soft_after
    free = reward - penalty * jnp.sum(soft, axis=1)
    return jnp.where(hit, collided, free).astype(dtype), hit, jnp.sum(hard, dtype=jnp.int32)


def vehicles_set(params: IntersectionParams, vehicle: VehicleState, present, spawn_seq):
    """(8, 8, 7) float32: per ego slot, the other present cars in agent order, kept iff strictly
    inside the +-sensor_range ego box, rows contiguous from 0 (§7.1). Absent egos: zeros.

    Written as (ego, other) arrays per feature (no trailing axis of 2, no sort, no dot products):
    XLA on CPU handles those tiny shapes badly. The row of a kept car is the number of kept cars
    with a smaller spawn sequence number.
    """
    n = present.shape[0]
    cos_e, sin_e = jnp.cos(vehicle.theta)[:, None], jnp.sin(vehicle.theta)[:, None]
    dx = vehicle.x[None, :] - vehicle.x[:, None]
    dy = vehicle.y[None, :] - vehicle.y[:, None]
    rel_x = cos_e * dx + sin_e * dy
    rel_y = -sin_e * dx + cos_e * dy
    u_x, u_y = body_velocity(vehicle)
    heading = vehicle.theta[None, :] - vehicle.theta[:, None]  # theta_o - theta_e
    cos_h, sin_h = jnp.cos(heading), jnp.sin(heading)
    if params.body_velocity_frame_bug:  # Q2: R(-theta_e) applied to the body-frame velocity
        cos_f, sin_f = jnp.broadcast_to(cos_e, heading.shape), jnp.broadcast_to(-sin_e, heading.shape)
    else:
        cos_f, sin_f = cos_h, sin_h
    vel_x = cos_f * u_x[None, :] - sin_f * u_y[None, :]
    vel_y = sin_f * u_x[None, :] + cos_f * u_y[None, :]
    position_norm = params.sensor_range
    velocity_norm = 2.0 * params.vehicle.top_speed
    features = [rel_x / position_norm, rel_y / position_norm, vel_x / velocity_norm, vel_y / velocity_norm]
    features = [jnp.clip(f, -1.0, 1.0) for f in features] + [cos_h, sin_h]
    inside = (jnp.abs(rel_x) < params.sensor_range) & (jnp.abs(rel_y) < params.sensor_range)
    kept = present[:, None] & present[None, :] & ~jnp.eye(n, dtype=bool) & inside  # (ego, other)
    earlier = spawn_seq[None, :] < spawn_seq[:, None]  # (other, other'): other' comes before other
    row = jnp.sum(kept[:, None, :] & earlier[None, :, :], axis=-1)  # (ego, other)
    slot_rows = jnp.arange(VEHICLES_SET_ROWS)
    place = kept[:, :, None] & (row[:, :, None] == slot_rows[None, None, :])  # (ego, other, row)
    dtype = rel_x.dtype
    columns = [jnp.any(place, axis=1).astype(dtype)]
    columns += [jnp.sum(jnp.where(place, f[:, :, None], 0.0), axis=1) for f in features]
    return jnp.stack(columns, axis=-1).astype(jnp.float32)


def state_observation(params: IntersectionParams, vehicle: VehicleState, route, s, present):
    """(8, 66) float32: odometry (6) then the 30 navigation points in the ego frame (§7.2)."""
    dtype = vehicle.x.dtype
    odometry = odometry_observation(params.vehicle, vehicle)
    offsets = jnp.arange(params.nav_points, dtype=dtype) * params.nav_spacing
    points = route_points(route, s[:, None] + offsets[None, :])  # (8, P, 2)
    local = jax.vmap(to_ego)(points, vehicle.x, vehicle.y, vehicle.theta)
    scale = math.sqrt(2.0) * params.nav_spacing * params.nav_points
    nav = jnp.clip((local / scale).reshape(local.shape[0], -1).astype(jnp.float32), -1.0, 1.0)
    obs = jnp.concatenate([odometry, nav], axis=-1)
    return jnp.where(present[:, None], obs, 0.0)


def observe(params: IntersectionParams, state: IntersectionState) -> dict[str, jax.Array]:
    """Observations of every alive slot of ``state`` (zeros elsewhere)."""
    return {
        "vehicles_set": vehicles_set(params, state.vehicle, state.alive, state.spawn_seq),
        "state": state_observation(params, state.vehicle, state.route, state.prev_s, state.alive),
    }
