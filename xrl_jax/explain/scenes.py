"""Where a step's observed objects are: scenario adapters from observation rows to world places.

Rows of an observation's object set hold ego-frame positions times a sensor normaliser; a
:class:`Scene` says which columns and which normaliser, so figures and attributions can put each
object's weight at the cone, trajectory point or car it came from. Multi-agent actors with a
neutral (state-only) component put it at the ego vehicle.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax
import numpy as np


@dataclasses.dataclass(frozen=True)
class ObjectSet:
    """The explanation's objects of one step, aligned with its weights (O,)."""

    world_xy: np.ndarray  # (O, 2); NaN for objects without a place (a baseline's whole observation)
    present: np.ndarray  # (O,) bool
    labels: tuple[dict, ...]  # per object, e.g. {"type": "cone", "colour": "blue"}
    side: np.ndarray  # (O,) where the glyph goes: +1 the ego's left, -1 its right, 0 up-right on screen
    ego_theta: float = 0.0  # the ego heading, which turns ``side`` into a direction


@dataclasses.dataclass(frozen=True)
class Scene:
    """What figures need to know about one scenario's observations.

    ``scale(env, params)`` is the sensor normaliser: ego-frame metres = row[x_col, y_col] · scale.
    ``label(row_index, row)`` names an object for the attribution export. ``offset_rule`` puts
    the glyphs beside the objects: "colour" (cones: yellow/left-boundary cones to the ego's left,
    blue ones to its right, i.e. off the road), "alternate" (sequence points: even indices left,
    odd right), "fixed" (up and to the right on the screen).
    """

    set_key: str
    x_col: int
    y_col: int
    scale: Callable[[Any, Any], float]
    label: Callable[[int, np.ndarray], dict]
    offset_rule: str


def _cone_label(index: int, row: np.ndarray) -> dict:
    return {"type": "cone", "colour": "blue" if row[3] > 0.5 else "yellow" if row[4] > 0.5 else "unknown"}


def _trajectory_label(index: int, row: np.ndarray) -> dict:
    return {"type": "trajectory_point", "trajectory_index": index}


def _vehicle_label(index: int, row: np.ndarray) -> dict:
    return {"type": "vehicle", "row": index}


SCENES: dict[str, Scene] = {
    "country_road": Scene("cones_set", 1, 2, lambda env, p: float(p.cone_normaliser), _cone_label, "colour"),
    "tracking": Scene(
        "trajectory_set",
        2,
        3,
        lambda env, p: math.sqrt(2.0) * float(p.lookahead_spacing) * int(env.lookahead_points),
        _trajectory_label,
        "alternate",
    ),
    # Multi-agent (docs/carenv-intersection.md §7.1): rows (present, x/30, y/30, ...) of the other
    # vehicles; the base frame comes from envs.render.render_intersection_state (drawing.render_base).
    "intersection": Scene("vehicles_set", 1, 2, lambda env, p: 30.0, _vehicle_label, "fixed"),
}


def scene_for(env_name: str) -> Scene:
    base = env_name.removesuffix("_discrete")
    if base not in SCENES:
        raise ValueError(f"no explanation figures for env {env_name!r}; known: {', '.join(SCENES)}")
    return SCENES[base]


def ego_to_world(points, pose) -> np.ndarray:
    """Ego-frame points (..., 2) (x forward, y left) to the world with pose (x, y, θ)."""
    points = np.asarray(points, np.float64)
    x, y, theta = (float(v) for v in pose)
    c, s = math.cos(theta), math.sin(theta)
    return np.stack(
        [x + c * points[..., 0] - s * points[..., 1], y + s * points[..., 0] + c * points[..., 1]], -1
    )


def scene_objects(
    scene: Scene, obs, pose, env, params, neutral: bool = False, is_mixture: bool = True
) -> ObjectSet:
    """World positions and labels of one step's observed objects (plus the neutral one at the ego).

    ``obs`` is one unbatched observation (numpy); ``pose`` = (x, y, θ) of the ego vehicle.
    Baselines get one pseudo-object without a position.
    """
    if not is_mixture:
        return ObjectSet(
            np.full((1, 2), np.nan), np.ones(1, bool), ({"type": "whole_observation"},), np.zeros(1)
        )
    rows = np.asarray(obs[scene.set_key], np.float64)
    present = rows[:, 0] > 0
    ego_xy = rows[:, [scene.x_col, scene.y_col]] * scene.scale(env, params)
    world = ego_to_world(ego_xy, pose)
    labels = tuple(scene.label(i, row) for i, row in enumerate(rows))
    if scene.offset_rule == "colour":
        side = np.array([1.0 if label.get("colour") == "yellow" else -1.0 for label in labels])
    elif scene.offset_rule == "alternate":
        side = np.where(np.arange(len(rows)) % 2 == 0, 1.0, -1.0)
    else:
        side = np.zeros(len(rows))
    if neutral:
        world = np.concatenate([np.asarray(pose, np.float64)[None, :2], world])
        present = np.concatenate([[True], present])
        labels = ({"type": "neutral"}, *labels)
        side = np.concatenate([[0.0], side])
    return ObjectSet(world, present, labels, side, float(pose[2]))


def ego_pose(state) -> tuple[float, float, float]:
    """(x, y, θ) of the ego vehicle of a racing state (one step)."""
    vehicle = state.vehicle
    return float(np.asarray(vehicle.x)), float(np.asarray(vehicle.y)), float(np.asarray(vehicle.theta))


def slot_pose(state, slot: int) -> tuple[float, float, float]:
    """(x, y, θ) of vehicle slot ``slot`` of a multi-agent state (one step)."""
    vehicle = jax.device_get(state.vehicle)
    return tuple(float(np.asarray(getattr(vehicle, k))[slot]) for k in ("x", "y", "theta"))


def intersection_objects(state, obs, slot: int, neutral: bool = True, is_mixture: bool = True) -> ObjectSet:
    """The explanation objects of slot ``slot``'s policy at one intersection step, labelled by car.

    ``obs`` is the env's per-slot observation; row k of the slot's ``vehicles_set`` (weight index
    k + 1 after the neutral component) is matched to the nearest other car of ``state`` and labelled
    ``{"type": "vehicle", "row": k, "slot": ..., "car": spawn_seq}``; the neutral component sits
    at the ego car.
    """
    ego_obs = jax.tree.map(lambda x: np.asarray(x)[slot], jax.device_get(obs))
    objects = scene_objects(
        SCENES["intersection"], ego_obs, slot_pose(state, slot), None, None,
        neutral=neutral and is_mixture, is_mixture=is_mixture,
    )  # fmt: skip
    if not is_mixture:
        return objects
    vehicle = jax.device_get(state.vehicle)
    cars_xy = np.stack([np.asarray(vehicle.x, np.float64), np.asarray(vehicle.y, np.float64)], -1)
    others = np.asarray(state.alive, bool).copy()
    others[slot] = False
    seq = np.asarray(state.spawn_seq)
    first_row = 1 if neutral else 0
    labels = list(objects.labels)
    for i in np.flatnonzero(objects.present[first_row:]) + first_row:
        if not others.any():
            break
        distance = np.where(others, np.linalg.norm(cars_xy - objects.world_xy[i], axis=-1), np.inf)
        match = int(np.argmin(distance))
        labels[i] = {**labels[i], "slot": match, "car": int(seq[match])}
    return dataclasses.replace(objects, labels=tuple(labels))
