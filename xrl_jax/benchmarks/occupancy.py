"""How full the observation sets are: present objects per set, measured from rollouts.

The per-object layers compute on the present objects only (:mod:`xrl_jax.sets`), so what a run
costs depends on how many objects its sets hold. This module drives each scenario as
docs/performance.md describes and records what the observations held:

* Country Road and Tracking: the hand controller of docs/carenv-single-agent.md §8.3 at 8 m/s, one
  episode of up to 600 steps on each of ``num_tracks`` generated tracks, every step's observation
  until the episode ends;
* Intersection: the training curriculum (1, 2, 4 or 8 vehicles per episode) with its draws replaced
  by their expected shares (:func:`curriculum_envs`: 8 : 4 : 2 : 1 envs at each cap, p ∝ 1/n), each
  env ``steps`` steps (its 60 s restarts included); every observation of a vehicle that acted (the
  ones the trainer stores and learns from, :func:`stored_counts`), and how many vehicles acted per
  env step. Two drivers: the scripted one of :mod:`envs.intersection_driver` (``policy="scripted"``,
  the table's figures: after its 2,000 warm-up steps the trainer stores what a learning policy drives,
  and such a policy keeps its cars on the road and near each other, as the scripted one does) and
  uniformly random actions (``policy="random"``: the warm-up's, recorded beside them). Random drivers
  leave the road or collide within seconds, so their sets hold about a quarter as many vehicles
  (docs/performance.md, "How full the sets are").

:func:`rollout_observations` returns the observations themselves (the update benchmarks sample
their batches from them); :func:`summarise` turns them into the table that ``set_occupancy.json``
beside this module holds (package data: an installed package reads it too;
:func:`measure_occupancy`, i.e. ``python experiments/costs.py --measure-occupancy``, rewrites it) and
that the cost estimates read (:func:`load_occupancy`, :func:`overflow_probability`,
:func:`update_cost`, with :func:`~xrl_jax.benchmarks.timing.update_flops`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import hand_controller
from envs.intersection import CURRICULUM
from envs.intersection_driver import scripted_actions
from xrl_jax import config
from xrl_jax.agents import make_agent
from xrl_jax.benchmarks.timing import update_flops
from xrl_jax.networks import packed_only as networks_packed_only
from xrl_jax.sets import Packing
from xrl_jax.tracks import cached_track_bank, racing_env

SCENARIOS = ("tracking", "country_road", "intersection")
OCCUPANCY_FILE = Path(__file__).resolve().parent / "set_occupancy.json"  # package data (pyproject.toml)
SET_KEYS = {name: config.scenario(name).set_key for name in SCENARIOS}
DEFAULTS = {
    "tracking": {"num_tracks": 32, "steps": 600, "seed": 0},
    "country_road": {"num_tracks": 32, "steps": 600, "seed": 0},
    "intersection": {"num_envs": 60, "steps": 1200, "seed": 0, "policy": "scripted"},
}
INTERSECTION_POLICIES = {
    "scripted": "scripted driver (envs/intersection_driver.py) under the training curriculum",
    "random": "uniformly random actions under the training curriculum",
}


def _racing_observations(scenario: str, num_tracks: int, steps: int, seed: int) -> dict[str, Any]:
    env, params = racing_env(scenario, cached_track_bank(1000 + seed, num_tracks))
    tables = getattr(params, "tables", None)

    def own_params(i):
        pick = lambda leaf: jax.lax.dynamic_slice_in_dim(leaf, i, 1)
        changes = {"tracks": jax.tree.map(pick, params.tracks)}
        if tables is not None:
            changes["tables"] = jax.tree.map(pick, tables)
        return params.replace(**changes)

    def episode(i, key):
        p = own_params(i)
        obs, state = env.reset_env(key, p)

        def step(carry, key):
            obs, state, live = carry
            action = hand_controller.centre_line_action(env, state, p)
            next_obs, state, _, terminated, truncated, _ = env.step_env(key, state, action, p)
            return (next_obs, state, live & ~(terminated | truncated)), (obs, live)

        return jax.lax.scan(step, (obs, state, jnp.bool_(True)), jax.random.split(key, steps))[1]

    keys = jax.random.split(jax.random.PRNGKey(seed), num_tracks)
    obs, live = jax.device_get(jax.jit(jax.vmap(episode))(jnp.arange(num_tracks), keys))
    live = np.asarray(live).reshape(-1)
    observations = {k: np.asarray(v).reshape(-1, *v.shape[2:])[live] for k, v in obs.items()}
    policy = "hand controller at 8 m/s (docs/carenv-single-agent.md §8.3)"
    return {"observations": observations, "policy": policy}


def curriculum_envs(num_envs: int) -> dict[int, int]:
    """Envs per vehicle cap in the curriculum's proportions (p ∝ 1/n: 8 : 4 : 2 : 1 of every 15), so
    that pooling their env steps weights each cap as the curriculum's draws do on average, without
    the draws' noise: 3,000 training steps of 2 envs draw only 6 caps."""
    shares = {cap: max(CURRICULUM) // cap for cap in CURRICULUM}
    unit, rest = divmod(num_envs, sum(shares.values()))
    if rest or unit < 1:
        raise ValueError(
            f"num_envs must be a positive multiple of {sum(shares.values())} (envs at caps "
            f"{', '.join(f'{cap}: {share}' for cap, share in shares.items())}), got {num_envs}"
        )
    return {cap: unit * share for cap, share in shares.items()}


def stored_counts(present: np.ndarray, acted: np.ndarray) -> np.ndarray:
    """Present objects in each observation the trainer stores: one per slot that acted in an env
    step (its observation before the step), none for an empty slot. ``present`` (..., slots, rows)
    and ``acted`` (..., slots), boolean; returns (stored observations,) int, in order."""
    present, acted = np.asarray(present, bool), np.asarray(acted, bool)
    if present.shape[:-1] != acted.shape:
        raise ValueError(f"present {present.shape} and acted {acted.shape} disagree on the slots")
    return present.sum(-1)[acted]


def occupancy_weightings(present: np.ndarray, acted: np.ndarray) -> dict[str, float]:
    """Mean present objects per set, three ways (``present`` (steps, envs, slots, rows), ``acted``
    (steps, envs, slots)): ``per_observation`` over the observations the trainer stores (what a
    batch's sets hold: the packed rows follow it), ``per_env_step`` over env steps with an acting
    vehicle, each the mean of its acting vehicles (a crowded step counts once, not once per vehicle),
    and ``per_slot`` over every slot of every env step, empty slots counting 0."""
    counts = np.asarray(present, bool).sum(-1)
    acted = np.asarray(acted, bool)
    acting, others = acted.sum(-1), np.where(acted, counts, 0).sum(-1)
    steps = acting > 0
    return {
        "per_observation": float(stored_counts(present, acted).mean()),
        "per_env_step": float((others[steps] / acting[steps]).mean()),
        "per_slot": float(others.sum() / acted.size),
    }


def _drive_intersection(env, params, num_envs: int, steps: int, key, policy: str):
    """``num_envs`` envs of ``params`` driven by ``policy`` for ``steps`` steps: every step's
    observations before the step (steps, envs, slots, ...) and which slots acted (steps, envs, slots)."""

    def rollout(key):
        reset_key, key = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_envs), params)

        def step(carry, key):
            obs, state = carry
            act_key, step_key = jax.random.split(key)
            if policy == "scripted":
                action = jax.vmap(scripted_actions, in_axes=(0, None))(obs, params)
            else:
                action = jax.vmap(env.sample_actions, in_axes=(0, None))(
                    jax.random.split(act_key, num_envs), params
                )
            next_obs, state, *_, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(step_key, num_envs), state, action, params
            )
            return (next_obs, state), (obs, info["acted"])

        return jax.lax.scan(step, (obs, state), jax.random.split(key, steps))[1]

    obs, acted = jax.device_get(jax.jit(rollout)(key))
    return obs, np.asarray(acted)


