"""The racing problem of Country Road and Tracking (docs/carenv-single-agent.md §3, §6, §8).

Both scenarios drive the same car on the same kind of track; they differ only in whether cones
exist (and can be hit) and in the sensor that is observed. This module holds everything they share:
params, state, the exact step order of §3.2, progress reward, cone collisions, idling and time
limits with integer counters, metrics, the off-track termination that OVERWRITES the reward, and the
track source (bank drawn at reset, or generation inside reset). Subclasses only add the sensor.

Tracks: ``params.tracks`` is a ``Track`` with a leading bank axis (size >= 1). With
``track_source="bank"`` (default) reset draws a bank index uniformly; the state stores only that
index (cheap to auto-reset under ``vmap``). A user track (``track_from_arrays``) is simply a bank of
size one (:func:`with_track`). ``RacingEnv.prepare`` (called by ``envs.make``) precomputes each bank
track's reset observation, so reset is a gather. A step never copies the bank track out: it reads
the few table entries it needs at ``[track_index, i]`` (:class:`TrackView`), and the projection is an
exact branch and bound over chunks of segments (:func:`project_point`). With
``track_source="generate"`` reset calls ``generate_track`` and the state carries the whole track
(costly under auto-reset: under vmap the reset, i.e. a track generation, runs every step).

Info (fixed shapes, every step): ``avg_track_velocity`` (the original's Metric.AvgTrackVelocity),
``cones_hit`` (Metric.ConesHit, cumulative, always 0 for Tracking), ``done_reason``
(:data:`DONE_NONE`/``LEFT_TRACK``/``MAX_TIME``/``IDLING`` = 0/1/2/3, as in the golden data, and
:data:`NONFINITE_ACTION` = 4), ``time_limit_truncated`` (= truncated), ``track_progress`` (m along the
travel direction), ``proj_s`` and ``dist_center`` (nearest centre-line point arc length in stored
order, distance), ``nonfinite_action`` (bool).

Invalid actions: a diverged policy must not poison the state or hang the step, so an action with a
NaN or ±inf entry (after the cast to the env's float dtype; a discrete index outside [0, 12), or a
float index that is not finite, counts the same) ends the episode: the car is stepped with the
neutral control (steering 0, pedals released), ``terminated`` is True with ``done_reason`` 4 (it
overrides the other reasons), the reward is ``offtrack_reward`` and ``info["nonfinite_action"]`` is
True. Finite continuous actions outside [-1, 1] are clipped (§4.1), however large.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import actions as actions_mod
from envs.core import Box, Dict, Discrete, Environment, default_float
from envs.racing_params import (
    RESET_CACHE_FIELDS,
    RacingParams,
    default_racing_params,
    stack_tracks,
    with_bank,
    with_track,
)
from envs.ring_geometry import (
    RingTables,
    TrackView,
    cone_body_positions,
    cone_hits,
    project_point,
    ring_tables,
)
from envs.track import Track
from envs.track_generator import generate_track
from envs.vehicle import VehicleState, odometry_observation, vehicle_step

DONE_NONE, LEFT_TRACK, MAX_TIME, IDLING, NONFINITE_ACTION = 0, 1, 2, 3, 4
# done_reason code -> the original's name (index = code).
DONE_REASONS = dict(enumerate(("", "LeftTrack", "MaxTime", "Idling", "NonFiniteAction")))

__all__ = [  # the params names are re-exported: callers import them from here
    "DONE_NONE",
    "DONE_REASONS",
    "IDLING",
    "LEFT_TRACK",
    "MAX_TIME",
    "NONFINITE_ACTION",
    "RESET_CACHE_FIELDS",
    "RacingEnv",
    "RacingParams",
    "RacingState",
    "check_action",
    "stack_tracks",
    "with_bank",
    "with_track",
]


@struct.dataclass
class RacingState:
    """Per-episode state. ``track``/``tables`` are only carried with ``track_source="generate"``."""

    vehicle: VehicleState
    track_index: jax.Array  # int32, index into params.tracks
    track: Track | None
    tables: RingTables | None
    cone_alive: jax.Array  # (MAX_CONES,) bool: present on the track and not hit yet
    step_count: jax.Array  # int32
    idle_count: jax.Array  # int32, consecutive idle steps
    prev_xy: jax.Array  # (2,) CoG at the previous step
    prev_s: jax.Array  # projection arc length at the previous step
    track_progress: jax.Array  # m along the travel direction
    velocity_sum: jax.Array  # sum of per-step along-track speeds (for the running mean)
    cones_hit: jax.Array  # int32, cumulative


class RacingEnv(Environment):
    """Shared racing logic; subclasses set ``has_cones`` and implement ``_sensor``/``_sensor_space``.

    ``discrete=True`` selects the paper's 12-way action table (§4.2); otherwise the action is
    the native Box(-1, 1, (3,)) (steer, throttle pedal, brake pedal) of §4.1.
    """

    has_cones: bool = True
    sensor_key: str = ""

    def __init__(self, discrete: bool = False):
        self.discrete = bool(discrete)

    def _config(self) -> tuple:
        """Static configuration; equal configs hash equal, so jit caches are shared between instances."""
        return (type(self), self.discrete)

    def __eq__(self, other) -> bool:
        return isinstance(other, RacingEnv) and self._config() == other._config()

    def __hash__(self) -> int:
        return hash(self._config())

    def __repr__(self) -> str:
        return f"{type(self).__name__}(discrete={self.discrete})"

    # ----- to implement in the scenarios -----
    def _sensor(self, params: RacingParams, view: TrackView, vehicle: VehicleState, cone_alive, s):
        raise NotImplementedError

    def _sensor_space(self, params: RacingParams | None):
        raise NotImplementedError

    # ----- API -----
    @property
    def name(self) -> str:
        return type(self).__name__ + ("Discrete" if self.discrete else "")

    @property
    def default_params(self) -> RacingParams:
        """The params ``envs.make`` gives this env without overrides (``envs.racing_params``)."""
        return default_racing_params(self)

    def action_space(self, params: RacingParams | None = None):
        if self.discrete:
            return Discrete(actions_mod.NUM_DISCRETE_ACTIONS)
        return Box(-1.0, 1.0, (3,), jnp.float32)

    def observation_space(self, params: RacingParams | None = None):
        return Dict({"state": Box(-1.0, 1.0, (6,), jnp.float32), self.sensor_key: self._sensor_space(params)})

    def current_track(self, state: RacingState, params: RacingParams) -> Track:
        """The episode's full ``Track`` (from the bank by index, or carried in the state)."""
        if state.track is not None:
            return state.track
        return jax.tree.map(lambda leaf: leaf[state.track_index], params.tracks)

    def _view(self, state: RacingState, params: RacingParams) -> TrackView:
        if state.track is not None:
            track = state.track
            return TrackView(state.tables, None, track.length, track.num_points, track.cone_type)
        tracks, row = params.tracks, state.track_index
        if params.tables is None:  # params built by hand: derive the tables of this track (slow)
            track = self.current_track(state, params)
            return TrackView(ring_tables(track), None, track.length, track.num_points, track.cone_type)
        return TrackView(
            params.tables, row, tracks.length[row], tracks.num_points[row], tracks.cone_type[row]
        )

    def _control(self, action):
        if self.discrete:
            return actions_mod.discrete_to_control(jnp.asarray(action, jnp.int32))
        return actions_mod.continuous_to_control(jnp.asarray(action, default_float()))

    def _checked_control(self, action):
        """``(control, invalid)``: the control, or the neutral zeros when the action is invalid
        (non-finite, or a discrete index outside the table; see the module docstring)."""
        if self.discrete:
            invalid = actions_mod.invalid_discrete_index(action)
        else:
            invalid = ~jnp.all(jnp.isfinite(jnp.asarray(action, default_float())))
        control = self._control(action)
        return jnp.where(invalid, jnp.zeros_like(control), control), invalid

    def _observation(self, params, view, vehicle, cone_alive, s) -> dict[str, jax.Array]:
        return {
            "state": odometry_observation(params.vehicle, vehicle),
            self.sensor_key: self._sensor(params, view, vehicle, cone_alive, s),
        }

    def _start(self, params: RacingParams, track: Track, tables: RingTables):
        """Reset observation and start arc length of a track (depends on nothing else)."""
        dtype = default_float()
        start = jnp.asarray(track.start_xy, dtype)
        vehicle = VehicleState.at_pose(start[0], start[1], track.start_theta)
        view = TrackView(tables, None, track.length, track.num_points, track.cone_type)
        s, _, _ = project_point(view, start[0], start[1])
        return self._observation(params, view, vehicle, self._initial_cones(track), s), s

    def _initial_cones(self, track: Track):
        alive = jnp.asarray(track.cone_present, bool)
        return alive if self.has_cones else jnp.zeros_like(alive)

    def prepare(self, params: RacingParams) -> RacingParams:
        """Precompute each bank track's reset observation and start arc length (makes reset a gather).

        ``envs.make`` calls this; the only constructor of the reset cache (see :class:`RacingParams`).
        Without it, reset computes them on the fly (correct, but slower under auto-reset + vmap).
        """
        if params.track_source != "bank" or params.tracks is None:
            return params
        if params.tables is None:
            params = with_bank(params, params.tracks)
        obs, s = _start_bank(self, params)
        return params.replace(start_s=s, reset_obs=obs, reset_cache_for=self._config())

    def reset_env(self, key: jax.Array, params: RacingParams):
        if params.track_source == "generate":
            track = generate_track(key)
            tables = ring_tables(track)
            obs, s = self._start(params, track, tables)
            return obs, self._initial_state(track, jnp.zeros((), jnp.int32), s, (track, tables))
        if params.track_source == "bank":
            if params.tracks is None:
                raise ValueError("track_source='bank' needs params.tracks (a bank of at least one track)")
            index = jax.random.randint(key, (), 0, params.bank_size, dtype=jnp.int32)
            return self.reset_on_track(params, index)
        raise ValueError(f"track_source must be 'bank' or 'generate', got {params.track_source!r}")

    def reset_on_track(self, params: RacingParams, index: jax.Array):
        """Start an episode on bank track ``index`` (deterministic: a reset draws nothing else).

        ``reset_env`` draws the index uniformly; a caller that assigns tracks itself (the fresh-track
        feed of :mod:`envs.track_feed`) calls this directly."""
        index = jnp.asarray(index, jnp.int32)
        pick = lambda leaf: leaf[index]
        if params.reset_obs is not None and params.reset_cache_for == self._config():
            track = params.tracks.replace(
                start_xy=pick(params.tracks.start_xy),
                start_theta=pick(params.tracks.start_theta),
                cone_present=pick(params.tracks.cone_present),
            )
            obs = {
                "state": pick(params.reset_obs["state"]),
                self.sensor_key: pick(params.reset_obs[self.sensor_key]),
            }
            s = pick(params.start_s)
        else:
            track = jax.tree.map(pick, params.tracks)
            tables = ring_tables(track) if params.tables is None else jax.tree.map(pick, params.tables)
            obs, s = self._start(params, track, tables)
        return obs, self._initial_state(track, index, s, (None, None))

    def _initial_state(self, track: Track, index, s, carried) -> RacingState:
        dtype = default_float()
        start = jnp.asarray(track.start_xy, dtype)
        zero = jnp.zeros((), dtype)
        return RacingState(
            vehicle=VehicleState.at_pose(start[0], start[1], track.start_theta),
            track_index=index,
            track=carried[0],
            tables=carried[1],
            cone_alive=self._initial_cones(track),
            step_count=jnp.zeros((), jnp.int32),
            idle_count=jnp.zeros((), jnp.int32),
            prev_xy=start,
            prev_s=jnp.asarray(s, dtype),
            track_progress=zero,
            velocity_sum=zero,
            cones_hit=jnp.zeros((), jnp.int32),
        )

    def step_env(self, key: jax.Array, state: RacingState, action: Any, params: RacingParams):
        del key  # the racing dynamics are deterministic
        dtype = default_float()
        view = self._view(state, params)
        vp = params.vehicle
        dt = jnp.asarray(vp.dt, dtype)

        # 1-3: action mapping, counter, vehicle update.
        control, invalid = self._checked_control(action)
        step_count = state.step_count + 1
        vehicle = vehicle_step(vp, state.vehicle, control)
        position = jnp.stack([vehicle.x, vehicle.y])

        # 4: cone collisions against the new pose; hit cones are removed for good.
        if self.has_cones:
            bx, by = cone_body_positions(view, vehicle)
            hit = state.cone_alive & cone_hits(bx, by)
            cone_alive = state.cone_alive & ~hit
            hits = jnp.sum(hit, dtype=jnp.int32)
        else:
            cone_alive = state.cone_alive
            hits = jnp.zeros((), jnp.int32)
        cones_hit = state.cones_hit + hits

        # 6 (geometry first; the sensor of step 5 reuses the projection).
        s, distance, tangent = project_point(view, vehicle.x, vehicle.y)
        reward = (
            -params.cone_penalty * hits
            + params.k_base
            + params.k_forwards * dt * (vehicle.vx * tangent[0] + vehicle.vy * tangent[1])
            - params.k_center * dt * distance
        )
        moved = jnp.sqrt(jnp.sum((position - state.prev_xy) ** 2))
        idle_count = jnp.where(moved / dt < params.idle_speed, state.idle_count + 1, 0)
        along = jnp.mod(state.prev_s - s, view.length)
        along = jnp.where(along > view.length / 2, along - view.length, along)
        velocity_sum = state.velocity_sum + along / dt
        avg_track_velocity = velocity_sum / step_count

        # Exactly one ending reason, in the priority order of §3.3.
        left_track = distance > params.track_width / 2
        max_time = step_count >= params.max_steps
        idling = idle_count >= params.max_idle_steps
        reason = jnp.where(
            left_track, LEFT_TRACK, jnp.where(max_time, MAX_TIME, jnp.where(idling, IDLING, DONE_NONE))
        )
        reason = jnp.where(invalid, NONFINITE_ACTION, reason).astype(jnp.int32)
        terminated = left_track | invalid
        truncated = ~terminated & (max_time | idling)
        reward = jnp.where(terminated, params.offtrack_reward, reward).astype(dtype)

        # 5: observation from the new state and the remaining cones.
        obs = self._observation(params, view, vehicle, cone_alive, s)

        new_state = state.replace(
            vehicle=vehicle,
            cone_alive=cone_alive,
            step_count=step_count,
            idle_count=idle_count.astype(jnp.int32),
            prev_xy=position,
            prev_s=s,
            track_progress=state.track_progress + along,
            velocity_sum=velocity_sum,
            cones_hit=cones_hit,
        )
        info = {
            "avg_track_velocity": avg_track_velocity,
            "cones_hit": cones_hit,
            "done_reason": reason,
            "time_limit_truncated": truncated,
            "track_progress": new_state.track_progress,
            "proj_s": s,
            "dist_center": distance,
            "nonfinite_action": invalid,
        }
        return obs, new_state, reward, terminated, truncated, info


