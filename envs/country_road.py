"""Country Road: the paper's cone track (``racing`` of docs/carenv-single-agent.md §1.1, §7.2).

Observation ``{"state": (6,), "cones_set": (100, 5)}``: rows ``[present, x/45, y/45, is_blue,
is_yellow]`` for the remaining cones strictly inside the body-frame box −15 < x < 45, −30 < y < 30,
in storage order, present rows first and zero padding after (§7.2). Blue (type 1) cones are on
the driver's right, yellow (type 2) on the left. Hitting a cone costs 0.2 and removes it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from envs.core import Box
from envs.racing import RacingEnv, RacingParams
from envs.ring_geometry import TrackView, cone_body_positions
from envs.vehicle_state import VehicleState

MAX_VISIBLE_CONES = 100


class CountryRoad(RacingEnv):
    """Cone track; continuous Box(-1, 1, (3,)) actions, or the 12-way table with ``discrete=True``."""

    has_cones = True
    sensor_key = "cones_set"

    def _sensor_space(self, params: RacingParams | None = None):
        return Box(-jnp.inf, jnp.inf, (MAX_VISIBLE_CONES, 5), jnp.float32)

    def _sensor(self, params: RacingParams, view: TrackView, vehicle: VehicleState, cone_alive, s):
        dtype = vehicle.x.dtype
        bx, by = cone_body_positions(view, vehicle)
        x_min, x_max, y_min, y_max = params.cone_bbox
        visible = cone_alive & (bx > x_min) & (bx < x_max) & (by > y_min) & (by < y_max)
        # Compact the visible cones to the front, keeping storage order (fixed shapes): scatter the
        # source index of each visible cone to its rank, then gather (much cheaper than row scatters).
        count = visible.shape[0]
        rank = _cumsum(visible.astype(jnp.int32)) - 1
        slot = jnp.where(visible & (rank < MAX_VISIBLE_CONES), rank, MAX_VISIBLE_CONES)
        source = (
            jnp.full((MAX_VISIBLE_CONES + 1,), count, jnp.int32)
            .at[slot]
            .set(jnp.arange(count, dtype=jnp.int32), mode="drop")[:MAX_VISIBLE_CONES]
        )
        present = source < count
        source = jnp.minimum(source, count - 1)
        cone_type = view.cone_type[source]
        columns = [
            present.astype(dtype),
            jnp.where(present, bx[source] / params.cone_normaliser, 0),
            jnp.where(present, by[source] / params.cone_normaliser, 0),
            (present & (cone_type == 1)).astype(dtype),
            (present & (cone_type == 2)).astype(dtype),
        ]
        return jnp.stack(columns, axis=-1).astype(jnp.float32)


def _cumsum(values):
    """Inclusive cumulative sum of a 1-D array as a sequential scan.

    On XLA CPU this is cheaper than ``jnp.cumsum`` once vmapped (the scan runs over the cone axis
    with the batch as contiguous vectors, instead of a reduce-window over a strided axis).
    """
    return jax.lax.scan(lambda total, x: (total + x, total + x), jnp.zeros((), values.dtype), values)[1]
