"""Recorded episodes as figures and attributions: any step's frame, a whole episode's frames, and
one JSON-ready row per step (which object weighed how much, and where it was).

The records come from :mod:`xrl_jax.explain.explanations`'s rollouts (device side); everything here runs on
host copies of them. Single-agent episodes follow the one ego car; intersection episodes follow a
vehicle slot, i.e. whichever car occupies it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from xrl_jax.explain.drawing import Glyph, explained_frame
from xrl_jax.explain.glyphs import StepExplanation, step_explanation
from xrl_jax.explain.scenes import (
    ObjectSet,
    ego_pose,
    intersection_objects,
    scene_for,
    scene_objects,
    slot_pose,
)


def _at(tree, t: int):
    return jax.tree.map(lambda x: np.asarray(x)[t], tree)


class _RecordedEpisode:
    """What both episode figures share: the record's valid length and the step-range check."""

    record: Any

    @property
    def length(self) -> int:
        return int(np.sum(np.asarray(self.record.valid)))

    def _check_step(self, t: int):
        if not 0 <= t < self.length:
            raise ValueError(f"step {t} is beyond the episode ({self.length} steps: 0..{self.length - 1})")


@dataclasses.dataclass
class EpisodeFigures(_RecordedEpisode):
    """Everything needed to draw any step of a recorded episode (host copies of the record)."""

    env_name: str
    env: Any
    params: Any
    record: Any  # xrl_jax.explain.EpisodeRecord as numpy
    neutral: bool = False
    mirrored: bool = False

    def step(self, t: int) -> tuple[StepExplanation, ObjectSet, Any]:
        self._check_step(t)
        explanation = _at(self.record.explanations, t)
        step = step_explanation(explanation, self.mirrored)
        state = _at(self.record.states, t)
        objects = scene_objects(
            scene_for(self.env_name),
            _at(self.record.obs, t),
            ego_pose(state),
            self.env,
            self.params,
            neutral=self.neutral and step.is_mixture,
            is_mixture=step.is_mixture,
        )
        return step, objects, state

    def frame(self, t: int, *, title: str = "", **options) -> tuple[np.ndarray, list[Glyph]]:
        """The frame of step ``t`` and its glyphs. ``options``: threshold, max_side, offset, and
        render_frame's width, height, hud."""
        step, objects, state = self.step(t)
        control = np.asarray(self.record.controls)[t]
        return explained_frame(
            self.env_name, state, self.params, control, step, objects, title=title, mirrored=self.mirrored,
            **options,
        )  # fmt: skip

    def frames(self, steps: Sequence[int] | None = None, **options) -> list[np.ndarray]:
        steps = range(self.length) if steps is None else steps
        title = options.pop("title", "")
        return [self.frame(t, title=f"{title} step {t}".strip(), **dict(options))[0] for t in steps]

    def attributions(self, threshold: float = 0.0) -> list[dict]:
        """One JSON-ready row per step: ego pose, action, control, reward and every present object's
        weight, world position and label (objects with weight < ``threshold`` left out)."""
        rows = []
        actions = np.asarray(self.record.actions)
        for t in range(self.length):
            step, objects, state = self.step(t)
            x, y, theta = ego_pose(state)
            items = attribution_items(step, objects, threshold)
            rows.append(
                {
                    "step": t,
                    "ego": {"x": x, "y": y, "theta": theta},
                    "action": np.asarray(actions[t]).tolist(),
                    "control": np.asarray(self.record.controls[t], np.float64).tolist(),
                    "reward": float(np.asarray(self.record.rewards)[t]),
                    "explained": bool(step.is_mixture),
                    "objects": items,
                }
            )
        return rows


def attribution_items(step: StepExplanation, objects: ObjectSet, threshold: float) -> list[dict]:
    """One step's attribution records: index, weight, world position and label of every present
    object with weight >= ``threshold`` (none for baselines, which have no per-object weights)."""
    if not step.is_mixture:
        return []
    items = []
    for i in np.flatnonzero(step.present & objects.present):
        if step.weights[i] >= threshold:
            wx, wy = objects.world_xy[i]
            items.append(
                {"index": int(i), "weight": float(step.weights[i]), "x": float(wx), "y": float(wy)}
                | objects.labels[i]
            )
    return items


def first_alive_slot(record) -> int | None:
    """The first slot holding a car at step 0 of a multi-agent record (the default ego), or None."""
    alive = np.flatnonzero(np.asarray(record.acted)[0])
    return int(alive[0]) if alive.size else None


def _stamp(frame: np.ndarray, text: str) -> np.ndarray:
    """``text`` in black at the top left of an RGB frame (the top view has no overlay hook); it
    also keeps the empty-slot frames of a video distinct, so GIF writers do not merge them."""
    if not text:
        return frame
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.asarray(frame, np.uint8))
    ImageDraw.Draw(image).multiline_text((4, 4), text, fill=(0, 0, 0))
    return np.asarray(image)


