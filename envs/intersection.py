"""Multi-agent Intersection (CarEnv ``marl_intersection`` as used by the paper), fixed-slot JAX port.

Reference: docs/carenv-intersection.md. Up to :data:`MAX_AGENTS` = 8 cars share a four-way crossing; each
follows its own route (12 routes, see ``envs.intersection_geometry``) and is rewarded for progress
along it. Cars appear at the four approaches, leave when they reach their goal, leave the road or
collide, and are replaced by new ones. Everything is one pure, fixed-shape function of
``(key, state, action, params)``, so ``jit`` and ``vmap`` (over envs) work unchanged.

Agents live in 8 *slots* (leading axis of every per-agent array) with an ``alive`` mask. The
original keeps agents in insertion order, which decides the vehicles-set row order and a reward
detail of collisions (§4.4, §5.4); a per-slot ``spawn_seq`` number reproduces that order. A new
agent takes the lowest free slot, and slots of agents terminating in the step are not free (§4.5).

Step order (§4.2 / §11): physics, route tracker reward and slip penalty, goal (SET +1),
off-road (SET -1), pairwise collisions (soft penalty / SET 0 or -1 in agent order), metrics,
spawning, observations of every slot alive now (survivors, terminating, new), then removal.

The 60 s restart of the paper's training loop happens INSIDE ``step`` after
``params.episode_steps`` steps (see :meth:`IntersectionEnv.step_env`): the returned obs/state
then belong to the new episode, ``info["final_obs"]`` keeps the ending step's observations,
and agents that acted and survived get ``truncated=True`` (a time limit, to be bootstrapped).

Invalid actions: a slot whose action has a NaN or ±inf entry (after the cast to the env's float
dtype), or whose discrete index selects no row of the 12-way table (outside [0, 12), or a float that
is not finite), ends that vehicle's episode: it is stepped with the neutral control (steering 0,
pedals released) so its state stays finite and other cars still see and hit it, it gets reward -1,
``terminated`` and ``done_reason`` :data:`NONFINITE_ACTION` = 4 (overriding goal, off-road and
collision for that car, which then count neither as a trip nor as a car off the road; hard collision
pairs still count), and ``info["nonfinite_action"]`` is True for it. Only acting (alive) slots are
checked: padding slots may hold anything. Finite continuous actions are clipped to [-1, 1].

Quirks of the original are reproduced by default and can be switched off with static flags of
:class:`IntersectionParams` (§9): ``stale_spawn_timers`` (Q1), ``body_velocity_frame_bug``
(Q2) and ``soft_collisions`` (Q3).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import actions as actions_mod
from envs import intersection_geometry as geo
from envs.core import Box, Dict, Discrete, Environment, default_float
from envs.vehicle import VehicleParams, VehicleState, body_velocity, odometry_observation, vehicle_step

MAX_AGENTS = 8
NUM_SPAWNERS = 4
CURRICULUM = (1, 2, 4, 8)
# Curriculum probabilities proportional to 1/n (§8.3): (8, 4, 2, 1) / 15.
CURRICULUM_PROBS = tuple(float(p) for p in (1.0 / np.array(CURRICULUM)) / np.sum(1.0 / np.array(CURRICULUM)))

DONE_NONE, COMPLETED_ROUTE, LEFT_ROAD, COLLIDED, NONFINITE_ACTION = 0, 1, 2, 3, 4
DONE_REASONS = {
    DONE_NONE: "",
    COMPLETED_ROUTE: "CompletedRoute",
    LEFT_ROAD: "LeftRoad",
    COLLIDED: "Collided",
    NONFINITE_ACTION: "NonFiniteAction",
}

VEHICLES_SET_ROWS = 8  # XRLDMP's max_objects
VEHICLE_FEATURES = 7  # present, x, y, vx, vy, cos, sin
ODOMETRY_DIM = 6
# Timer comparison tolerance of Q13: the original's t = 15 x 0.1 is 1.5000000000000002 > 1.5.
_SPAWN_TIME_TOLERANCE = 1e-6
_MAX_SENSOR_RANGE = 44.0  # fresh cars on different approaches are >= 44.6 m apart along x or y


@struct.dataclass
class IntersectionParams:
    """Everything configurable about the scenario. Numbers are pytree leaves (may be traced);
    switches and shapes are static.

    ``dt`` must equal ``vehicle.dt`` (the physics step); the spawner clock uses ``dt``.
    ``max_vehicles``: 0 draws the cap at every (re)start from :data:`CURRICULUM` with probabilities
    proportional to 1/n (training); 1..8 fixes it (evaluation uses 8).
    ``episode_steps``: the training loop's 60 s restart, done inside the env (§8.4).
    Quirk flags (default = original behaviour):
      ``stale_spawn_timers`` (Q1): spawners that do not spawn at a restart keep their timer from the
        previous episode's clock; False clears all four timers at every restart.
      ``body_velocity_frame_bug`` (Q2): other cars' velocity in the vehicles set is their body-frame
        velocity rotated by minus the ego heading; False uses R(theta_o - theta_e) v_o_body.
      ``soft_collisions``: padded rectangles give -k_soft_collision*dt per overlapping pair (on in all
        paper configs); False tests the hard rectangles only.
    """

    vehicle: VehicleParams = VehicleParams()
    dt: float = 0.1
    k_forwards: float = 0.05
    k_tracking: float = 0.015
    slip_start_deg: float = 4.0
    slip_scale_deg: float = 20.0
    k_soft_collision: float = 0.5
    spawn_speed_range: tuple = (5.55, 8.33)
    spawn_jitter: float = 0.2
    spawn_interval: float = 1.5
    spawn_time_noise: float = 0.2
    goal_margin: float = 5.0
    stationary_speed: float = 0.01
    sensor_range: float = 30.0
    soft_pad_long: float = geo.SOFT_PAD_LONG
    soft_pad_lat: float = geo.SOFT_PAD_LAT
    nav_spacing: float = 1.0
    nav_points: int = struct.field(pytree_node=False, default=30)
    max_vehicles: int = struct.field(pytree_node=False, default=0)
    episode_steps: int = struct.field(pytree_node=False, default=600)
    stale_spawn_timers: bool = struct.field(pytree_node=False, default=True)
    body_velocity_frame_bug: bool = struct.field(pytree_node=False, default=True)
    soft_collisions: bool = struct.field(pytree_node=False, default=True)

    def __post_init__(self):
        if not isinstance(self.max_vehicles, int) or not 0 <= self.max_vehicles <= MAX_AGENTS:
            raise ValueError(
                f"max_vehicles must be an int in 0..{MAX_AGENTS} (0 = curriculum), got {self.max_vehicles!r}"
            )
        if not isinstance(self.episode_steps, int) or self.episode_steps < 1:
            raise ValueError(f"episode_steps must be a positive int, got {self.episode_steps!r}")
        if isinstance(self.sensor_range, (int, float)) and not 0 < self.sensor_range <= _MAX_SENSOR_RANGE:
            raise ValueError(
                f"sensor_range must lie in (0, {_MAX_SENSOR_RANGE}] m (the restart relies on spawned cars "
                f"not seeing each other), got {self.sensor_range!r}"
            )
        if not isinstance(self.nav_points, int) or self.nav_points < 1:
            raise ValueError(f"nav_points must be a positive int, got {self.nav_points!r}")

    @property
    def state_dim(self) -> int:
        return ODOMETRY_DIM + 2 * self.nav_points


@struct.dataclass
class IntersectionState:
    """Per slot (leading axis 8) and global state; see the module docstring."""

    vehicle: VehicleState  # (8,) leaves
    alive: jax.Array  # (8,) bool
    spawn_seq: jax.Array  # (8,) int32, insertion order of the agent in the slot
    route: jax.Array  # (8,) int32 in 0..11
    prev_xy: jax.Array  # (8, 2) route tracker's previous position
    prev_s: jax.Array  # (8,) route tracker's previous projected arc length
    step: jax.Array  # () int32, steps since the episode started
    max_vehicles: jax.Array  # () int32, this episode's cap
    next_seq: jax.Array  # () int32
    spawner_last: jax.Array  # (4,) last spawn time (episode clock, possibly of an earlier episode: Q1)
    spawner_set: jax.Array  # (4,) bool, False = "none" (never spawned)
    trips_completed: jax.Array  # () int32
    come_off_vehicles: jax.Array  # () int32
    collided_vehicles: jax.Array  # () int32
    velocity_sum: jax.Array  # () float, sum over agent-steps of displacement / dt
    velocity_count: jax.Array  # () int32, number of agent-steps

    @property
    def mean_velocity(self) -> jax.Array:
        return jnp.where(
            self.velocity_count > 0, self.velocity_sum / jnp.maximum(self.velocity_count, 1), 0.0
        )


# --------------------------------------------------------------------------------------------
# Route tables and small helpers
# --------------------------------------------------------------------------------------------


def _route_tables(route, dtype):
    """Route polylines, cumulative lengths and lengths of the given route indices (gathered)."""
    xy = jnp.asarray(geo.ROUTE_XY, dtype)[route]
    cumlen = jnp.asarray(geo.ROUTE_CUMLEN, dtype)[route]
    length = jnp.asarray(geo.ROUTE_LENGTH, dtype)[route]
    return xy, cumlen, length


def _project(route, xy, dtype):
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


def _to_ego(points, x, y, theta):
    """World points (..., 2) into the ego frame of pose (x, y, theta): R(-theta)(p - (x, y))."""
    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    dx, dy = points[..., 0] - x, points[..., 1] - y
    return jnp.stack([cos_t * dx + sin_t * dy, -sin_t * dx + cos_t * dy], axis=-1)


def _poses(vehicle: VehicleState):
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


# --------------------------------------------------------------------------------------------
# Observations (§7)
# --------------------------------------------------------------------------------------------


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
    local = jax.vmap(_to_ego)(points, vehicle.x, vehicle.y, vehicle.theta)
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


# --------------------------------------------------------------------------------------------
# Spawning (§2.3, §3.3, §3.4)
# --------------------------------------------------------------------------------------------


def _spawn_cars(key, params: IntersectionParams, approach, dtype):
    """Fresh cars (one per slot) on approaches ``approach`` (8,): random route, jitter and speed."""
    key_route, key_jitter, key_speed = jax.random.split(key, 3)
    n = approach.shape[0]
    kind = jax.random.randint(key_route, (n,), 0, 3, dtype=jnp.int32)
    route = (3 * approach + kind).astype(jnp.int32)
    pose = jnp.asarray(geo.SPAWN_POSES, dtype)[approach]
    jitter = jax.random.uniform(key_jitter, (n, 2), dtype, -params.spawn_jitter, params.spawn_jitter)
    xy = pose[:, :2] + jitter
    theta = pose[:, 2]
    low, high = params.spawn_speed_range
    v0 = jax.random.uniform(key_speed, (n,), dtype, low, high)
    omega = v0 / params.vehicle.wheel_radius
    zero = jnp.zeros((n,), dtype)
    vehicle = VehicleState(
        x=xy[:, 0],
        y=xy[:, 1],
        theta=theta,
        vx=jnp.cos(theta) * v0,
        vy=jnp.sin(theta) * v0,
        yaw_rate=zero,
        omega_front=omega,
        omega_rear=omega,
        steer=zero,
    )
    s, _ = _project(route, xy, dtype)
    return vehicle, route, xy, s


def _where_slots(mask, new, old):
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old
    )


def _draw_max_vehicles(key, params: IntersectionParams):
    if params.max_vehicles > 0:
        return jnp.asarray(params.max_vehicles, jnp.int32)
    logits = jnp.log(jnp.asarray(CURRICULUM_PROBS, jnp.float32))
    return jnp.asarray(CURRICULUM, jnp.int32)[jax.random.categorical(key, logits)]


def _fresh_state(key, params: IntersectionParams, spawner_last, spawner_set) -> IntersectionState:
    """Reset of §3.2: min(4, max_vehicles) cars on distinct random approaches, in slots 0.."""
    dtype = default_float()
    key_cap, key_perm, key_cars = jax.random.split(key, 3)
    max_vehicles = _draw_max_vehicles(key_cap, params)
    order = jax.random.permutation(key_perm, NUM_SPAWNERS).astype(jnp.int32)
    count = jnp.minimum(max_vehicles, NUM_SPAWNERS)
    slot = jnp.arange(MAX_AGENTS)
    alive = slot < count
    approach = order[jnp.minimum(slot, NUM_SPAWNERS - 1)]
    vehicle, route, xy, s = _spawn_cars(key_cars, params, approach, dtype)
    spawned = jnp.zeros(NUM_SPAWNERS, bool).at[order].set(jnp.arange(NUM_SPAWNERS) < count)
    zero_i = jnp.zeros((), jnp.int32)
    return IntersectionState(
        vehicle=vehicle,
        alive=alive,
        spawn_seq=jnp.where(alive, slot, 0).astype(jnp.int32),
        route=route,
        prev_xy=xy,
        prev_s=s,
        step=zero_i,
        max_vehicles=max_vehicles,
        next_seq=count.astype(jnp.int32),
        spawner_last=jnp.where(spawned, 0.0, jnp.asarray(spawner_last, dtype)).astype(dtype),
        spawner_set=spawned | spawner_set,
        trips_completed=zero_i,
        come_off_vehicles=zero_i,
        collided_vehicles=zero_i,
        velocity_sum=jnp.zeros((), dtype),
        velocity_count=zero_i,
    )


def spawn_vehicles(key, params: IntersectionParams, state: IntersectionState, occupied, time):
    """Spawning inside a step (§3.4). ``occupied`` (8,) = alive incl. terminating agents.

    Returns (state with the new cars written into free slots, new-car mask (8,)).
    """
    dtype = state.prev_s.dtype
    key_perm, key_cars, key_timer = jax.random.split(key, 3)
    count = jnp.sum(occupied, dtype=jnp.int32)
    room = jnp.maximum(state.max_vehicles - count, 0)
    poses = _poses(state.vehicle)
    areas = jnp.asarray(geo.SPAWN_AREAS, dtype)
    touches = jax.vmap(
        lambda box: jax.vmap(
            lambda p: geo.rectangle_intersects_box(p, geo.VEHICLE_HALF_LENGTH, geo.VEHICLE_HALF_WIDTH, box)
        )(poses)
    )(areas)  # (4, 8)
    area_free = ~jnp.any(touches & occupied[None, :], axis=1)
    timer_ok = ~state.spawner_set | (
        time - state.spawner_last > params.spawn_interval - _SPAWN_TIME_TOLERANCE
    )
    eligible = area_free & timer_ok
    order = jax.random.permutation(key_perm, NUM_SPAWNERS).astype(jnp.int32)
    eligible_walk = eligible[order]
    rank = jnp.cumsum(eligible_walk) - 1
    take_walk = eligible_walk & (rank < room)
    n_new = jnp.sum(take_walk, dtype=jnp.int32)
    # j-th spawned car (walk order) -> approach; j-th free slot (lowest first) receives it.
    by_rank = take_walk[None, :] & (rank[None, :] == jnp.arange(NUM_SPAWNERS)[:, None])  # (rank, walk)
    approach_of_rank = jnp.sum(jnp.where(by_rank, order[None, :], 0), axis=1)
    free = ~occupied
    free_rank = jnp.cumsum(free) - 1
    new = free & (free_rank < n_new)
    approach = approach_of_rank[jnp.clip(free_rank, 0, NUM_SPAWNERS - 1)]
    vehicle, route, xy, s = _spawn_cars(key_cars, params, approach, dtype)
    taken = jnp.zeros(NUM_SPAWNERS, bool).at[order].set(take_walk)
    noise = params.spawn_time_noise * jax.random.normal(key_timer, (NUM_SPAWNERS,), dtype)
    state = state.replace(
        vehicle=_where_slots(new, vehicle, state.vehicle),
        route=jnp.where(new, route, state.route),
        prev_xy=jnp.where(new[:, None], xy, state.prev_xy),
        prev_s=jnp.where(new, s, state.prev_s),
        spawn_seq=jnp.where(new, state.next_seq + free_rank, state.spawn_seq).astype(jnp.int32),
        next_seq=state.next_seq + n_new,
        spawner_last=jnp.where(taken, time + noise, state.spawner_last).astype(dtype),
        spawner_set=state.spawner_set | taken,
    )
    return state, new


# --------------------------------------------------------------------------------------------
# The environment
# --------------------------------------------------------------------------------------------


class IntersectionEnv(Environment):
    """Multi-agent intersection; continuous (8, 3) actions, or (8,) indices of the 12-way table
    with ``discrete=True``. Per-slot outputs; see the module docstring and :meth:`step_env`."""

    num_agents = MAX_AGENTS

    def __init__(self, discrete: bool = False):
        self.discrete = bool(discrete)

    def __eq__(self, other) -> bool:
        return isinstance(other, IntersectionEnv) and self.discrete == other.discrete

    def __hash__(self) -> int:
        return hash((IntersectionEnv, self.discrete))

    def __repr__(self) -> str:
        return f"IntersectionEnv(discrete={self.discrete})"

    @property
    def name(self) -> str:
        return "IntersectionDiscrete" if self.discrete else "Intersection"

    @property
    def default_params(self) -> IntersectionParams:
        return IntersectionParams()

    def action_space(self, params: IntersectionParams | None = None):
        """Per-agent action space."""
        if self.discrete:
            return Discrete(actions_mod.NUM_DISCRETE_ACTIONS)
        return Box(-1.0, 1.0, (3,), jnp.float32)

    def observation_space(self, params: IntersectionParams | None = None):
        """Per-agent observation space."""
        params = self.default_params if params is None else params
        return Dict(
            {
                "vehicles_set": Box(-1.0, 1.0, (VEHICLES_SET_ROWS, VEHICLE_FEATURES), jnp.float32),
                "state": Box(-1.0, 1.0, (params.state_dim,), jnp.float32),
            }
        )

    def sample_actions(self, key, params: IntersectionParams | None = None):
        """Uniform random actions for all 8 slots."""
        space = self.action_space(params)
        return jax.vmap(space.sample)(jax.random.split(key, MAX_AGENTS))

    def _control(self, action, alive):
        action = jnp.asarray(action)
        if self.discrete:
            if action.shape != (MAX_AGENTS,):
                raise ValueError(
                    f"discrete intersection action must have shape ({MAX_AGENTS},), got {action.shape}"
                )
            index = jnp.where(alive, action.astype(jnp.int32), 0)
            return actions_mod.discrete_to_control(index)
        if action.shape != (MAX_AGENTS, 3):
            raise ValueError(f"intersection action must have shape ({MAX_AGENTS}, 3), got {action.shape}")
        action = jnp.where(alive[:, None], action.astype(default_float()), 0.0)
        return actions_mod.continuous_to_control(action)

    def _checked_control(self, action, alive):
        """``(control (8, 3), invalid (8,))``: ``_control`` with the neutral zeros in the alive slots
        whose action is invalid (see the module docstring); ``invalid`` is False where not alive."""
        control = self._control(action, alive)  # validates the shape first
        action = jnp.asarray(action)
        if self.discrete:
            invalid = actions_mod.invalid_discrete_index(action)
        else:
            invalid = ~jnp.all(jnp.isfinite(action.astype(default_float())), axis=-1)
        invalid = alive & invalid
        return jnp.where(invalid[:, None], jnp.zeros_like(control), control), invalid

    def reset_env(self, key: jax.Array, params: IntersectionParams):
        """A fresh environment: spawner timers are all "none"."""
        dtype = default_float()
        state = _fresh_state(key, params, jnp.zeros(NUM_SPAWNERS, dtype), jnp.zeros(NUM_SPAWNERS, bool))
        return observe(params, state), state

    def restart(self, key: jax.Array, state: IntersectionState, params: IntersectionParams):
        """The training loop's episode restart: like ``reset_env`` but keeping spawner timers (Q1)."""
        if params.stale_spawn_timers:
            last, has = state.spawner_last, state.spawner_set
        else:
            last, has = jnp.zeros_like(state.spawner_last), jnp.zeros_like(state.spawner_set)
        new_state = _fresh_state(key, params, last, has)
        # Fresh cars stand on distinct approaches, >= 44.6 m apart along x or y, so nobody is inside
        # anybody's sensor box (sensor_range <= 44, checked by the params; the reset test checks
        # the general computation gives zeros): skip the vehicles set, which runs on every step.
        obs = {
            "vehicles_set": jnp.zeros((MAX_AGENTS, VEHICLES_SET_ROWS, VEHICLE_FEATURES), jnp.float32),
            "state": state_observation(
                params, new_state.vehicle, new_state.route, new_state.prev_s, new_state.alive
            ),
        }
        return obs, new_state

    def step_env(self, key: jax.Array, state: IntersectionState, action: Any, params: IntersectionParams):
        """One multi-agent step (§4.2) plus the in-env episode restart.

        Returns per-slot ``(obs, state, reward, terminated, truncated, info)``; reward/terminated/
        truncated are meaningful where ``info["acted"]``. Info keys: ``acted``, ``alive``, ``final_obs``,
        ``episode_end``, ``done_reason`` (0 none, 1 completed route, 2 left road, 3 collided,
        4 non-finite action), ``nonfinite_action`` (per slot), ``trips_completed``,
        ``come_off_vehicles``, ``collided_vehicles``, ``mean_velocity``,
        ``episode_step`` (episode values at the end of this step, before any restart).
        """
        dtype = default_float()
        key_spawn, key_restart = jax.random.split(key)
        acted = state.alive
        step = state.step + 1
        time = step.astype(dtype) * params.dt

        # Physics (cars do not interact physically).
        control, invalid = self._checked_control(action, acted)
        stepped = vehicle_step(params.vehicle, state.vehicle, control)
        vehicle = _where_slots(acted, stepped, state.vehicle)

        # Route tracker (§6.1) and slip penalty (§6.2).
        xy = jnp.stack([vehicle.x, vehicle.y], axis=-1)
        reward, s, moved, goal = route_tracker(params, state.route, state.prev_xy, state.prev_s, xy)
        reward = reward - slip_penalty(params, vehicle) * params.dt
        velocity_sum = state.velocity_sum + jnp.sum(jnp.where(acted, moved / params.dt, 0.0))
        velocity_count = state.velocity_count + jnp.sum(acted, dtype=jnp.int32)

        goal = acted & goal & ~invalid
        reward = jnp.where(goal, 1.0, reward)
        reason = jnp.where(goal, COMPLETED_ROUTE, DONE_NONE)

        on_road = jax.vmap(
            lambda x, y, t: geo.rectangle_on_road(x, y, t, geo.VEHICLE_HALF_LENGTH, geo.VEHICLE_HALF_WIDTH)
        )(vehicle.x, vehicle.y, vehicle.theta)
        off_road = acted & ~on_road & ~invalid
        reward = jnp.where(off_road, -1.0, reward)
        reason = jnp.where(off_road, LEFT_ROAD, reason)

        u_x, u_y = body_velocity(vehicle)
        speed = jnp.sqrt(u_x * u_x + u_y * u_y)
        reward, hit, hard_pairs = collision_rewards(
            params, _poses(vehicle), speed, acted, state.spawn_seq, reward.astype(dtype)
        )
        reason = jnp.where(hit, COLLIDED, reason)
        reason = jnp.where(invalid, NONFINITE_ACTION, reason).astype(jnp.int32)
        reward = jnp.where(invalid, -1.0, reward).astype(dtype)
        terminated = acted & (goal | off_road | hit | invalid)

        ended = state.replace(
            vehicle=vehicle,
            prev_xy=jnp.where(acted[:, None], xy, state.prev_xy),
            prev_s=jnp.where(acted, s, state.prev_s),
            step=step,
            trips_completed=state.trips_completed + jnp.sum(goal, dtype=jnp.int32),
            come_off_vehicles=state.come_off_vehicles + jnp.sum(off_road, dtype=jnp.int32),
            collided_vehicles=state.collided_vehicles + hard_pairs,
            velocity_sum=velocity_sum,
            velocity_count=velocity_count,
        )
        ended, new = spawn_vehicles(key_spawn, params, ended, acted, time)

        # Observations of everyone in the scene now (terminating and new agents included).
        ended = ended.replace(alive=acted | new)
        final_obs = observe(params, ended)
        ended = ended.replace(alive=(acted & ~terminated) | new)

        # The training loop's restart (§8.4), done here.
        episode_end = step >= params.episode_steps
        restart_obs, restart_state = self.restart(key_restart, ended, params)
        next_state = jax.tree.map(lambda a, b: jnp.where(episode_end, a, b), restart_state, ended)
        obs = jax.tree.map(lambda a, b: jnp.where(episode_end, a, b), restart_obs, final_obs)

        reward = jnp.where(acted, reward, 0.0).astype(dtype)
        truncated = acted & ~terminated & episode_end
        info = {
            "acted": acted,
            "alive": next_state.alive,
            "final_obs": final_obs,
            "episode_end": episode_end,
            "done_reason": jnp.where(acted, reason, DONE_NONE).astype(jnp.int32),
            "nonfinite_action": invalid,
            "trips_completed": ended.trips_completed,
            "come_off_vehicles": ended.come_off_vehicles,
            "collided_vehicles": ended.collided_vehicles,
            "mean_velocity": ended.mean_velocity,
            "episode_step": step,
        }
        return obs, next_state, reward, terminated, truncated, info


