"""A trained agent's whole evaluation driven again with its explanation at every step, as plain arrays
(:class:`ExplainedSteps`) for :mod:`xrl_jax.explain.statistics`.

Racing: every held-out track, the ego car explained; the Intersection: every evaluation episode, each
car an agent. Each step's objects get their ego-frame place, a kind (Country Road's cones by colour;
Tracking's centre-line points; the Intersection's other cars by how their approach meets the own: the
same approach, the opposite one (oncoming), a side one (crossing), and the neutral, state-only
component), the speed at which the ego closes in on them, and an identity that follows an object from
one step to the next (a cone's world place, a centre-line point's rank ahead, a car's spawn number).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from xrl_jax.explain.explanations import make_episode_rollout, make_multiagent_episode_rollout
from xrl_jax.explain.scenes import SCENES

AGREEMENT_STEPS = 4000  # steps per seed explained by every other seed (a uniform sample)


@dataclass(frozen=True)
class ExplainedSteps:
    """One seed's explained evaluation steps (N), over the explanation's object slots (O).

    ``steps_to_early_end[i]``: 0 at the step whose action ended the car's episode early (racing: it
    left the track or idled; the Intersection: it left the road or collided), +inf where the car
    reached the time limit or its goal.
    ``follows[i]``: step i is the next step of the same car as step i − 1 (so their weights can be
    compared); ``obs``: the observations the agent acted on, for explaining them with other seeds.
    """

    weights: np.ndarray  # (N, O)
    present: np.ndarray  # (N, O)
    xy: np.ndarray  # (N, O, 2) ego frame, m; NaN for the neutral component
    kind: np.ndarray  # (N, O) int, indices into ``kinds``
    identity: np.ndarray  # (N, O, D) same object at consecutive steps <=> within ``identity_tolerance``
    closing: np.ndarray  # (N, O) m/s at which the distance shrinks (NaN: neutral)
    speed: np.ndarray  # (N,) m/s of the ego car
    follows: np.ndarray  # (N,) bool
    steps_to_early_end: np.ndarray  # (N,) steps until this car's episode ends early (+inf: it does not)
    returns: np.ndarray  # (episodes,) each evaluation episode's return (all cars' for the Intersection)
    obs: Any  # (N, ...) per leaf
    kinds: tuple[str, ...]
    identity_tolerance: float

    @property
    def distance(self) -> np.ndarray:
        return np.linalg.norm(self.xy, axis=-1)

    @property
    def time_to_contact(self) -> np.ndarray:
        """Distance over closing speed for approaching objects; +inf for objects not approached."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.closing > 1e-6, self.distance / self.closing, np.inf)


def _object_weights(record, rows: np.ndarray) -> np.ndarray:
    """The explanation's weights per object slot (and the neutral component first, where the agent
    has one); NaN for a baseline, whose one pseudo-object is the whole observation."""
    if not getattr(record.explanations, "is_mixture", True):
        return np.full(rows.shape[:-1], np.nan)
    return np.asarray(record.explanations.weights, np.float64)


def _body_velocity(vx, vy, theta):
    """World-frame velocity turned into the car's frame (x forward, y left)."""
    c, s = np.cos(theta), np.sin(theta)
    return c * vx + s * vy, -s * vx + c * vy


def _with_neutral(arrays: dict, neutral: bool, shape_prefix: tuple[int, ...], kind_index: int) -> dict:
    """Prepend the neutral component's column (no place, not approached, its own kind and identity)."""
    if not neutral:
        return arrays
    column = {
        "present": np.ones((*shape_prefix, 1), bool),
        "xy": np.full((*shape_prefix, 1, 2), np.nan),
        "kind": np.full((*shape_prefix, 1), kind_index),
        "identity": np.full((*shape_prefix, 1, arrays["identity"].shape[-1]), -1.0),
        "closing": np.full((*shape_prefix, 1), np.nan),
    }
    return {
        k: np.concatenate([column[k], v], axis=len(shape_prefix)) if k in column else v
        for k, v in arrays.items()
    }