def _intersection_observations(num_envs: int, steps: int, seed: int, policy: str) -> dict[str, Any]:
    if policy not in INTERSECTION_POLICIES:
        raise ValueError(f"unknown policy {policy!r}; valid: {', '.join(INTERSECTION_POLICIES)}")
    env, params = envs.make("intersection")  # continuous actions: the scripted driver's
    kept, present, acted, by_cap = [], [], [], {}
    for cap, count in curriculum_envs(num_envs).items():
        key = jax.random.fold_in(jax.random.PRNGKey(seed), cap)
        obs, cap_acted = _drive_intersection(env, params.replace(max_vehicles=cap), count, steps, key, policy)
        kept.append({k: np.asarray(v)[cap_acted] for k, v in obs.items()})
        present.append(np.asarray(obs["vehicles_set"])[..., 0] > 0)
        acted.append(cap_acted)
        by_cap[str(cap)] = {
            "acting_vehicles_per_env_step": round(float(cap_acted.sum() / (steps * count)), 3),
            "mean": round(occupancy_weightings(present[-1], cap_acted)["per_observation"], 3),
        }
    # The caps' envs side by side: one env step of the curriculum's mix.
    present, acted = np.concatenate(present, axis=1), np.concatenate(acted, axis=1)
    return {
        "observations": {k: np.concatenate([part[k] for part in kept]) for k in kept[0]},
        "policy": INTERSECTION_POLICIES[policy],
        "acting_vehicles_per_env_step": float(acted.sum() / (steps * num_envs)),
        "weightings": {k: round(v, 3) for k, v in occupancy_weightings(present, acted).items()},
        "by_cap": by_cap,
    }


