"""Score the hand-written centre-line controller (docs/carenv-single-agent.md §8.3) on the held-out
evaluation tracks, the yardstick the results compare every agent with.

    python experiments/controller.py --env country_road --speeds 8 10 12

Drives one episode on each of the first EPISODES evaluation tracks (the tracks every run evaluates
on: --eval-track-seed and --episodes as a run's eval_track_seed and eval_episodes) at each target
speed, and prints the mean return, the early-termination rate, the mean speed along the track and
the cones hit. --json writes the same numbers, per-episode returns included.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, non_negative_int, positive_int, positive_speed


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="controller.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True, choices=("tracking", "country_road"))
    parser.add_argument("--speeds", nargs="+", type=positive_speed, default=[8.0], metavar="M_PER_S",
                        help="target speeds in m/s (default: 8, the reference setting of §8.3)")  # fmt: skip
    parser.add_argument("--episodes", type=positive_int, default=100,
                        help="evaluation tracks, one episode each (default 100, as a run)")  # fmt: skip
    parser.add_argument("--eval-track-seed", type=non_negative_int, default=1,
                        help="seed of the evaluation tracks (default 1, as a run)")  # fmt: skip
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from xrl_jax.evaluate import hand_controller_evaluation

    score = hand_controller_evaluation(args.env, args.eval_track_seed, args.episodes)
    results = [score(speed) for speed in args.speeds]
    print(f"hand controller on {args.env}, {args.episodes} evaluation tracks (seed {args.eval_track_seed})")
    print("| target speed (m/s) | mean return | ETR | speed along the track (m/s) | cones hit |")
    print("|---|---|---|---|---|")
    for r in results:
        print(f"| {r['target_speed']:g} | {r['avg_return']:.2f} | {r['avg_etr']:.2f} | "
              f"{r['avg_track_velocity']:.2f} | {r['avg_cones_hit']:.2f} |")  # fmt: skip
    if args.json:
        document = {"env": args.env, "eval_track_seed": args.eval_track_seed, "episodes": args.episodes,
                    "results": results}  # fmt: skip
        Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
        print(f"written: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
