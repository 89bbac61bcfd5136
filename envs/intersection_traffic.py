"""Traffic of the Intersection scenario: who is on the road. Spawning at the four approaches
(docs/carenv-intersection.md §2.3, §3.3, §3.4), the fresh state of an episode, and hand-built
states (:func:`place_vehicles`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs import intersection_geometry as geo
from envs.core import default_float
from envs.intersection_rules import project_on_routes, vehicle_poses
from envs.intersection_state import (
    CURRICULUM,
    CURRICULUM_PROBS,
    MAX_AGENTS,
    NUM_SPAWNERS,
    SPAWN_TIME_TOLERANCE,
    IntersectionParams,
    IntersectionState,
)
from envs.vehicle_state import VehicleState


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
    s, _ = project_on_routes(route, xy, dtype)
    return vehicle, route, xy, s


def where_slots(mask, new, old):
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old
    )


def _draw_max_vehicles(key, params: IntersectionParams):
    if params.max_vehicles > 0:
        return jnp.asarray(params.max_vehicles, jnp.int32)
    logits = jnp.log(jnp.asarray(CURRICULUM_PROBS, jnp.float32))
    return jnp.asarray(CURRICULUM, jnp.int32)[jax.random.categorical(key, logits)]


def fresh_state(key, params: IntersectionParams, spawner_last, spawner_set) -> IntersectionState:
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
    poses = vehicle_poses(state.vehicle)
    areas = jnp.asarray(geo.SPAWN_AREAS, dtype)
    touches = jax.vmap(
        lambda box: jax.vmap(
            lambda p: geo.rectangle_intersects_box(p, geo.VEHICLE_HALF_LENGTH, geo.VEHICLE_HALF_WIDTH, box)
        )(poses)
    )(areas)  # (4, 8)
    area_free = ~jnp.any(touches & occupied[None, :], axis=1)
    timer_ok = ~state.spawner_set | (time - state.spawner_last > params.spawn_interval - SPAWN_TIME_TOLERANCE)
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
        vehicle=where_slots(new, vehicle, state.vehicle),
        route=jnp.where(new, route, state.route),
        prev_xy=jnp.where(new[:, None], xy, state.prev_xy),
        prev_s=jnp.where(new, s, state.prev_s),
        spawn_seq=jnp.where(new, state.next_seq + free_rank, state.spawn_seq).astype(jnp.int32),
        next_seq=state.next_seq + n_new,
        spawner_last=jnp.where(taken, time + noise, state.spawner_last).astype(dtype),
        spawner_set=state.spawner_set | taken,
    )
    return state, new


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
    s, _ = project_on_routes(jnp.asarray(route), xy, dtype)
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
