"""CarEnv action mappings (docs/carenv-single-agent.md §4): raw agent actions -> vehicle control (s, a, b).

The vehicle (``envs.vehicle.vehicle_step``) takes control = (steering command s in [-1, 1],
throttle a in [0, 1], brake b in [0, 1]). Agents act in one of three spaces:

* continuous Box(-1, 1, (3,)) = (steer, throttle pedal, brake pedal), CarEnv's native space (§4.1);
* Discrete(12), the paper's wrapper (§4.2): a fixed table of raw continuous actions;
* reduced Box(-1, 1, (2,)) = (steer, longitudinal), unused by the paper but part of CarEnv (§4.3).

All mappings are elementwise over leading batch axes and jittable.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

# Pedal map of §4.1: [-1, -0.9] -> 0 and [0.9, 1] -> 1, linear in between.
_PEDAL_SCALE = 1.8
_PEDAL_OFFSET = 0.5


def _default_float(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def _check_last_axis(x, size, what):
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(f"{what} must have shape (..., {size}), got {x.shape}")


def pedal_to_position(pedal):
    """Raw pedal in [-1, 1] -> pedal position in [0, 1] (``-1`` means released, not reverse)."""
    pedal = _default_float(pedal)
    # XLA rewrites x / constant as x * (1 / constant), which is off by one ulp for some pedals; hiding
    # the constant behind a barrier keeps a true division, bit-identical to the original in float64.
    # (The divisor is made data dependent so that it stays a full array under vmap, too.)
    scale = jax.lax.optimization_barrier(pedal * 0.0 + _PEDAL_SCALE)
    return jnp.clip(pedal / scale + _PEDAL_OFFSET, 0.0, 1.0)


def continuous_to_control(action) -> jax.Array:
    """Raw continuous action (..., 3) = (steer, throttle pedal, brake pedal) -> control (..., 3)."""
    action = _default_float(action)
    _check_last_axis(action, 3, "continuous action")
    steer = jnp.clip(action[..., 0], -1.0, 1.0)
    return jnp.stack([steer, pedal_to_position(action[..., 1]), pedal_to_position(action[..., 2])], axis=-1)


# §4.2: Cartesian product, steer slowest, brake fastest: i = 4*i_steer + 2*i_throttle + i_brake.
DISCRETE_STEER = (-1.0, 0.0, 1.0)
DISCRETE_PEDAL = (-1.0, 1.0)
DISCRETE_ACTIONS = np.array(
    list(itertools.product(DISCRETE_STEER, DISCRETE_PEDAL, DISCRETE_PEDAL)), dtype=np.float32
)
DISCRETE_ACTIONS.setflags(write=False)
NUM_DISCRETE_ACTIONS = len(DISCRETE_ACTIONS)  # 12
# The same table after the pedal map: pedals become exactly 0 / 1.
DISCRETE_CONTROLS = np.stack(
    [DISCRETE_ACTIONS[:, 0], (DISCRETE_ACTIONS[:, 1] > 0), (DISCRETE_ACTIONS[:, 2] > 0)], axis=-1
).astype(np.float32)
DISCRETE_CONTROLS.setflags(write=False)


def _check_index(index):
    index = jnp.asarray(index)
    if not jnp.issubdtype(index.dtype, jnp.integer):
        raise TypeError(f"discrete action index must be an integer array, got dtype {index.dtype}")
    try:
        concrete = np.asarray(index)
    except jax.errors.TracerArrayConversionError:  # traced: range cannot be checked here
        return index
    if ((concrete < 0) | (concrete >= NUM_DISCRETE_ACTIONS)).any():
        raise ValueError(f"discrete action index must be in [0, {NUM_DISCRETE_ACTIONS}), got {concrete}")
    return index


def _lookup(table, index):
    table = jnp.asarray(table, dtype=jnp.result_type(float))
    valid = (index >= 0) & (index < NUM_DISCRETE_ACTIONS)
    rows = table[jnp.clip(index, 0, NUM_DISCRETE_ACTIONS - 1)]
    return jnp.where(valid[..., None], rows, jnp.nan)


def invalid_discrete_index(index) -> jax.Array:
    """True where ``index`` (traced, any shape) selects no row of the table: outside [0, 12) or,
    for a float array, NaN, ±inf or a value that does not truncate into [0, 12). Checked before
    any cast to int32, which truncates towards zero and has no defined value for NaN or inf."""
    index = jnp.asarray(index)
    if jnp.issubdtype(index.dtype, jnp.integer):
        return (index < 0) | (index >= NUM_DISCRETE_ACTIONS)
    return ~jnp.isfinite(index) | (index <= -1) | (index >= NUM_DISCRETE_ACTIONS)


def discrete_to_action(index) -> jax.Array:
    """Discrete index (...) -> raw continuous action (..., 3) of the paper's 12-way table.

    Out-of-range traced indices give NaN rows (cannot raise under jit; NaN makes the bug visible).
    """
    return _lookup(DISCRETE_ACTIONS, _check_index(index))


def discrete_to_control(index) -> jax.Array:
    """Discrete index (...) -> vehicle control (..., 3); same as mapping ``discrete_to_action``."""
    return _lookup(DISCRETE_CONTROLS, _check_index(index))


def reduced_to_action(action) -> jax.Array:
    """Reduced action (..., 2) = (steer, longitudinal l) -> raw continuous action (..., 3) (§4.3).

    l >= 0 presses the throttle pedal to 2l - 1 with the brake released (-1); l < 0 presses the
    brake pedal to -2l - 1 with the throttle released.
    """
    action = _default_float(action)
    _check_last_axis(action, 2, "reduced action")
    longitudinal = action[..., 1]
    accelerate = longitudinal >= 0.0
    throttle = jnp.where(accelerate, 2.0 * longitudinal - 1.0, -1.0)
    brake = jnp.where(accelerate, -1.0, -2.0 * longitudinal - 1.0)
    return jnp.stack([action[..., 0], throttle, brake], axis=-1)


def reduced_to_control(action) -> jax.Array:
    """Reduced action (..., 2) -> vehicle control (..., 3)."""
    return continuous_to_control(reduced_to_action(action))
