"""Score a scenario's yardstick, the scripted driver every agent is compared with, on the
evaluation the runs use.

    python experiments/controller.py --env country_road --speeds 8 10 12
    python experiments/controller.py --env intersection --speeds 10 15

Racing (tracking, country_road): the hand-written centre-line controller of
docs/carenv-single-agent.md §8.3, one episode on each of the first EPISODES evaluation tracks (the
tracks every run evaluates on: --eval-track-seed and --episodes as a run's eval_track_seed and
eval_episodes) at each target speed; prints the mean return, the early-termination rate, the mean
speed along the track and the cones hit. Intersection: the scripted driver of
envs/intersection_driver.py in every car (route following, slowing for turns, giving way to a car
that reaches a crossing point first) on the agents' evaluation episodes (EPISODES episodes of 60 s
with 8 cars) at each cruise speed; prints the return, completed trips, early terminations (cars off
the road and collided cars) and mean velocity per episode. --json writes the same numbers,
per-episode returns included.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, non_negative_int, positive_int, positive_speed

DEFAULT_SPEEDS = {"tracking": 8.0, "country_road": 8.0, "intersection": 10.0}  # the drivers' own defaults
DEFAULT_EPISODES = {"tracking": 100, "country_road": 100, "intersection": 20}  # as the paper's runs


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="controller.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True, choices=("tracking", "country_road", "intersection"))
    parser.add_argument("--speeds", nargs="+", type=positive_speed, metavar="M_PER_S",
                        help="target (racing) or cruise (intersection) speeds in m/s (default: 8 on "
                             "the racing scenarios, the reference setting of §8.3; 10 on the "
                             "intersection)")  # fmt: skip
    parser.add_argument("--episodes", type=positive_int,
                        help="episodes (racing: evaluation tracks, one episode each; default 100 racing, "
                             "20 intersection, as the paper's runs)")  # fmt: skip
    parser.add_argument("--eval-track-seed", type=non_negative_int, default=1,
                        help="seed of the racing evaluation tracks (default 1, as a run)")  # fmt: skip
    parser.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    return parser


def _racing_table(results: list[dict]) -> list[str]:
    lines = ["| target speed (m/s) | mean return | ETR | speed along the track (m/s) | cones hit |",
             "|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['target_speed']:g} | {r['avg_return']:.2f} | {r['avg_etr']:.2f} | "
              f"{r['avg_track_velocity']:.2f} | {r['avg_cones_hit']:.2f} |" for r in results]  # fmt: skip
    return lines


def _intersection_table(results: list[dict]) -> list[str]:
    lines = ["| cruise speed (m/s) | return | completed trips | early terminations | off the road | "
             "collided | mean velocity (m/s) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['target_speed']:g} | {r['avg_return']:.2f} | {r['avg_trips_completed']:.2f} | "
              f"{r['avg_early_terminations']:.2f} | {r['avg_come_off_vehicles']:.2f} | "
              f"{r['avg_collided_vehicles']:.2f} | {r['avg_mean_velocity']:.2f} |"
              for r in results]  # fmt: skip
    return lines


# Per yardstick (the scenario's fact): the heading, the table, and whether the track seed picks its
# episodes (the Intersection's are fixed).
YARDSTICK_OUTPUT = {
    "hand controller": (
        "hand controller on {env}, {episodes} evaluation tracks (seed {seed})",
        _racing_table,
        True,
    ),
    "scripted driver": (
        "scripted driver on the intersection, {episodes} evaluation episodes of 60 s with 8 cars",
        _intersection_table,
        False,
    ),
}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from xrl_jax.config import scenario
    from xrl_jax.evaluation import yardstick_evaluation

    speeds = args.speeds or [DEFAULT_SPEEDS[args.env]]
    episodes = args.episodes or DEFAULT_EPISODES[args.env]
    score = yardstick_evaluation(args.env, args.eval_track_seed, episodes)
    results = [score(speed) for speed in speeds]
    heading, table, seeded = YARDSTICK_OUTPUT[scenario(args.env).yardstick]
    print(heading.format(env=args.env, episodes=episodes, seed=args.eval_track_seed))
    print("\n".join(table(results)))
    if args.json:
        document = {"env": args.env, "episodes": episodes, "results": results}
        if seeded:
            document["eval_track_seed"] = args.eval_track_seed
        Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
        print(f"written: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
