"""A trained run's explanations over its whole evaluation (``experiments/explain.py --stats``).

Every seed's agent drives the run's evaluation again with its explanation recorded at every step
(:mod:`xrl_jax.explain.evaluation_steps`); the statistics of :mod:`xrl_jax.explain.statistics` are
reported per seed and over seeds (IQM with its bootstrap interval, as the returns are). Seeds are
compared on the same observations: a sample of each seed's steps is explained again by every other
seed's policy.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax.explain.evaluation_steps import ExplainedSteps, agreement_sample, explained_steps
from xrl_jax.explain.explanations import explain
from xrl_jax.explain.statistics import (
    Binned,
    binned_mean,
    binned_weight,
    explanation_size,
    interval_over_seeds,
    seed_agreement,
    weight_by_kind,
    weight_change,
    weight_map,
)

SIZE_SHARE = 0.9  # an explanation's size: the fewest objects carrying 90 % of the weight
DISTANCE_EDGES = tuple(float(d) for d in range(0, 52, 4))  # m from the ego's centre
CONTACT_EDGES = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0)  # s at the current closing speed
SPEED_EDGES = tuple(float(v) for v in range(0, 42, 3))  # m/s
MAP_CELL = 2.0  # m, the weight map's grid


def map_edges(steps: ExplainedSteps) -> tuple[np.ndarray, np.ndarray]:
    """The weight map's grid: the square around the ego that holds the present objects' places."""
    places = steps.xy[steps.present & np.all(np.isfinite(steps.xy), -1)]
    reach = float(np.max(np.abs(places))) if places.size else MAP_CELL
    half = MAP_CELL * math.ceil(reach / MAP_CELL)
    edges = np.arange(-half, half + MAP_CELL / 2, MAP_CELL)
    return edges, edges


def seed_statistics(steps: ExplainedSteps, x_edges, y_edges) -> dict[str, Any]:
    """Sums and per-step series of one seed (the report divides by its steps)."""
    sizes = explanation_size(steps.weights, SIZE_SHARE)
    previous = np.roll(np.arange(len(steps.speed)), 1)
    follows = steps.follows
    change = weight_change(
        steps.weights[previous[follows]],
        steps.identity[previous[follows]],
        steps.weights[follows],
        steps.identity[follows],
        steps.identity_tolerance,
    )
    return {
        "steps": len(steps.speed),
        "map": weight_map(steps.xy, steps.weights, steps.present, x_edges, y_edges),
        "kind": weight_by_kind(steps.kind, steps.weights, steps.present, len(steps.kinds)),
        "slot": Binned(steps.weights.sum(0), steps.present.sum(0)),
        "distance": binned_weight(steps.distance, steps.weights, steps.present, DISTANCE_EDGES),
        "contact": binned_weight(steps.time_to_contact, steps.weights, steps.present, CONTACT_EDGES),
        "size": sizes,
        "size_by_speed": binned_mean(sizes, steps.speed, SPEED_EDGES),
        "present": steps.present.sum(-1),
        "change": change,
        "returns": steps.returns,
        "situations": {name: _situation(steps, sizes, mask) for name, mask in _situations(steps).items()},
    }


BEFORE_END_STEPS = 20  # the last 2 s (10 steps a second) before a car's episode ended early


def _situations(steps: ExplainedSteps) -> dict[str, np.ndarray]:
    """Which steps are which situation: the last 2 s before an early end (left the track or road,
    collided), and every other step."""
    before = steps.steps_to_early_end < BEFORE_END_STEPS
    return {"before_early_end": before, "other": ~before}


def _situation(steps: ExplainedSteps, sizes: np.ndarray, mask: np.ndarray) -> dict[str, Any]:
    """One situation's sums: steps, weight by kind, explanation sizes, weight-weighted distance."""
    weights = np.where(steps.present[mask], steps.weights[mask], 0.0)
    distance = np.where(np.isfinite(steps.distance[mask]), steps.distance[mask], 0.0)
    placed = weights * np.isfinite(steps.distance[mask])
    return {
        "steps": int(mask.sum()),
        "kind": weight_by_kind(steps.kind[mask], steps.weights[mask], steps.present[mask], len(steps.kinds)),
        "size": sizes[mask],
        "distance_mass": float(np.sum(placed * distance)),
        "placed_mass": float(np.sum(placed)),
    }


def agreement(agent, agent_states, samples: list[Any]):
    """Every seed's policy (``agent_states`` stacked, S) on each seed's sample of observations
    (:func:`agreement_sample`): (S, S) similarity and same-top matrices, averaged over the samples."""
    seeds = jax.tree.leaves(agent_states)[0].shape[0]
    explain_all = jax.jit(lambda states, obs: jax.vmap(lambda s: explain(agent, s, obs).weights)(states))
    similarity, same_top = np.zeros((seeds, seeds)), np.zeros((seeds, seeds))
    for sample in samples:
        weights = np.asarray(explain_all(agent_states, jax.tree.map(jnp.asarray, sample)))  # (S, n, O)
        s, t = seed_agreement(weights)
        similarity += s / len(samples)
        same_top += t / len(samples)
    return similarity, same_top


