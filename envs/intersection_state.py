"""Params, state and constants of the Intersection scenario (docs/carenv-intersection.md).

Agents live in :data:`MAX_AGENTS` slots (leading axis of every per-agent array) with an ``alive``
mask; see ``envs.intersection`` for the scenario and its step order.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import intersection_geometry as geo
from envs.vehicle_state import VehicleParams, VehicleState

MAX_AGENTS = 8
NUM_SPAWNERS = 4
CURRICULUM = (1, 2, 4, 8)
# Curriculum probabilities proportional to 1/n (§8.3): (8, 4, 2, 1) / 15.
CURRICULUM_PROBS = tuple(float(p) for p in (1.0 / np.array(CURRICULUM)) / np.sum(1.0 / np.array(CURRICULUM)))

DONE_NONE, COMPLETED_ROUTE, LEFT_ROAD, COLLIDED, NONFINITE_ACTION = 0, 1, 2, 3, 4
# done_reason code -> the original's name (index = code).
DONE_REASONS = dict(enumerate(("", "CompletedRoute", "LeftRoad", "Collided", "NonFiniteAction")))

VEHICLES_SET_ROWS = 8  # XRLDMP's max_objects
VEHICLE_FEATURES = 7  # present, x, y, vx, vy, cos, sin
ODOMETRY_DIM = 6
# Timer comparison tolerance of Q13: the original's t = 15 x 0.1 is 1.5000000000000002 > 1.5.
SPAWN_TIME_TOLERANCE = 1e-6
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
    # Rewards (§6).
    k_forwards: float = 0.05
    k_tracking: float = 0.015
    slip_start_deg: float = 4.0
    slip_scale_deg: float = 20.0
    k_soft_collision: float = 0.5
    # Spawning (§3.3, §3.4).
    spawn_speed_range: tuple = (5.55, 8.33)
    spawn_jitter: float = 0.2
    spawn_interval: float = 1.5
    spawn_time_noise: float = 0.2
    # Ending an agent's episode, sensing and collision shapes.
    goal_margin: float = 5.0
    stationary_speed: float = 0.01
    sensor_range: float = 30.0
    soft_pad_long: float = geo.SOFT_PAD_LONG
    soft_pad_lat: float = geo.SOFT_PAD_LAT
    nav_spacing: float = 1.0
    # Static configuration.
    nav_points: int = struct.field(pytree_node=False, default=30)
    max_vehicles: int = struct.field(pytree_node=False, default=0)
    episode_steps: int = struct.field(pytree_node=False, default=600)
    # Quirk flags (§9), static.
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