def place_vehicles(
    params: IntersectionParams,
    poses,
    routes,
    speeds=None,
    alive=None,
    spawn_seq=None,
    max_vehicles: int | None = None,
    step: int = 0,
) -> IntersectionState:
    """A hand-built state (tests, demos): cars at ``poses`` (n, 3) on ``routes`` (n,) with forward
    body speeds ``speeds`` (n,) (axle speeds matching), in slots 0..n-1, spawner timers "none".

    The trackers start at the given positions. ``spawn_seq`` defaults to the slot index.
    ``max_vehicles`` defaults to n, so nothing spawns unless a car leaves.
    """
    dtype = default_float()
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    n = poses.shape[0]
    if n > MAX_AGENTS:
        raise ValueError(f"at most {MAX_AGENTS} vehicles, got {n}")
    routes = np.broadcast_to(np.asarray(routes, np.int32), (n,))
    if np.any((routes < 0) | (routes >= geo.NUM_ROUTES)):
        raise ValueError(f"routes must lie in 0..{geo.NUM_ROUTES - 1}, got {routes}")
    speeds = np.zeros(n) if speeds is None else np.broadcast_to(np.asarray(speeds, np.float64), (n,))
    pad = MAX_AGENTS - n
    full = np.concatenate([poses, np.tile([[0.0, 0.0, 0.0]], (pad, 1))])
    speed = np.concatenate([speeds, np.zeros(pad)])
    route = np.concatenate([routes, np.zeros(pad, np.int32)]).astype(np.int32)
    alive_arr = (
        np.arange(MAX_AGENTS) < n
        if alive is None
        else np.concatenate([np.asarray(alive, bool), np.zeros(pad, bool)])
    )
    seq = (
        np.arange(MAX_AGENTS)
        if spawn_seq is None
        else np.concatenate([np.asarray(spawn_seq), np.arange(n, 8)])
    )
    x, y, theta = (jnp.asarray(full[:, i], dtype) for i in range(3))
    v = jnp.asarray(speed, dtype)
    omega = v / params.vehicle.wheel_radius
    zero = jnp.zeros(MAX_AGENTS, dtype)
    vehicle = VehicleState(x, y, theta, jnp.cos(theta) * v, jnp.sin(theta) * v, zero, omega, omega, zero)
    xy = jnp.stack([x, y], -1)
    s, _ = _project(jnp.asarray(route), xy, dtype)
    zero_i = jnp.zeros((), jnp.int32)
    return IntersectionState(
        vehicle=vehicle,
        alive=jnp.asarray(alive_arr),
        spawn_seq=jnp.asarray(seq, jnp.int32),
        route=jnp.asarray(route),
        prev_xy=xy,
        prev_s=s,
        step=jnp.asarray(step, jnp.int32),
        max_vehicles=jnp.asarray(n if max_vehicles is None else max_vehicles, jnp.int32),
        next_seq=jnp.asarray(int(np.max(seq)) + 1, jnp.int32),
        spawner_last=jnp.zeros(NUM_SPAWNERS, dtype),
        spawner_set=jnp.zeros(NUM_SPAWNERS, bool),
        trips_completed=zero_i,
        come_off_vehicles=zero_i,
        collided_vehicles=zero_i,
        velocity_sum=jnp.zeros((), dtype),
        velocity_count=zero_i,
    )