# ------------------------------------------------------------------------------------------------
# Racing: every held-out track, the ego car explained
# ------------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=4)  # one compilation per (env, agent, length): every seed reuses it
def _track_batch_rollout(env, agent, max_steps: int):
    """``run(key, params, tracks, tables, agent_state)``, jitted: one episode per track of the
    batch (``tracks`` leaves (B, 1, ...): a bank of one track each, as the evaluation gives them)."""
    rollout = make_episode_rollout(env, agent, max_steps)

    def run(key, params, tracks, tables, agent_state):
        def one(track, table):
            changes = {"tracks": track} if table is None else {"tracks": track, "tables": table}
            return rollout(key, params.replace(**changes), agent_state)

        return jax.vmap(one, in_axes=(0, None if tables is None else 0))(tracks, tables)

    return jax.jit(run)


def _racing_rollouts(trainer, agent_state, episodes: int, key, batch: int = 20):
    """The evaluation tracks driven again with explanations, ``batch`` tracks at a time (host copies)."""
    params = trainer.eval_params
    run = _track_batch_rollout(trainer.env, trainer.agent, int(params.max_steps) + 1)
    tables = getattr(params, "tables", None)
    for start in range(0, episodes, batch):
        part = slice(start, min(start + batch, episodes))
        tracks = jax.tree.map(lambda leaf, part=part: leaf[part, None], params.tracks)
        table = None if tables is None else jax.tree.map(lambda leaf, part=part: leaf[part, None], tables)
        yield jax.device_get(run(key, params, tracks, table, agent_state))