def summarise(per_seed: list[dict], kinds: tuple[str, ...], x_edges, y_edges, similarity, same_top) -> dict:
    """The JSON summary: each statistic per seed and as IQM [95 % CI] over seeds."""
    steps = np.array([s["steps"] for s in per_seed], np.float64)

    def per_step(name):  # (seeds, bins): weight share per step in each bin
        return np.stack([s[name].mass for s in per_seed]) / steps[:, None]

    def per_object(name):
        with np.errstate(invalid="ignore"):
            return np.stack([s[name].mean_weight() for s in per_seed])

    def columns(matrix):
        return [interval_over_seeds(matrix[:, j]) for j in range(matrix.shape[1])]

    pooled_map = sum((s["map"] for s in per_seed), Binned(0.0, 0))
    sizes = [s["size"] for s in per_seed]
    speed_means = np.stack([s["size_by_speed"][0] for s in per_seed])
    speed_counts = np.sum([s["size_by_speed"][1] for s in per_seed], axis=0)
    off_diagonal = ~np.eye(len(per_seed), dtype=bool)
    return {
        "seeds": len(per_seed),
        "steps_per_seed": steps.astype(int).tolist(),
        "return_per_seed": [float(np.mean(s["returns"])) for s in per_seed],
        "kinds": list(kinds),
        "kind": {
            "share": columns(per_step("kind")),
            "objects_per_step": columns(np.stack([s["kind"].count for s in per_seed]) / steps[:, None]),
            "weight_per_object": columns(per_object("kind")),
        },
        "slot": {"share": columns(per_step("slot"))},
        "distance": {
            "edges": list(DISTANCE_EDGES),
            "share": columns(per_step("distance")),
            "weight_per_object": columns(per_object("distance")),
        },
        "time_to_contact": {
            "edges": list(CONTACT_EDGES),
            "share": columns(per_step("contact")),
            "weight_per_object": columns(per_object("contact")),
        },
        "map": {
            "x_edges": np.asarray(x_edges).tolist(),
            "y_edges": np.asarray(y_edges).tolist(),
            # 4 significant digits: a figure's colours, not numbers to quote (a third of the file's size)
            "share": _significant(pooled_map.mass / steps.sum()),
            "objects": _significant(pooled_map.count / steps.sum()),
        },
        "size": {
            "share": SIZE_SHARE,
            "mean": interval_over_seeds([np.mean(s) for s in sizes]),
            "median_per_seed": [float(np.median(s)) for s in sizes],
            "objects_present": interval_over_seeds([np.mean(s["present"]) for s in per_seed]),
            "speed_edges": list(SPEED_EDGES),
            "by_speed": columns(speed_means),
            "steps_by_speed": speed_counts.astype(int).tolist(),
        },
        "situations": _summarise_situations(per_seed),
        "stability": {
            "mean_change": interval_over_seeds([np.mean(s["change"]) for s in per_seed]),
            "median_change": interval_over_seeds([np.median(s["change"]) for s in per_seed]),
            "share_above_half": interval_over_seeds([np.mean(s["change"] > 0.5) for s in per_seed]),
        },
        "agreement": {
            "similarity": similarity.tolist(),
            "same_top": same_top.tolist(),
            "mean_similarity_between_seeds": float(similarity[off_diagonal].mean())
            if len(per_seed) > 1
            else 1.0,
            "mean_same_top_between_seeds": float(same_top[off_diagonal].mean()) if len(per_seed) > 1 else 1.0,
        },
    }


def _summarise_situations(per_seed: list[dict]) -> dict:
    """Per situation, over the seeds that met it: its share of the steps, the weight by kind, the
    mean explanation size and the weight's mean distance from the ego."""
    summary = {}
    for name in per_seed[0]["situations"]:
        parts = [s["situations"][name] for s in per_seed]
        met = [p for p in parts if p["steps"]]
        with np.errstate(invalid="ignore", divide="ignore"):
            distance_per_weight = [np.divide(p["distance_mass"], p["placed_mass"]) for p in met]
            kind = np.stack([p["kind"].mass / p["steps"] for p in met]) if met else np.zeros((0, 0))
            summary[name] = {
                "steps": [p["steps"] for p in parts],
                "kind_share": [interval_over_seeds(kind[:, j]) for j in range(kind.shape[1])],
                "size": interval_over_seeds([np.mean(p["size"]) for p in met]),
                "weighted_distance": interval_over_seeds(distance_per_weight),
            }
    return summary


