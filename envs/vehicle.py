"""Dynamic single-track vehicle with Dugoff-type tyres: the CarEnv v1.2 racing car in pure JAX.

Reference: docs/carenv-single-agent.md §2 (model), §9 (pitfalls). This module steps the car; its
params, state, frames and odometry observation are in ``envs.vehicle_state`` (re-exported here).

Everything is elementwise: a ``VehicleState`` whose fields share any batch shape is stepped in one
call, and ``jax.vmap`` works as well. The 20 physics sub-steps run in a ``lax.fori_loop`` whose
body holds no branches (``jnp.where`` only). Per-step constants (steering rotation, brake moments,
engine limits, stiffness x load products, h/m ...) are computed once per environment step.

Three rounding-level departures from the original's literal operation order make the sub-step
about twice as fast on CPU. Measured on the golden files: float64 replays stay within 1e-11 of the
recording (tolerance 1e-6); float32 stays within 3e-4 on the vehicle runs and 1.1e-3 on the
episodes (wheel speeds x r_w, stiff at 8 m/s), like a literal float32 port (4e-4 / 5e-4):

* the world velocity gets the world-frame acceleration, v' = v + h W(theta)(F)/m, instead of the
  round trip u' = B(theta)(v) + hF/m, v' = W(theta)(u') (§2.5 item 29 states both are equal);
* cos/sin of the heading are not re-evaluated every sub-step but rotated along by the same angle
  increments h r' that update theta, and re-derived from theta at every environment step;
* the loop is "rotated" by half a sub-step: each sub-step leaves its standstill snap (item 31)
  and position update (item 32) pending and the next one settles them first; the floating-point
  operations are the same, but the snap then reads materialised loop values, so XLA does not
  re-evaluate the whole force chain in every fusion that needs v', r' or p'.

The model is ill-conditioned below ~5 m/s with rolling wheels and at the exact-zero wheel-lock /
standstill switches (§2.6): it is reproduced faithfully, not "fixed". Those switches compare
against exact zeros, which the lock and the snap write; keep that logic exact when editing.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from envs.vehicle_state import (
    VEHICLE_HALF_LENGTH,
    VEHICLE_HALF_WIDTH,
    VehicleParams,
    VehicleState,
    body_velocity,
    odometry_observation,
    world_to_body,
)

__all__ = [  # the vehicle_state names are re-exported: callers import them from here
    "VEHICLE_HALF_LENGTH",
    "VEHICLE_HALF_WIDTH",
    "VehicleDiagnostics",
    "VehicleParams",
    "VehicleState",
    "body_velocity",
    "odometry_observation",
    "slip_ratio",
    "steering_actuator",
    "tyre_force",
    "vehicle_step",
    "vehicle_step_with_diagnostics",
    "world_to_body",
]

# Small constants of the original, part of the model's definition (§2.5).
_ENGINE_EPS = 1e-5  # engine torque divides by |omega| + this
_SLIP_EPS = 1e-10  # slip-ratio denominator guard
_TAN_ALPHA_EPS = 1e-3  # "safe" slip-angle tangent guard
_LAMBDA_EPS = 1e-10  # Dugoff lambda denominator guard
_SLIPPING_LAMBDA = 0.3  # tyre reported as slipping when lambda <= this
_BRAKING_THRESHOLD = 0.05  # brake-light flag when b > this
_STANDSTILL_SPEED_SQ = 0.01  # (0.1 m/s)^2
_STANDSTILL_YAW_RATE = 0.05
_STANDSTILL_OMEGA = 1e-5


class VehicleDiagnostics(NamedTuple):
    """Quantities of the LAST sub-step of an env step, from the state at its start (§2.5 item 33)."""

    slip_ratio: jax.Array  # (..., 2): sigma_f, sigma_r
    force_front_body: jax.Array  # (..., 2): front tyre force rotated into the body frame
    force_rear_body: jax.Array  # (..., 2): rear tyre force (body frame = rear wheel frame)
    slipping: jax.Array  # (..., 2) bool: lambda <= 0.3, front / rear
    braking: jax.Array  # bool: b > 0.05 (brake lights only)


def tyre_force(c_sigma, c_alpha, slip_ratio, w_x, w_y, mu, f_z):
    """Coupled Dugoff-type tyre of CarEnv (§2.5 items 9-14), in the tyre's own frame.

    Returns ``(F_x, F_y, slipping)``. Stiffnesses are per unit load; the original uses (1 + |sigma|)
    denominators and a clamped slip-angle tangent w_y / (|w_x| + 1e-3), not the textbook forms.
    """
    return _tyre(c_sigma * f_z, c_alpha * f_z, mu * f_z, slip_ratio, w_x, w_y)


def _tyre(k_sigma, k_alpha, mu_fz, sigma, w_x, w_y):
    """``tyre_force`` with the load products precomputed (hot path)."""
    inv_slip = 1.0 / (1.0 + jnp.abs(sigma))
    tan_alpha = w_y / (jnp.abs(w_x) + _TAN_ALPHA_EPS)
    fx_lin = k_sigma * sigma * inv_slip
    fy_lin = -k_alpha * tan_alpha * inv_slip
    lam = mu_fz / (2.0 * jnp.sqrt(fx_lin * fx_lin + fy_lin * fy_lin) + _LAMBDA_EPS)
    # lambda <= 1 is inclusive (§2.6).
    scale = jnp.where(lam <= 1.0, lam * (2.0 - lam), 1.0)
    return scale * fx_lin, scale * fy_lin, lam <= _SLIPPING_LAMBDA


def slip_ratio(omega, wheel_radius, ground_speed):
    """Longitudinal slip (omega*r_w - w_x) / (max(|omega*r_w|, |w_x|) + 1e-10); in [-2, 2]."""
    wheel_speed = omega * wheel_radius
    return (wheel_speed - ground_speed) / (
        jnp.maximum(jnp.abs(wheel_speed), jnp.abs(ground_speed)) + _SLIP_EPS
    )


def steering_actuator(params: VehicleParams, steer, command):
    """Rate-limited steering (§2.3): move towards command*delta_max by at most dt*rate, no overshoot.

    Applied once per ENVIRONMENT step with the full dt.
    """
    target = jnp.clip(command * params.max_steer, -params.max_steer, params.max_steer)
    direction = jnp.sign(target - steer)
    candidate = jnp.clip(
        steer + params.dt * params.max_steer_rate * direction, -params.max_steer, params.max_steer
    )
    return jnp.where(direction != jnp.sign(target - candidate), target, candidate)


def _axle_brake(omega, drive_sum, brake_available):
    """Brake moment actually applied and whether it dominates (§2.5 items 18-19).

    A stopped wheel (omega == 0 exactly) gets static friction that cancels the other moments up
    to the available amount; a turning wheel gets the full moment against its rotation.
    """
    applied = jnp.where(
        omega == 0.0,
        jnp.clip(-drive_sum, -brake_available, brake_available),
        -jnp.sign(omega) * brake_available,
    )
    dominates = (jnp.abs(applied) > jnp.abs(drive_sum)) & (jnp.sign(applied) != jnp.sign(drive_sum))
    return applied, dominates


class _StepConstants(NamedTuple):
    """Everything that is constant across the sub-steps of one environment step."""

    h: jax.Array
    cos_steer: jax.Array
    sin_steer: jax.Array
    brake_front: jax.Array
    brake_rear: jax.Array
    engine_power_x_throttle: jax.Array
    engine_torque_limit: jax.Array
    k_sigma_front: jax.Array
    k_alpha_front: jax.Array
    mu_fz_front: jax.Array
    k_sigma_rear: jax.Array
    k_alpha_rear: jax.Array
    mu_fz_rear: jax.Array
    wheel_radius: jax.Array
    half_wheelbase: jax.Array
    drag_gain: jax.Array
    h_over_mass: jax.Array
    h_over_inertia_front: jax.Array
    h_over_inertia_rear: jax.Array
    h_over_yaw_inertia: jax.Array
    rear_wheel_drive: bool


def _step_constants(params: VehicleParams, steer_used, throttle, brake, dtype) -> _StepConstants:
    def c(value):
        return jnp.asarray(value, dtype=dtype)

    f_z = params.axle_load
    rolling = params.rolling_moment
    h = params.dt / params.physics_substeps
    return _StepConstants(
        h=c(h),
        cos_steer=jnp.cos(steer_used),
        sin_steer=jnp.sin(steer_used),
        brake_front=brake * params.brake_torque * params.brake_balance + rolling,
        brake_rear=brake * params.brake_torque * (1.0 - params.brake_balance) + rolling,
        engine_power_x_throttle=params.engine_power * throttle,
        engine_torque_limit=params.engine_torque_max * throttle,
        k_sigma_front=c(params.longitudinal_stiffness_front * f_z),
        k_alpha_front=c(params.cornering_stiffness_front * f_z),
        mu_fz_front=c(params.mu_front * f_z),
        k_sigma_rear=c(params.longitudinal_stiffness_rear * f_z),
        k_alpha_rear=c(params.cornering_stiffness_rear * f_z),
        mu_fz_rear=c(params.mu_rear * f_z),
        wheel_radius=c(params.wheel_radius),
        half_wheelbase=c(params.wheelbase / 2.0),
        drag_gain=c(params.drag_gain),
        h_over_mass=c(h / params.mass),
        h_over_inertia_front=c(h / params.front_axle_inertia),
        h_over_inertia_rear=c(h / params.rear_axle_inertia),
        h_over_yaw_inertia=c(h / params.yaw_inertia),
        rear_wheel_drive=params.rear_wheel_drive,
    )


# Loop carry: (x, y, theta, vx, vy, r, omega_f, omega_r, cos(theta), sin(theta), slow) where v, r
# are before the pending standstill snap, (x, y) before the pending position update, and ``slow``
# is the snap's test on the OLD speed of the sub-step that left them pending (module docstring).
_Carry = tuple


def _settle(carry: _Carry, pending_h):
    """Apply the pending standstill snap and position update (``pending_h`` = 0 before the first)."""
    x, y, theta, vx, vy, r, omega_f, omega_r, cos_t, sin_t, slow = carry
    standstill = (
        slow
        & (jnp.abs(r) < _STANDSTILL_YAW_RATE)
        & (jnp.abs(omega_f) < _STANDSTILL_OMEGA)
        & (jnp.abs(omega_r) < _STANDSTILL_OMEGA)
    )
    r = jnp.where(standstill, 0.0, r)
    vx = jnp.where(standstill, 0.0, vx)
    vy = jnp.where(standstill, 0.0, vy)
    return x + pending_h * vx, y + pending_h * vy, theta, vx, vy, r, omega_f, omega_r, cos_t, sin_t


def _rotate(cos_t, sin_t, angle):
    """(cos, sin) of theta + angle from those of theta, for the small per-sub-step angles h*r.

    Taylor series to angle^8: relative truncation error < 1e-17 for |angle| < 0.03 (|r| < 6 rad/s),
    < 3e-14 for |angle| < 0.1. cos(angle) - 1 is kept separate to avoid cancellation, and one Newton
    step pulls (cos, sin) back to unit length, so float32 rounding cannot drift its norm.
    """
    a2 = angle * angle
    sin_d = angle * (1.0 + a2 * (-1.0 / 6.0 + a2 * (1.0 / 120.0 + a2 * (-1.0 / 5040.0))))
    cos_dm1 = -a2 * (0.5 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 * (1.0 / 40320.0))))
    c = cos_t + (cos_t * cos_dm1 - sin_t * sin_d)
    s = sin_t + (sin_t * cos_dm1 + cos_t * sin_d)
    f = 1.5 - 0.5 * (c * c + s * s)
    return c * f, s * f


def _substep(k: _StepConstants, carry: _Carry, pending_h):
    """One 5 ms semi-implicit Euler sub-step (§2.5); returns the new carry and diagnostics."""
    x, y, theta, vx, vy, r, omega_f, omega_r, cos_t, sin_t = _settle(carry, pending_h)
    rw = k.wheel_radius

    # Kinematics: body velocity, axle centres, front wheel frame (rotated by -delta).
    u_x = cos_t * vx + sin_t * vy
    u_y = -sin_t * vx + cos_t * vy
    lever = r * k.half_wheelbase
    front_lat = u_y + lever
    rear_lat = u_y - lever
    wf_x = k.cos_steer * u_x + k.sin_steer * front_lat
    wf_y = -k.sin_steer * u_x + k.cos_steer * front_lat

    # Engine on the driven axle: power limited, clipped to +-T_max*a (exactly 0 for a = 0).
    driven_omega = omega_r if k.rear_wheel_drive else omega_f
    engine = jnp.clip(
        k.engine_power_x_throttle / (jnp.abs(driven_omega) + _ENGINE_EPS),
        -k.engine_torque_limit,
        k.engine_torque_limit,
    )

    sigma_f = slip_ratio(omega_f, rw, wf_x)
    sigma_r = slip_ratio(omega_r, rw, u_x)
    ff_x, ff_y, slipping_f = _tyre(k.k_sigma_front, k.k_alpha_front, k.mu_fz_front, sigma_f, wf_x, wf_y)
    fr_x, fr_y, slipping_r = _tyre(k.k_sigma_rear, k.k_alpha_rear, k.mu_fz_rear, sigma_r, u_x, rear_lat)

    # Axle moments: tyre reaction from the wheel-frame longitudinal force, engine, brakes.
    drive_f = -ff_x * rw
    drive_r = -fr_x * rw
    if k.rear_wheel_drive:
        drive_r = drive_r + engine
    else:
        drive_f = drive_f + engine
    brake_f, dominates_f = _axle_brake(omega_f, drive_f, k.brake_front)
    brake_r, dominates_r = _axle_brake(omega_r, drive_r, k.brake_rear)

    # Chassis: front force back into the body frame (+delta), drag on both body components.
    ffb_x = k.cos_steer * ff_x - k.sin_steer * ff_y
    ffb_y = k.sin_steer * ff_x + k.cos_steer * ff_y
    force_x = ffb_x + fr_x - k.drag_gain * u_x * jnp.abs(u_x)
    force_y = ffb_y + fr_y - k.drag_gain * u_y * jnp.abs(u_y)
    yaw_moment = k.half_wheelbase * ffb_y - k.half_wheelbase * fr_y

    # Semi-implicit Euler: velocity with the force rotated by the OLD heading, heading with the NEW r.
    new_omega_f = omega_f + k.h_over_inertia_front * (drive_f + brake_f)
    new_omega_r = omega_r + k.h_over_inertia_rear * (drive_r + brake_r)
    new_r = r + k.h_over_yaw_inertia * yaw_moment
    new_theta = theta + k.h * new_r

    # Coulomb lock: a dominating brake that would reverse the wheel (or move a stopped one) holds it.
    new_omega_f = jnp.where(dominates_f & (jnp.sign(new_omega_f) != jnp.sign(omega_f)), 0.0, new_omega_f)
    new_omega_r = jnp.where(dominates_r & (jnp.sign(new_omega_r) != jnp.sign(omega_r)), 0.0, new_omega_r)

    new_carry = (
        x,
        y,
        new_theta,
        vx + k.h_over_mass * (cos_t * force_x - sin_t * force_y),
        vy + k.h_over_mass * (sin_t * force_x + cos_t * force_y),
        new_r,
        new_omega_f,
        new_omega_r,
        *_rotate(cos_t, sin_t, k.h * new_r),
        vx * vx + vy * vy < _STANDSTILL_SPEED_SQ,
    )
    diagnostics = (sigma_f, sigma_r, ffb_x, ffb_y, fr_x, fr_y, slipping_f, slipping_r)
    return new_carry, diagnostics


def _prepare(params: VehicleParams, state: VehicleState, control):
    control = jnp.asarray(control)
    if control.ndim < 1 or control.shape[-1] != 3:
        raise ValueError(f"control must have shape (..., 3) = (steer, throttle, brake), got {control.shape}")
    dtype = jnp.result_type(*jax.tree.leaves(state), control)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    state = jax.tree.map(lambda v: jnp.asarray(v, dtype=dtype), state)
    control = control.astype(dtype)
    command, throttle, brake = control[..., 0], control[..., 1], control[..., 2]
    # Steering delay quirk (§2.3): physics uses the angle from BEFORE this step's update.
    steer_used = state.steer
    new_steer = steering_actuator(params, state.steer, command)
    consts = _step_constants(params, steer_used, throttle, brake, dtype)
    shape = jnp.broadcast_shapes(*(jnp.shape(v) for v in jax.tree.leaves(state)), command.shape)
    fields = (
        state.x,
        state.y,
        state.theta,
        state.vx,
        state.vy,
        state.yaw_rate,
        state.omega_front,
        state.omega_rear,
    )
    carry = tuple(jnp.broadcast_to(v, shape) for v in fields)
    # Nothing pending before the first sub-step: slow = False disables the snap, pending_h = 0.
    carry = (*carry, jnp.cos(carry[2]), jnp.sin(carry[2]), jnp.zeros(shape, bool))
    return carry, consts, jnp.broadcast_to(new_steer, shape), brake > _BRAKING_THRESHOLD


def _pending_h(consts: _StepConstants, index):
    return jnp.where(index == 0, jnp.zeros_like(consts.h), consts.h)


def _finish(consts: _StepConstants, carry, new_steer) -> VehicleState:
    return VehicleState(*_settle(carry, consts.h)[:8], steer=new_steer)


def vehicle_step(params: VehicleParams, state: VehicleState, control, unroll: int = 1) -> VehicleState:
    """One environment step (§2.4): steering actuator, then ``physics_substeps`` sub-steps.

    ``control`` = (steering command in [-1, 1], throttle a in [0, 1], brake b in [0, 1]), i.e. the
    already mapped pedals (see ``envs.actions``). State fields and control may share any batch
    shape (``control`` with a trailing axis of 3). ``unroll`` is passed to the sub-step loop; 1 is
    fastest on CPU (unrolling lets XLA duplicate the force chain across sub-steps).
    """
    carry, consts, new_steer, _ = _prepare(params, state, control)
    carry = jax.lax.fori_loop(
        0,
        params.physics_substeps,
        lambda i, c: _substep(consts, c, _pending_h(consts, i))[0],
        carry,
        unroll=unroll,
    )
    return _finish(consts, carry, new_steer)


def vehicle_step_with_diagnostics(params: VehicleParams, state: VehicleState, control):
    """``vehicle_step`` that also returns the last sub-step's ``VehicleDiagnostics`` (slower)."""
    carry, consts, new_steer, braking = _prepare(params, state, control)
    zero = jnp.zeros_like(carry[0])
    diag0 = (zero,) * 6 + (zero > 0.0,) * 2

    def body(i, c):
        return _substep(consts, c[0], _pending_h(consts, i))

    carry, diag = jax.lax.fori_loop(0, params.physics_substeps, body, (carry, diag0))
    sigma_f, sigma_r, ffb_x, ffb_y, fr_x, fr_y, slipping_f, slipping_r = diag
    diagnostics = VehicleDiagnostics(
        slip_ratio=jnp.stack([sigma_f, sigma_r], axis=-1),
        force_front_body=jnp.stack([ffb_x, ffb_y], axis=-1),
        force_rear_body=jnp.stack([fr_x, fr_y], axis=-1),
        slipping=jnp.stack([slipping_f, slipping_r], axis=-1),
        braking=jnp.broadcast_to(braking, zero.shape),
    )
    return _finish(consts, carry, new_steer), diagnostics
