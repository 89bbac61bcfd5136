"""How full the observation sets are: present objects per set, measured from rollouts.

The per-object layers compute on the present objects only (:mod:`xrl_jax.sets`), so what a run
costs depends on how many objects its sets hold. This module drives each scenario as
docs/performance.md describes and records what the observations held:

* Country Road and Tracking: the hand controller of docs/carenv-single-agent.md §8.3 at 8 m/s, one
  episode of up to 600 steps on each of ``num_tracks`` generated tracks, every step's observation
  until the episode ends;
* Intersection: the training curriculum (1, 2, 4 or 8 vehicles per episode) with uniformly random
  actions, ``num_envs`` envs for ``steps`` steps; every observation of a vehicle that acted (the
  ones the trainer stores and learns from), and how many vehicles acted per env step.

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
    "intersection": {"num_envs": 16, "steps": 1200, "seed": 0},
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


def _intersection_observations(num_envs: int, steps: int, seed: int) -> dict[str, Any]:
    env, params = envs.make("intersection")  # the training curriculum

    def rollout(key):
        reset_key, key = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_envs), params)

        def step(carry, key):
            obs, state = carry
            act_key, step_key = jax.random.split(key)
            action = jax.vmap(env.sample_actions, in_axes=(0, None))(
                jax.random.split(act_key, num_envs), params
            )
            next_obs, state, *_, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(step_key, num_envs), state, action, params
            )
            return (next_obs, state), (obs, info["acted"])

        return jax.lax.scan(step, (obs, state), jax.random.split(key, steps))[1]

    obs, acted = jax.device_get(jax.jit(rollout)(jax.random.PRNGKey(seed)))
    acted = np.asarray(acted)  # (steps, envs, slots)
    flat = acted.reshape(-1)
    observations = {k: np.asarray(v).reshape(-1, *v.shape[3:])[flat] for k, v in obs.items()}
    return {
        "observations": observations,
        "policy": "uniformly random actions under the training curriculum",
        "acting_vehicles_per_env_step": float(acted.sum() / (steps * num_envs)),
    }


# How each scenario is driven (the module's doc), taking its DEFAULTS' settings.
ROLLOUTS = {
    "tracking": functools.partial(_racing_observations, "tracking"),
    "country_road": functools.partial(_racing_observations, "country_road"),
    "intersection": _intersection_observations,
}


def rollout_observations(scenario: str, **settings: int) -> dict[str, Any]:
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
    return summary


def measure_occupancy(path: str | Path = OCCUPANCY_FILE) -> dict[str, dict[str, Any]]:
    """Drive every scenario as this module describes and write the table to ``path`` (one line per
    scenario, so that a re-measurement reads as a small diff)."""
    table = {scenario: summarise(scenario, rollout_observations(scenario)) for scenario in SCENARIOS}
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
    "OCCUPANCY_FILE",
    "SCENARIOS",
    "fallback_probability",
    "load_occupancy",
    "measure_occupancy",
    "overflow_probability",
    "packed_only",
    "present_counts",
    "rollout_observations",
    "scenario_of",
    "summarise",
    "update_cost",
]