def explanation_statistics(
    cfg, trainer, agent_states, key=None, deletion_episodes: int = 20, note=lambda message: None
) -> dict:
    """The summary of every seed in ``agent_states`` (stacked), seed by seed so that one seed's steps
    are in memory at a time: an X agent's statistics (:func:`summarise`), and for every agent the
    deletion curves on ``deletion_episodes`` of the evaluation episodes (none with 0); ``note`` hears
    the progress."""
    from xrl_jax.explain.run_deletion import deletion_curves

    key = jax.random.PRNGKey(0) if key is None else key
    is_mixture = trainer.agent.config.is_mixture
    seeds = jax.tree.leaves(agent_states)[0].shape[0]
    rng = np.random.default_rng(0)
    per_seed, samples, edges, kinds = [], [], None, ()
    for seed in range(seeds):
        state = jax.tree.map(lambda leaf, seed=seed: leaf[seed], agent_states)
        steps = explained_steps(cfg, trainer, state, key)
        if is_mixture:
            edges = edges or map_edges(steps)  # the first seed's grid for all: the maps add up
            per_seed.append(seed_statistics(steps, *edges))
        samples.append(agreement_sample(steps, rng))
        kinds = steps.kinds
        note(f"seed {seed}: {len(steps.speed)} steps explained")
    summary = {"env": cfg.env, "algo": cfg.algo, "total_steps": cfg.total_steps, "seeds": seeds}
    if is_mixture:
        similarity, same_top = agreement(trainer.agent, agent_states, samples)
        summary |= summarise(per_seed, kinds, *edges, similarity, same_top)
    if deletion_episodes:
        episodes = min(deletion_episodes, cfg.eval_episodes)
        summary["deletion"] = deletion_curves(cfg, trainer, agent_states, samples, episodes, key, note)
    return summary


def _significant(matrix: np.ndarray, digits: int = 4) -> list:
    return [[float(f"{value:.{digits}g}") for value in row] for row in np.asarray(matrix, np.float64)]


def _json_ready(value):
    """NaN (a bin no object fell in, a seed without steps) as JSON's null, everything else as is."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_statistics(
    run, out, point: int = 0, key: int = 0, deletion_episodes: int = 20, note=lambda message: None
) -> str:
    """Statistics of every seed (at sweep ``point``) of the run in folder ``run``: ``out/stats.json``,
    an X agent's ``out/stats.png`` and the deletion curves' ``out/deletion.png``; returns the line
    that says what was written. Raises ``ValueError`` with one line for a run it cannot take (a
    user's env, a point out of range)."""
    import json
    from pathlib import Path

    from xrl_jax.explain.statistics_figures import draw_deletion, draw_statistics
    from xrl_jax.runs.folder import read_run_config, write_atomic
    from xrl_jax.train import load_trained_agents, scenario_kind

    cfg = read_run_config(run)  # the checks below before minutes of restoring
    if scenario_kind(cfg).figure not in ("track", "slots"):
        raise ValueError(f"{cfg.env} is a user's env: --stats knows the paper's three scenarios only")
    if not 0 <= point < cfg.num_points:
        raise ValueError(f"sweep point {point} out of range: the run has points 0..{cfg.num_points - 1}")
    if not cfg.agent.is_mixture and not deletion_episodes:
        raise ValueError(
            f"{cfg.algo} is a baseline: without per-object weights its statistics are the deletion curves, "
            "which --deletion-episodes 0 turns off"
        )
    cfg, trainer, agent_states = load_trained_agents(run)
    members = slice(point * cfg.num_seeds, (point + 1) * cfg.num_seeds)
    agent_states = jax.tree.map(lambda leaf: leaf[members], agent_states)
    summary = explanation_statistics(
        cfg, trainer, agent_states, jax.random.PRNGKey(key), deletion_episodes, note
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "stats.json", json.dumps(_json_ready(summary), indent=1, allow_nan=False) + "\n")
    title = f"{cfg.env} {cfg.algo}, {cfg.num_seeds} seeds, {cfg.total_steps:,} steps"
    written = [out / "stats.json"]
    said = []
    if "size" in summary:
        written.append(draw_statistics(summary, out / "stats.png", f"{title}: explanations"))
        size, change = summary["size"]["mean"], summary["stability"]["mean_change"]
        said.append(
            f"{size['estimate']:.2f} objects carry {summary['size']['share']:.0%} of the weight (IQM over "
            f"seeds), step-to-step change {change['estimate']:.3f} TV"
        )
    if "deletion" in summary:
        written.append(draw_deletion(summary["deletion"], out / "deletion.png", f"{title}: deletion curves"))
        said.extend(_against_random(summary["deletion"]))
    return f"{', '.join(map(str, written))}: {summary['seeds']} seeds; " + "; ".join(said)


def _against_random(deletion: dict) -> list[str]:
    """One phrase per ranker: how much faster than random its deletions change policy and return."""
    phrases = []
    for ranker, differences in deletion["against_random"].items():
        tv, ret = differences["tv"], differences["return"]
        phrases.append(
            f"deleting by {ranker} vs random: TV {tv['estimate']:+.3f} [{tv['low']:+.3f}, "
            f"{tv['high']:+.3f}], return {ret['estimate']:+.2f} [{ret['low']:+.2f}, {ret['high']:+.2f}]"
        )
    return phrases