@functools.partial(jax.jit, static_argnums=0)
def _start_bank(env: RacingEnv, params: RacingParams):
    return jax.vmap(env._start, in_axes=(None, 0, 0))(params, params.tracks, params.tables)


def check_action(env: RacingEnv, action) -> np.ndarray:
    """Host-side validation used by the Gymnasium adaptors: raises ValueError outside the space, on
    NaN/inf, on a complex action (casting would silently drop its imaginary part) and on a masked
    array (casting would silently use the masked entries' values)."""
    if np.ma.isMaskedArray(action):
        raise ValueError(f"action must be a plain array, got a masked array: {action!r}")
    arr = np.asarray(action)
    if np.iscomplexobj(arr):
        raise ValueError(f"action must be real, got complex dtype {arr.dtype}: {action!r}")
    if env.discrete:
        n = actions_mod.NUM_DISCRETE_ACTIONS
        if arr.shape != () or not np.issubdtype(arr.dtype, np.integer) or not 0 <= int(arr) < n:
            raise ValueError(f"action must be an integer in [0, {n}), got {action!r}")
        return arr.astype(np.int32)
    if arr.shape != (3,) or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"action must be a numeric array of shape (3,), got {action!r}")
    if np.any(~np.isfinite(arr)) or np.any(np.abs(arr) > 1.0):
        raise ValueError(f"action must lie in [-1, 1]^3 and be finite, got {action!r}")
    return arr.astype(np.float32)
