"""The racing car's params and state, its body box and frames, and the odometry observation.

Reference: docs/carenv-single-agent.md §2.1-§2.3 (params, state), §7.1 (odometry observation).
The data the scenarios, geometry and rendering read about a car; the dynamics that step it are in
``envs.vehicle`` (which re-exports these names).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

# The car body as a box around the CoG (§1.1): collisions with cones and between cars, and drawing.
VEHICLE_HALF_LENGTH = 1.905
VEHICLE_HALF_WIDTH = 0.74


# Odometry normalisers of §7.1 (the yaw-rate one is literally 6.28, not 2*pi).
_YAW_RATE_NORMALISER = 6.28
_WHEEL_SPEED_HEADROOM = 1.1


@struct.dataclass
class VehicleParams:
    """Constants of the racing car (§2.2 / §2.3), all SI. Leaves may be traced (vmapped sweeps)."""

    wheelbase: float = 2.4  # CoG exactly midway: l_f = l_r = wheelbase / 2
    mass: float = 750.0
    yaw_inertia: float = 812.0
    front_axle_inertia: float = 2.0
    rear_axle_inertia: float = 2.0
    engine_power: float = 60_000.0
    engine_torque_max: float = 1_200.0  # at the driven axle, no gearbox
    brake_torque: float = 3_000.0  # total, split by brake_balance
    brake_balance: float = 0.5  # fraction on the front axle
    mu_front: float = 1.05
    mu_rear: float = 1.05
    cornering_stiffness_front: float = 10.0  # per unit load (multiplied by F_z)
    longitudinal_stiffness_front: float = 10.0
    cornering_stiffness_rear: float = 12.0
    longitudinal_stiffness_rear: float = 12.0
    wheel_radius: float = 0.3
    rolling_resistance: float = 0.015
    drag_area_density: float = 0.86  # A * C_d * rho; drag gain is half of it
    max_steer: float = 0.52
    max_steer_rate: float = 1.0
    gravity: float = 9.81
    rear_wheel_drive: bool = struct.field(pytree_node=False, default=False)
    physics_substeps: int = struct.field(pytree_node=False, default=20)
    dt: float = struct.field(pytree_node=False, default=0.1)

    def __post_init__(self):
        if not isinstance(self.physics_substeps, int) or self.physics_substeps < 1:
            raise ValueError(f"physics_substeps must be a positive int, got {self.physics_substeps!r}")
        if not float(self.dt) > 0.0:
            raise ValueError(f"dt must be positive, got {self.dt!r}")

    @property
    def axle_load(self):
        """Static load per axle, m*g/2 (no load transfer anywhere)."""
        return self.mass * self.gravity / 2.0

    @property
    def rolling_moment(self):
        """Rolling resistance, modelled as an always-present brake moment per axle."""
        return self.rolling_resistance * self.axle_load * self.wheel_radius

    @property
    def drag_gain(self):
        return 0.5 * self.drag_area_density

    @property
    def top_speed(self):
        """Drag-limited top speed (P / k_d)^(1/3), used to normalise velocities."""
        return (self.engine_power / self.drag_gain) ** (1.0 / 3.0)

    @property
    def max_wheel_speed(self):
        return self.top_speed / self.wheel_radius


@struct.dataclass
class VehicleState:
    """Vehicle state (§2.1). ``vx, vy`` are the WORLD-frame CoG velocity; ``steer`` is the
    actuator angle after the last step, i.e. the one the next step's physics uses."""

    x: jax.Array
    y: jax.Array
    theta: jax.Array
    vx: jax.Array
    vy: jax.Array
    yaw_rate: jax.Array
    omega_front: jax.Array
    omega_rear: jax.Array
    steer: jax.Array

    @classmethod
    def at_pose(cls, x, y, theta) -> VehicleState:
        """A car at rest at the given pose, as after a reset (§3.1)."""
        dtype = jnp.result_type(float)
        x, y, theta = (jnp.asarray(v, dtype=dtype) for v in (x, y, theta))
        zero = jnp.zeros(jnp.broadcast_shapes(x.shape, y.shape, theta.shape), dtype)
        return cls(x + zero, y + zero, theta + zero, zero, zero, zero, zero, zero, zero)

    def to_vector(self) -> jax.Array:
        """(..., 9) in the golden-data order (x, y, theta, v_x, v_y, r, omega_f, omega_r, delta)."""
        return jnp.stack(
            [
                self.x,
                self.y,
                self.theta,
                self.vx,
                self.vy,
                self.yaw_rate,
                self.omega_front,
                self.omega_rear,
                self.steer,
            ],
            axis=-1,
        )

    @classmethod
    def from_vector(cls, vector) -> VehicleState:
        vector = jnp.asarray(vector)
        if vector.ndim < 1 or vector.shape[-1] != 9:
            raise ValueError(f"vehicle state vector must have shape (..., 9), got {vector.shape}")
        if not jnp.issubdtype(vector.dtype, jnp.floating):
            vector = vector.astype(jnp.result_type(float))
        return cls(*(vector[..., i] for i in range(9)))


def world_to_body(x_world, y_world, x, y, theta):
    """World points into the body frame of pose (x, y, theta): B(theta)(P - p) (§0)."""
    cos_t, sin_t = jnp.cos(theta), jnp.sin(theta)
    dx, dy = x_world - x, y_world - y
    return cos_t * dx + sin_t * dy, -sin_t * dx + cos_t * dy


def body_velocity(state: VehicleState):
    """Body-frame CoG velocity (u_x forward, u_y leftward) = B(theta)(v)."""
    cos_t, sin_t = jnp.cos(state.theta), jnp.sin(state.theta)
    return cos_t * state.vx + sin_t * state.vy, -sin_t * state.vx + cos_t * state.vy


def odometry_observation(params: VehicleParams, state: VehicleState) -> jax.Array:
    """The 6-value ``state`` observation of §7.1, float32, clipped to [-1, 1].

    Computed in the state's dtype, cast to float32, then clipped, as the original does.
    """
    u_x, u_y = body_velocity(state)
    wheel_norm = _WHEEL_SPEED_HEADROOM * params.max_wheel_speed
    raw = jnp.stack(
        [
            u_x / params.top_speed,
            u_y / params.top_speed,
            state.yaw_rate / _YAW_RATE_NORMALISER,
            state.steer / params.max_steer,
            state.omega_front / wheel_norm,
            state.omega_rear / wheel_norm,
        ],
        axis=-1,
    )
    return jnp.clip(raw.astype(jnp.float32), -1.0, 1.0)
