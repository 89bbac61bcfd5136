"""Evaluate a finished run's agents again, on its training tracks or on its held-out tracks.

    python experiments/evaluate.py RESULTS_DIR [--tracks train|eval] [--episodes N] [--key K]
                                   [--mode eval|deterministic]

Every seed's agent (every member's, in a sweep) is restored from the run's newest checkpoint and
driven with the run's evaluation
protocol (docs/algorithms.md §6.1) over the first N tracks of the chosen set, one episode per track:
``train`` is the fixed training bank of a run with ``train_tracks`` > 0 (the gap to ``eval`` is the
generalisation gap), ``eval`` the run's held-out evaluation tracks. Prints each seed's average return
and early-termination rate and their IQM with its 95 % stratified bootstrap CI over seeds, and
writes the same to ``RESULTS_DIR/evaluation_<tracks>.json`` (``evaluation_<tracks>_deterministic.json``
with ``--mode deterministic``, which drives XSAC greedily too).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, positive_int


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="evaluate.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a results folder of experiments/run.py (racing scenarios)")
    parser.add_argument(
        "--tracks", choices=("train", "eval"), default="train", help="which tracks (default: train)"
    )
    parser.add_argument(
        "--episodes", type=positive_int, help="tracks to drive, one episode each (default: all)"
    )
    parser.add_argument(
        "--key", type=int, default=0, help="seed of the evaluation's random numbers (default 0)"
    )
    parser.add_argument(
        "--mode",
        choices=("eval", "deterministic"),
        default="eval",
        help="eval: each agent's evaluation policy as in the reference (XSAC samples, the others are "
        "greedy; default); deterministic: greedy for every agent, XSAC at the approximate mode of its "
        "mixture (docs/algorithms.md §3.9), a diagnostic outside the paper's protocol",
    )
    return parser


def fail(message: str) -> int:
    print(f"evaluate.py: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    run = Path(args.run)
    import jax

    from xrl_jax.evaluation import make_evaluate, summarize_episodes
    from xrl_jax.runs.folder import RunFolderError, read_run_config
    from xrl_jax.runs.summary import aggregate_metrics, summary_metrics
    from xrl_jax.sets import MEMBERS_AXIS
    from xrl_jax.train import load_trained_agents

    try:
        cfg = read_run_config(run)
        if cfg.multi_agent:
            return fail("intersection runs have no tracks; their evaluation episodes are in the run's eval/")
        if args.tracks == "train" and cfg.fresh_tracks:
            return fail(
                f"{run} trained on fresh tracks (train_tracks=0): no training track was driven twice, so the "
                "held-out evaluation already measures generalisation; use --tracks eval"
            )
        cfg, trainer, agent_states = load_trained_agents(run)
    except RunFolderError as err:
        return fail(str(err))
    params = trainer.env_params if args.tracks == "train" else trainer.eval_params
    available = int(params.tracks.num_points.shape[0])
    episodes = available if args.episodes is None else args.episodes
    if episodes > available:
        return fail(f"--episodes {episodes}: the run's {args.tracks} tracks are only {available}")
    evaluate_one = make_evaluate(trainer.env, params, trainer.agent, episodes, args.mode)
    evaluate = jax.jit(jax.vmap(evaluate_one, in_axes=(None, 0), axis_name=MEMBERS_AXIS))
    results = jax.device_get(evaluate(jax.random.PRNGKey(args.key), agent_states))  # all seeds at once
    from xrl_jax.runs.folder import member_fields

    per_seed = []
    for member in range(cfg.num_members):  # a plain run's members are its seeds
        result = summarize_episodes(jax.tree.map(lambda x, m=member: x[m], results))
        fields = member_fields(cfg, member)
        per_seed.append({**fields, **result} if cfg.num_points > 1 else {"seed": fields["seed"], **result})
        where = f"point {fields['point']} {fields['sweep']} " if cfg.num_points > 1 else ""
        etr = result["avg_etr"]
        scores = f"return {result['avg_return']:.2f}, early-termination rate {etr:.2f}"
        print(f"{where}seed {fields['seed']}: {scores}")
    aggregates = []
    for point, values in enumerate(cfg.sweep_points):
        rows = [per_seed[m] for m in cfg.point_members(point)]
        aggregate = aggregate_metrics(rows, cfg.env)
        aggregates.append({"point": point, "values": values, "aggregate": aggregate})
        for key, label in summary_metrics(cfg.env):
            if key in aggregate:
                agg = aggregate[key]
                interval = f"[{agg['low']:.3f}, {agg['high']:.3f}]"
                at = f" at {values}" if values else ""
                print(f"{label}{at} on {episodes} {args.tracks} tracks: IQM {agg['estimate']:.3f} {interval}")
    document = {
        "tracks": args.tracks,
        "episodes": episodes,
        "key": args.key,
        "mode": args.mode,
        "per_seed": [{k: v for k, v in row.items() if k != "episode_returns"} for row in per_seed],
    }
    if cfg.num_points > 1:
        document["points"] = aggregates
    else:
        document["aggregate"] = aggregates[0]["aggregate"]
    suffix = "" if args.mode == "eval" else f"_{args.mode}"
    out = run / f"evaluation_{args.tracks}{suffix}.json"
    out.write_text(json.dumps(document, indent=2) + "\n")
    print(f"written: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