# How each scenario is driven (the module's doc), taking its DEFAULTS' settings.
ROLLOUTS = {
    "tracking": functools.partial(_racing_observations, "tracking"),
    "country_road": functools.partial(_racing_observations, "country_road"),
    "intersection": _intersection_observations,
}


def rollout_observations(scenario: str, **settings: int | str) -> dict[str, Any]:
    """Real observations of ``scenario`` (the protocol of the module doc; ``settings`` override
    :data:`DEFAULTS`): ``{"observations": {key: (M, ...)}, "policy": str, ...}``."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; valid: {', '.join(SCENARIOS)}")
    unknown = sorted(set(settings) - set(DEFAULTS[scenario]))
    if unknown:
        raise ValueError(f"unknown setting(s) {unknown} for {scenario}; valid: {sorted(DEFAULTS[scenario])}")
    chosen = {**DEFAULTS[scenario], **settings}
    return {**ROLLOUTS[scenario](**chosen), "settings": chosen}


def present_counts(observations: dict[str, np.ndarray], scenario: str) -> np.ndarray:
    """Present objects per observation, (M,) int."""
    return np.asarray(observations[SET_KEYS[scenario]][..., 0] > 0).sum(-1)


def summarise(scenario: str, rollout: dict[str, Any]) -> dict[str, Any]:
    """The occupancy table of one scenario: how it was measured, the slots per set, the histogram of
    present objects per set (index = count) and its mean and percentiles."""
    objects = rollout["observations"][SET_KEYS[scenario]]
    counts = present_counts(rollout["observations"], scenario)
    slots = int(objects.shape[1])
    summary = {
        "policy": rollout["policy"],
        "settings": rollout["settings"],
        "observations": int(counts.shape[0]),
        "slots": slots,
        "histogram": np.bincount(counts, minlength=slots + 1).tolist(),
        "mean": round(float(counts.mean()), 3),
        "p50": int(np.percentile(counts, 50)),
        "p90": int(np.percentile(counts, 90)),
        "p99": int(np.percentile(counts, 99)),
        "max": int(counts.max()),
    }
    if "acting_vehicles_per_env_step" in rollout:
        summary["acting_vehicles_per_env_step"] = round(rollout["acting_vehicles_per_env_step"], 3)
    for key in ("weightings", "by_cap"):  # the Intersection's
        if key in rollout:
            summary[key] = rollout[key]
    return summary


def measure_occupancy(path: str | Path = OCCUPANCY_FILE) -> dict[str, dict[str, Any]]:
    """Drive every scenario as this module describes and write the table to ``path`` (one line per
    scenario, so that a re-measurement reads as a small diff). The Intersection's entry is the
    scripted driver's; the random drivers' is kept under its ``random_actions``."""
    table = {scenario: summarise(scenario, rollout_observations(scenario)) for scenario in SCENARIOS}
    random = summarise("intersection", rollout_observations("intersection", policy="random"))
    kept = (
        "policy",
        "observations",
        "histogram",
        "mean",
        "acting_vehicles_per_env_step",
        "weightings",
        "by_cap",
    )
    table["intersection"]["random_actions"] = {k: random[k] for k in kept}
    lines = [f"  {json.dumps(k)}: {json.dumps(v, ensure_ascii=False)}" for k, v in table.items()]
    Path(path).write_text("{\n" + ",\n".join(lines) + "\n}\n")
    return table


def load_occupancy(path: str | Path = OCCUPANCY_FILE) -> dict[str, dict[str, Any]]:
    """The measured table (``set_occupancy.json``), checked for the fields the estimates use."""
    path = Path(path)
    try:
        table = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"cannot read the occupancy table {path}: {err}") from None
    for scenario in SCENARIOS:
        entry = table.get(scenario)
        if not isinstance(entry, dict) or len(entry.get("histogram", ())) != entry.get("slots", -1) + 1:
            raise ValueError(
                f"{path}: no valid entry for {scenario} (rewrite it: costs.py --measure-occupancy)"
            )
    return table


def overflow_probability(
    histogram: list[int], sets_per_call: int, capacity: int, extra_rows: int = 0, calls: int = 1
) -> float:
    """Probability that ``calls`` independent calls of ``sets_per_call`` sets, each set drawn from the
    measured histogram plus ``extra_rows`` always-present rows, do not all fit in ``capacity`` packed
    rows: the chance that a call (or a members' shared decision) falls back to every slot.

    The sum of a call's counts is taken as normal (many sets) or computed exactly (few sets).
    """
    probs = np.asarray(histogram, float)
    probs = probs / probs.sum()
    values = np.arange(probs.size) + extra_rows
    if sets_per_call <= 16:  # exact: the distribution of the sum by repeated convolution
        total = np.array([1.0])
        for _ in range(sets_per_call):
            total = np.convolve(total, probs)
        offset = sets_per_call * extra_rows
        tail = float(total[max(capacity - offset + 1, 0) :].sum())
    else:
        mean = float((values * probs).sum())
        var = float(((values - mean) ** 2 * probs).sum())
        z = (capacity + 0.5 - sets_per_call * mean) / math.sqrt(max(sets_per_call * var, 1e-12))
        tail = 0.5 * math.erfc(z / math.sqrt(2.0))
    return float(1.0 - (1.0 - min(max(tail, 0.0), 1.0)) ** calls)


def scenario_of(agent) -> str:
    """The scenario whose observation layout ``agent`` was built for (by its set's key)."""
    for scenario, key in SET_KEYS.items():
        if key == agent.obs_shape.set_key:
            return scenario
    raise ValueError(f"no measured scenario has the set {agent.obs_shape.set_key!r}")


def fallback_probability(agent, batch_size: int, members: int = 1, table: dict | None = None) -> float:
    """Chance that an update of ``members`` members sharing their branches (one device's block) computes
    on every slot because some batch (observations or next observations) holds more present objects
    than its packed rows: the larger of the Deep Set's rule and the mixture actor's (whose rows are
    the slots that carry weight — all of an empty set — plus the neutral object), by the measured
    occupancy of the agent's scenario."""
    config = agent.config
    if config.packed_rows is None or config.dense_sets:
        return 0.0
    entry = (table or load_occupancy())[scenario_of(agent)]
    histogram, slots = list(entry["histogram"]), entry["slots"]
    calls = 2 * members
    probability = overflow_probability(
        histogram, batch_size, Packing(config.packed_rows).capacity(batch_size, slots), calls=calls
    )
    if config.is_mixture:
        neutral = int(config.neutral_object)
        weighted = list(histogram)
        if not neutral:  # an empty set's every slot carries weight
            weighted[slots] += weighted[0]
            weighted[0] = 0
        capacity = Packing(config.packed_rows + neutral).capacity(batch_size, slots + neutral)
        probability = max(
            probability, overflow_probability(weighted, batch_size, capacity, extra_rows=neutral, calls=calls)
        )
    return probability


def packed_only(agent):
    """``agent`` with its packed computation compiled alone (no dense fallback), to count the FLOPs
    that run: XLA's cost analysis counts a conditional as its larger branch. Lower it, never run it
    (:func:`xrl_jax.networks.packed_only`)."""
    return dataclasses.replace(agent, networks=networks_packed_only(agent.networks))


def update_cost(agent, batch_size: int, members: int = 1, table: dict | None = None) -> dict[str, float]:
    """FLOPs of one update as it runs: ``dense`` (every slot), ``packed`` (the packed computation
    alone), the ``fallback_probability`` and the ``expected`` mix of the two (``packed`` and the
    probability are absent, 0, for an agent that computes on every slot)."""
    config, example = agent.config, agent.dummy_observation()
    dense = update_flops(make_agent(config.replace(dense_sets=True), example, agent.action_size), batch_size)
    if config.packed_rows is None or config.dense_sets:
        return {"dense": dense, "packed": None, "fallback_probability": 0.0, "expected": dense}
    packed = update_flops(packed_only(agent), batch_size)
    probability = fallback_probability(agent, batch_size, members, table)
    expected = (1.0 - probability) * packed + probability * dense
    return {"dense": dense, "packed": packed, "fallback_probability": probability, "expected": expected}


__all__ = [
    "DEFAULTS",
    "INTERSECTION_POLICIES",
    "OCCUPANCY_FILE",
    "SCENARIOS",
    "curriculum_envs",
    "fallback_probability",
    "load_occupancy",
    "measure_occupancy",
    "occupancy_weightings",
    "overflow_probability",
    "packed_only",
    "present_counts",
    "rollout_observations",
    "scenario_of",
    "stored_counts",
    "summarise",
    "update_cost",
]