def _racing_steps(env_name: str, trainer, record) -> dict:
    """One batch of racing episodes (E, T, ...) as the flat arrays of :class:`ExplainedSteps`."""
    scene = SCENES[env_name.removesuffix("_discrete")]
    rows = np.asarray(record.obs[scene.set_key], np.float64)  # (E, T, O, F)
    valid = np.asarray(record.valid, bool)
    vehicle = record.states.vehicle
    theta = np.asarray(vehicle.theta, np.float64)
    vx, vy = np.asarray(vehicle.vx, np.float64), np.asarray(vehicle.vy, np.float64)
    xy = rows[..., [scene.x_col, scene.y_col]] * scene.scale(trainer.env, trainer.eval_params)
    forward, left = _body_velocity(vx, vy, theta)
    distance = np.linalg.norm(xy, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        closing = (forward[..., None] * xy[..., 0] + left[..., None] * xy[..., 1]) / distance
    if scene.set_key == "cones_set":
        kind = (rows[..., 4] > 0.5).astype(np.int64)  # 0 blue (right-hand) cone, 1 yellow (left-hand)
        c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
        world = np.stack(
            [
                np.asarray(vehicle.x, np.float64)[..., None] + c * xy[..., 0] - s * xy[..., 1],
                np.asarray(vehicle.y, np.float64)[..., None] + s * xy[..., 0] + c * xy[..., 1],
            ],
            -1,
        )
        identity, kinds = world, ("blue cone", "yellow cone")
    else:
        kind = np.zeros(rows.shape[:-1], np.int64)
        identity = np.broadcast_to(np.arange(rows.shape[-2], dtype=np.float64)[:, None], (*xy.shape[:-1], 1))
        kinds = ("centre-line point",)
    follows = valid & np.concatenate([np.zeros_like(valid[:, :1]), valid[:, :-1]], axis=1)
    length = valid.sum(-1)
    ended_early = np.asarray(record.terminated, bool)[np.arange(len(length)), np.maximum(length - 1, 0)]
    steps_left = (length - 1)[:, None] - np.arange(valid.shape[1])[None, :]
    arrays = {
        "weights": _object_weights(record, rows),
        "present": rows[..., 0] > 0,
        "xy": xy,
        "kind": kind,
        "identity": identity,
        "closing": closing,
        "speed": np.hypot(vx, vy),
        "follows": follows,
        "steps_to_early_end": np.where(ended_early[:, None], steps_left, np.inf),
    }
    neutral = arrays["weights"].shape[-1] == rows.shape[-2] + 1  # weight index 0: the neutral component
    arrays = _with_neutral(arrays, neutral, rows.shape[:2], len(kinds))
    flat = {k: v[valid] for k, v in arrays.items()}
    flat["obs"] = jax.tree.map(lambda leaf: np.asarray(leaf)[valid], record.obs)
    rewards = np.where(valid, np.asarray(record.rewards, np.float64), 0.0)
    return flat | {"returns": rewards.sum(-1), "kinds": kinds + (("neutral",) if neutral else ())}


# ------------------------------------------------------------------------------------------------
# The Intersection: every evaluation episode, every car an agent
# ------------------------------------------------------------------------------------------------

INTERSECTION_KINDS = ("same approach", "oncoming", "crossing", "neutral")


def _intersection_steps(record) -> dict:
    """One Intersection episode (T, 8 slots, ...) as flat arrays over the steps a slot held a car."""
    from envs.intersection_geometry import ROUTE_APPROACH

    acted = np.asarray(record.acted, bool)  # (T, S)
    rows = np.asarray(record.obs["vehicles_set"], np.float64)  # (T, S, O, 7)
    vehicle = record.states.vehicle
    x, y = np.asarray(vehicle.x, np.float64), np.asarray(vehicle.y, np.float64)  # (T, S)
    theta = np.asarray(vehicle.theta, np.float64)
    vx, vy = np.asarray(vehicle.vx, np.float64), np.asarray(vehicle.vy, np.float64)
    xy = rows[..., 1:3] * SCENES["intersection"].scale(None, None)  # (T, S, O, 2)
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    world = np.stack(
        [x[..., None] + c * xy[..., 0] - s * xy[..., 1], y[..., None] + s * xy[..., 0] + c * xy[..., 1]], -1
    )
    # Each row is the car standing where it says (§7.1 of docs/carenv-intersection.md lists the
    # others in slot order without naming them): the nearest other car of the same state.
    cars = np.stack([x, y], -1)  # (T, S, 2)
    gap = np.linalg.norm(world[:, :, :, None, :] - cars[:, None, None, :, :], axis=-1)  # (T, S, O, S')
    own = np.eye(acted.shape[1], dtype=bool)[None, :, None, :]
    match = np.argmin(np.where(own, np.inf, gap), axis=-1)  # (T, S, O) slot of the car of each row
    pick = lambda a: np.take_along_axis(
        np.broadcast_to(a[:, None, :], match.shape[:2] + a.shape[1:]), match, axis=-1
    )
    approach = ROUTE_APPROACH[np.asarray(record.states.route)]  # (T, S)
    own_approach = approach[..., None]
    other_approach = pick(approach)
    kind = np.where(other_approach == own_approach, 0, np.where(other_approach == (own_approach ^ 1), 1, 2))
    seq = np.asarray(record.states.spawn_seq)
    velocity = np.stack([vx, vy], -1)
    relative_velocity = np.stack([pick(vx), pick(vy)], -1) - velocity[:, :, None, :]
    offset = np.stack([pick(x), pick(y)], -1) - cars[:, :, None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        closing = -np.sum(offset * relative_velocity, -1) / np.linalg.norm(offset, axis=-1)
    same_car = np.concatenate([np.zeros_like(acted[:1]), (seq[1:] == seq[:-1]) & acted[:-1]], axis=0)
    arrays = {
        "weights": _object_weights(record, rows),
        "present": rows[..., 0] > 0,
        "xy": xy,
        "kind": kind,
        "identity": pick(seq).astype(np.float64)[..., None],
        "closing": closing,
        "speed": np.hypot(vx, vy),
        "follows": acted & same_car,
        "steps_to_early_end": _steps_to_early_end(record, acted, seq),
    }
    neutral = arrays["weights"].shape[-1] == rows.shape[-2] + 1  # weight index 0: the neutral component
    arrays = _with_neutral(arrays, neutral, acted.shape, INTERSECTION_KINDS.index("neutral"))
    # Slot by slot, so that a car's steps are consecutive (``follows`` looks one step back).
    by_slot = acted.T
    flat = {k: np.swapaxes(v, 0, 1)[by_slot] for k, v in arrays.items()}
    flat["obs"] = jax.tree.map(lambda leaf: np.swapaxes(np.asarray(leaf), 0, 1)[by_slot], record.obs)
    total = np.sum(np.where(acted, np.asarray(record.rewards, np.float64), 0.0))
    return flat | {"returns": np.array([total]), "kinds": INTERSECTION_KINDS}


LEFT_ROAD, COLLIDED = 2, 3  # done_reason codes of an Intersection car's early end


def _steps_to_early_end(record, acted: np.ndarray, seq: np.ndarray) -> np.ndarray:
    """(T, S) steps until the car in each slot ends early (left the road, collided); +inf if it does
    not (it completes its route, or the episode ends first). Backwards over time, all slots at once."""
    reason = np.asarray(record.done_reason)
    early = acted & np.isin(reason, (LEFT_ROAD, COLLIDED))
    steps = np.full(acted.shape, np.inf)
    upcoming = np.full(acted.shape[1], np.inf)  # the step of the next early end of the car in the slot
    for t in range(acted.shape[0] - 1, -1, -1):
        if t + 1 < acted.shape[0]:  # a different car (or none) next: its end is not this car's
            upcoming = np.where(acted[t + 1] & (seq[t + 1] == seq[t]), upcoming, np.inf)
        upcoming = np.where(early[t], t, upcoming)
        steps[t] = upcoming - t
    return steps


def _intersection_rollouts(trainer, agent_state, episodes: int, key):
    params = trainer.eval_params
    rollout = make_multiagent_episode_rollout(trainer.env, trainer.agent, int(params.episode_steps))
    for episode in range(episodes):
        yield jax.device_get(rollout(episode, key, params, agent_state))


# ------------------------------------------------------------------------------------------------
# One seed's steps, and the statistics over seeds
# ------------------------------------------------------------------------------------------------


def join_steps(parts: list[dict]) -> ExplainedSteps:
    """Batches of flat step arrays (the ``_*_steps`` adaptors' dicts) as one :class:`ExplainedSteps`."""
    fields = [k for k in parts[0] if k not in ("obs", "kinds")]
    joined = {k: np.concatenate([p[k] for p in parts]) for k in fields}
    obs = jax.tree.map(lambda *leaves: np.concatenate(leaves), *[p["obs"] for p in parts])
    return ExplainedSteps(**joined, obs=obs, kinds=tuple(parts[0]["kinds"]), identity_tolerance=0.05)


def explained_steps(cfg, trainer, agent_state, key=None) -> ExplainedSteps:
    """One seed's whole evaluation with its explanations, as :class:`ExplainedSteps`.

    Racing: the run's held-out tracks, the evaluation policy; the Intersection: its evaluation
    episodes (every car the agent). ``key`` feeds the policy's own randomness (XSAC samples).
    """
    key = jax.random.PRNGKey(0) if key is None else key
    from xrl_jax.train import scenario_kind

    figure = scenario_kind(cfg).figure  # what an explanation follows: a car on a track, or agent slots
    if figure == "slots":
        records = _intersection_rollouts(trainer, agent_state, cfg.eval_episodes, key)
        parts = [_intersection_steps(record) for record in records]
    elif figure == "track":
        records = _racing_rollouts(trainer, agent_state, cfg.eval_episodes, key)
        parts = [_racing_steps(cfg.env_name, trainer, record) for record in records]
    else:
        raise ValueError(f"explanation statistics read tracks or agent slots; {cfg.env} has neither")
    return join_steps(parts)


def agreement_sample(steps: ExplainedSteps, rng: np.random.Generator):
    """A uniform sample of ``AGREEMENT_STEPS`` of a seed's observations (all when fewer): what the
    other seeds' policies explain again, and what the deletion curves delete from."""
    n = len(steps.speed)
    pick = np.sort(rng.choice(n, size=min(n, AGREEMENT_STEPS), replace=False))
    return jax.tree.map(lambda leaf: leaf[pick], steps.obs)