@dataclasses.dataclass
class IntersectionEpisodeFigures(_RecordedEpisode):
    """Frames and attributions of one recorded Intersection episode (host copy of a
    :class:`xrl_jax.explain.MultiAgentEpisodeRecord`) following vehicle slot ``slot``.

    The figure follows the *slot*, i.e. whichever car occupies it: after its car completed its
    route, left the road or crashed, the slot may be refilled by a new car, which the frames then
    follow (the title names the car by its spawn number and says "new car" where it changed).
    Steps where the slot is empty are drawn as the top view of the whole crossing, without glyphs.
    """

    params: Any
    record: Any
    slot: int
    neutral: bool = True
    mirrored: bool = False

    def __post_init__(self):
        num_slots = np.asarray(self.record.acted).shape[-1]
        if isinstance(self.slot, bool) or not 0 <= int(self.slot) < num_slots:
            raise ValueError(f"slot {self.slot} out of range: the intersection has slots 0..{num_slots - 1}")
        self.slot = int(self.slot)

    def occupied(self, t: int, slot: int | None = None) -> bool:
        """Whether ``slot`` (default: the followed one) holds a car in state s_t."""
        return bool(np.asarray(self.record.acted)[t, self.slot if slot is None else slot])

    def car(self, t: int, slot: int | None = None) -> int | None:
        """Spawn number of the car in ``slot`` at step t (None if empty)."""
        slot = self.slot if slot is None else slot
        return int(np.asarray(self.record.states.spawn_seq)[t, slot]) if self.occupied(t, slot) else None

    def new_car(self, t: int) -> bool:
        """The followed slot holds at step t a different car than at its previous occupied step."""
        occupied = np.asarray(self.record.acted)[: t + 1, self.slot]
        before = np.flatnonzero(occupied[:t])
        if not occupied[t] or before.size == 0:
            return False
        seq = np.asarray(self.record.states.spawn_seq)[:, self.slot]
        return bool(seq[before[-1]] != seq[t])

    def step(self, t: int, slot: int | None = None):
        """``(StepExplanation, ObjectSet, state)`` of ``slot`` at step t; the first two are None
        when the slot is empty."""
        self._check_step(t)
        slot = self.slot if slot is None else slot
        state = _at(self.record.states, t)
        if not self.occupied(t, slot):
            return None, None, state
        explanation = jax.tree.map(lambda x: np.asarray(x)[t, slot], self.record.explanations)
        step = step_explanation(explanation, self.mirrored)
        objects = intersection_objects(state, _at(self.record.obs, t), slot, self.neutral, step.is_mixture)
        return step, objects, state

    def title(self, t: int, prefix: str = "") -> str:
        car = self.car(t)
        who = f"slot {self.slot} empty" if car is None else f"slot {self.slot} car {car}"
        if self.new_car(t):
            who += " (new car)"
        return f"{prefix} step {t}\n{who}".strip()

    def frame(self, t: int, *, title: str = "", **options) -> tuple[np.ndarray, list[Glyph]]:
        """The frame of step ``t`` and its glyphs (none when the slot is empty: top view).
        ``options``: threshold, max_side, offset, and render_frame's width, height, hud."""
        step, objects, state = self.step(t)
        if step is None:
            from envs import render

            size = {k: options[k] for k in ("width", "height") if k in options}
            frame = render.render_intersection_state(state, self.params, ego_slot=None, **size)
            return _stamp(frame, title), []
        controls = np.asarray(self.record.controls)[t]
        return explained_frame(
            "intersection", state, self.params, controls, step, objects, title=title, ego_slot=self.slot,
            mirrored=self.mirrored, **options,
        )  # fmt: skip

    def frames(self, steps: Sequence[int] | None = None, **options) -> list[np.ndarray]:
        steps = range(self.length) if steps is None else steps
        prefix = options.pop("title", "")
        return [self.frame(t, title=self.title(t, prefix), **dict(options))[0] for t in steps]

    def attributions(self, threshold: float = 0.0, all_slots: bool = False) -> list[dict]:
        """JSON-ready rows: per step one row of the followed slot (also when it is empty:
        ``"alive": false`` and no objects), or with ``all_slots`` one row per occupied slot.
        A row holds step, slot, car, the ego pose, action, control, reward, end flags and every
        present object's index, weight, world position and label ("neutral" or a vehicle with its
        observation row, slot and car)."""
        record = self.record
        num_slots = np.asarray(record.acted).shape[-1]
        rows = []
        for t in range(self.length):
            slots = [s for s in range(num_slots) if self.occupied(t, s)] if all_slots else [self.slot]
            for slot in slots:
                step, objects, state = self.step(t, slot)
                row = {"step": t, "slot": slot, "car": self.car(t, slot), "alive": step is not None}
                if step is None:
                    rows.append({**row, "ego": None, "explained": False, "objects": []})
                    continue
                x, y, theta = slot_pose(state, slot)
                items = attribution_items(step, objects, threshold)
                row.update(
                    ego={"x": x, "y": y, "theta": theta},
                    action=np.asarray(record.actions)[t, slot].tolist(),
                    control=np.asarray(record.controls[t, slot], np.float64).tolist(),
                    reward=float(np.asarray(record.rewards)[t, slot]),
                    terminated=bool(np.asarray(record.terminated)[t, slot]),
                    truncated=bool(np.asarray(record.truncated)[t, slot]),
                    done_reason=int(np.asarray(record.done_reason)[t, slot]),
                    explained=bool(step.is_mixture),
                    objects=items,
                )
                rows.append(row)
        return rows


def write_attributions(rows: Sequence[dict], path: str | Path) -> Path:
    """JSON lines, one per step."""
    path = Path(path)
    with open(path, "w") as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + "\n")
    return path
