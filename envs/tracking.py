"""Tracking: the track seen through a centre-line lookahead (docs/carenv-single-agent.md §1.2).

No cones exist (no collisions, ``cones_hit`` stays 0). Observation ``{"state": (6,),
"trajectory_set": (25, 4)}``: row k = ``[1, 2k/25 − 1, x_k, y_k]`` where (x_k, y_k) is the body-frame
centre-line point k·2 m ahead (along the travel direction) of the nearest centre-line point, divided
by √2·2·25 and clipped to [−1, 1] (§7.3, §7.4; the index column keeps the paper's k/n quirk, so
it never reaches +1). The set is in the default float dtype (float64 under x64, as the original).
"""

from __future__ import annotations

import jax.numpy as jnp

from envs.core import Box, default_float
from envs.racing import RacingEnv, RacingParams
from envs.ring_geometry import TrackView, points_at_arclength
from envs.vehicle_state import VehicleState, world_to_body

LOOKAHEAD_POINTS = 25  # paper's override of CarEnv's 50 (spacing 2 m instead of 1 m: params)


class Tracking(RacingEnv):
    """Centre-line tracking; continuous Box(-1, 1, (3,)) actions, or 12-way with ``discrete=True``."""

    has_cones = False
    sensor_key = "trajectory_set"

    def __init__(self, discrete: bool = False, lookahead_points: int = LOOKAHEAD_POINTS):
        super().__init__(discrete)
        if int(lookahead_points) < 1:
            raise ValueError(f"lookahead_points must be >= 1, got {lookahead_points}")
        self.lookahead_points = int(lookahead_points)

    def _config(self) -> tuple:
        return (*super()._config(), self.lookahead_points)

    def __repr__(self) -> str:
        return f"Tracking(discrete={self.discrete}, lookahead_points={self.lookahead_points})"

    def _sensor_space(self, params: RacingParams | None = None):
        return Box(-1.0, 1.0, (self.lookahead_points, 4), jnp.float32)

    def _sensor(self, params: RacingParams, view: TrackView, vehicle: VehicleState, cone_alive, s):
        dtype = default_float()
        n = self.lookahead_points
        k = jnp.arange(n, dtype=dtype)
        # The travel direction is opposite to the stored order: k*spacing ahead = s - k*spacing stored.
        px, py = points_at_arclength(view, s - k * params.lookahead_spacing)
        bx, by = world_to_body(px, py, vehicle.x, vehicle.y, vehicle.theta)
        scale = jnp.sqrt(jnp.asarray(2.0, dtype)) * params.lookahead_spacing * n
        return jnp.stack(
            [
                jnp.ones_like(bx),
                2.0 * k / n - 1.0,
                jnp.clip(bx / scale, -1.0, 1.0),
                jnp.clip(by / scale, -1.0, 1.0),
            ],
            axis=-1,
        ).astype(dtype)
