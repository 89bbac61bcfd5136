"""Evaluating a trained run's agents again, on its training tracks or its held-out tracks
(``experiments/evaluate.py``): every member restored from the run's newest good checkpoint, all
driven at once with the run's evaluation protocol (docs/algorithms.md §6.1), summarised per seed
and over seeds, and written into the run's folder.

It restores agents through :func:`~xrl_jax.train.restore.load_trained_agents_and_steps`, so it sits
with the trainer, above the folder's readers (:mod:`xrl_jax.runs`) and the protocols
(:mod:`xrl_jax.evaluation`).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax

from xrl_jax.evaluation import make_evaluate, summarize_episodes
from xrl_jax.runs.folder import RunFolderError, evaluation_file, member_fields, read_run_config, write_atomic
from xrl_jax.runs.summary import aggregate_metrics, summary_metrics
from xrl_jax.sets import MEMBERS_AXIS
from xrl_jax.train.kinds import scenario_kind
from xrl_jax.train.restore import load_trained_agents_and_steps

TRACK_SETS = ("train", "eval")  # the run's fixed training bank, its held-out evaluation tracks


def evaluate_run(
    run: str | Path,
    tracks: str = "train",
    episodes: int | None = None,
    key: int = 0,
    mode: str = "eval",
    log=print,
) -> Path:
    """Drive every member of the run in ``run`` over the first ``episodes`` tracks (all when None) of
    ``tracks``, one episode per track, with the PRNG key ``key`` and the policies of ``mode``; writes
    the results per seed (with the step of the checkpoint evaluated), and their IQM with its 95 % CI
    over seeds per sweep point, into the folder and returns that file's path. ``log`` takes one line
    per seed and per summary metric.

    Raises :class:`~xrl_jax.runs.folder.RunFolderError` (one line) when the folder cannot be
    evaluated so: not a run, an Intersection run (no tracks), training tracks of a run that trained
    on fresh ones, or more episodes than the set has tracks."""
    run = Path(run)
    cfg = read_run_config(run)
    scenario_kind(cfg).check_reevaluation(cfg, run, tracks)  # only racing runs have tracks
    cfg, trainer, agent_states, checkpoint_steps = load_trained_agents_and_steps(run)
    params = trainer.env_params if tracks == "train" else trainer.eval_params
    available = int(params.tracks.num_points.shape[0])
    episodes = available if episodes is None else episodes
    if episodes > available:
        raise RunFolderError(f"--episodes {episodes}: the run's {tracks} tracks are only {available}")
    evaluate_one = make_evaluate(trainer.env, params, trainer.agent, episodes, mode)
    evaluate = jax.jit(jax.vmap(evaluate_one, in_axes=(None, 0), axis_name=MEMBERS_AXIS))
    results = jax.device_get(evaluate(jax.random.PRNGKey(key), agent_states))  # all members at once
    per_seed = [_member_result(cfg, member, results, log) for member in range(cfg.num_members)]
    for row, step in zip(per_seed, checkpoint_steps, strict=True):
        row["checkpoint_step"] = step  # what was evaluated: the last step, unless that checkpoint was damaged
    aggregates = []
    for point, values in enumerate(cfg.sweep_points):
        aggregate = aggregate_metrics([per_seed[m] for m in cfg.point_members(point)], cfg.env)
        aggregates.append({"point": point, "values": values, "aggregate": aggregate})
        for metric, label in summary_metrics(cfg.env):
            if metric in aggregate:
                agg = aggregate[metric]
                interval = f"[{agg['low']:.3f}, {agg['high']:.3f}]"
                at = f" at {values}" if values else ""
                log(f"{label}{at} on {episodes} {tracks} tracks: IQM {agg['estimate']:.3f} {interval}")
    document = {
        "tracks": tracks,
        "episodes": episodes,
        "key": key,
        "mode": mode,
        "per_seed": [{k: v for k, v in row.items() if k != "episode_returns"} for row in per_seed],
    }
    if cfg.num_points > 1:
        document["points"] = aggregates
    else:
        document["aggregate"] = aggregates[0]["aggregate"]
    out = evaluation_file(run, tracks, mode)
    write_atomic(out, json.dumps(document, indent=2) + "\n")
    return out


def _member_result(cfg, member: int, results, log) -> dict:
    """Member ``member``'s summarised episodes with the fields that name it (a plain run's members
    are its seeds), logged in one line."""
    result = summarize_episodes(jax.tree.map(lambda x: x[member], results))
    fields = member_fields(cfg, member)
    where = f"point {fields['point']} {fields['sweep']} " if cfg.num_points > 1 else ""
    scores = f"return {result['avg_return']:.2f}, early-termination rate {result['avg_etr']:.2f}"
    log(f"{where}seed {fields['seed']}: {scores}")
    return {**fields, **result} if cfg.num_points > 1 else {"seed": fields["seed"], **result}
