"""Deletion curves of a trained run (``experiments/explain.py --stats``): how much the policy and the
evaluation change when the objects an explanation ranks first are removed from every observation.

Per seed and ranker (:data:`xrl_jax.explain.faithfulness.RANKERS`): the mean total variation between
the policy and the policy without its top-k objects over a sample of the seed's evaluation steps, and
the evaluation's mean return (on the Intersection also completed trips and early terminations: cars
that left the road or collided) of the agent acting on every observation without its top-k objects.
The X agents rank by their own weights; the Deep Set baselines, which have none, by the post-hoc
occlusion and gradient × input; both against a random order. Each ranker's evaluations are one
compiled program vmapped over k.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax.explain.faithfulness import RANKERS, DeletingAgent, policy_change_curve
from xrl_jax.explain.statistics import interval_over_seeds

DELETION_KS = (0, 1, 2, 3, 5, 8)  # objects removed per observation (at most all but one)
MIXTURE_RANKERS = ("weight", "random")
BASELINE_RANKERS = ("occlusion", "gradient_x_input", "random")
POLICY_STATES = 1000  # evaluation steps per seed on which the policy's change is measured
STATE_CHUNK = 100  # states at a time: occlusion runs one forward pass per object slot
TV_SAMPLES = 256  # Monte Carlo draws per state for a continuous policy's total variation
TRAFFIC_METRICS = ("trips_completed", "early_terminations")  # the Intersection's, per episode


def rankers_of(agent) -> tuple[str, ...]:
    return MIXTURE_RANKERS if agent.config.is_mixture else BASELINE_RANKERS


def _policy_change_program(agent, ranker: str, ks):
    """``curve(agent_state, obs, key) -> (len(ks),)`` jitted once per ranker: the mean TV over a
    chunk of observations."""
    set_key = agent.obs_shape.set_key
    return jax.jit(
        lambda state, obs, key: policy_change_curve(
            agent, state, obs, set_key, RANKERS[ranker], ks, key, TV_SAMPLES
        ).mean(-1)
    )


def _policy_change(curve, agent_state, sample, key, num_ks: int) -> np.ndarray:
    """(num_ks,) the mean TV over up to ``POLICY_STATES`` observations of ``sample``, in chunks; NaN
    for a seed whose evaluation left none (the IQM over seeds skips it)."""
    count = min(POLICY_STATES, len(jax.tree.leaves(sample)[0]))
    if count == 0:
        return np.full(num_ks, np.nan)
    total = 0.0
    for start in range(0, count, STATE_CHUNK):
        stop = min(start + STATE_CHUNK, count)
        obs = jax.tree.map(lambda leaf, a=start, b=stop: jnp.asarray(leaf[a:b]), sample)
        total = total + np.asarray(curve(agent_state, obs, jax.random.fold_in(key, start))) * (stop - start)
    return total / count


def _evaluations(cfg, trainer, ranker: str, ks, episodes: int):
    """``evaluate(key, agent_state) -> {metric: (len(ks), episodes)}``: the kind's own evaluation of
    the agent without its top-k objects by ``ranker``, every k in one program."""
    from xrl_jax.train import scenario_kind

    acting = DeletingAgent(trainer.agent, RANKERS[ranker], None)
    evaluate = scenario_kind(cfg).make_evaluate(
        cfg.replace(eval_episodes=episodes), trainer.env, trainer.eval_params, acting
    )
    counts = jnp.asarray(ks, jnp.int32)
    return jax.jit(lambda key, state: jax.vmap(lambda k: evaluate(key, (state, k)))(counts))


def deletion_curves(cfg, trainer, agent_states, samples, episodes: int, key, note=lambda m: None) -> dict:
    """The deletion curves of every seed (``agent_states`` stacked; ``samples``: each seed's
    observations, :func:`~xrl_jax.explain.evaluation_steps.agreement_sample`), evaluated on the first
    ``episodes`` of the run's evaluation episodes. Per ranker and k: each seed's value and the IQM
    over seeds with its interval; per ranker but random, the paired difference to the random order
    of the mean over k > 0 (mean over seeds, bootstrap interval)."""
    agent = trainer.agent
    num_objects = cfg.scenario.num_objects
    ks = tuple(k for k in DELETION_KS if k < num_objects)
    metrics = ("return", *(m for m in TRAFFIC_METRICS if f"avg_{m}" in dict(cfg.scenario.summary_metrics)))
    seeds = jax.tree.leaves(agent_states)[0].shape[0]
    per_seed = {r: {"tv": [], **{m: [] for m in metrics}} for r in rankers_of(agent)}
    for ranker, rows in per_seed.items():
        evaluate = _evaluations(cfg, trainer, ranker, ks, episodes)
        curve = _policy_change_program(agent, ranker, ks)
        for seed in range(seeds):
            state = jax.tree.map(lambda leaf, s=seed: leaf[s], agent_states)
            seed_key = jax.random.fold_in(key, seed)
            rows["tv"].append(_policy_change(curve, state, samples[seed], seed_key, len(ks)))
            results = jax.device_get(evaluate(seed_key, state))
            for metric in metrics:
                rows[metric].append(np.asarray(results[metric], np.float64).mean(-1))
        note(f"deletion by {ranker}: {seeds} seeds")
    curves = {}
    for ranker, rows in per_seed.items():
        curves[ranker] = {}
        for name, values in rows.items():
            matrix = np.stack(values)  # (seeds, len(ks))
            curves[ranker][name] = {
                "per_seed": matrix.tolist(),
                "over_seeds": [interval_over_seeds(matrix[:, j]) for j in range(len(ks))],
            }
    differences = {}
    for ranker, rows in per_seed.items():
        if ranker == "random":
            continue
        differences[ranker] = {
            name: interval_over_seeds(
                np.stack(rows[name])[:, 1:].mean(-1) - np.stack(per_seed["random"][name])[:, 1:].mean(-1),
                statistic=np.mean,
            )
            for name in rows
        }
    return {
        "ks": list(ks),
        "episodes": episodes,
        "states_per_seed": min(POLICY_STATES, *(len(jax.tree.leaves(s)[0]) for s in samples)),
        "metrics": ["tv", *metrics],
        "rankers": curves,
        "against_random": differences,
    }
