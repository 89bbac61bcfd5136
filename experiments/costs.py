"""Parameter counts and inference FLOPs per action on Country Road shapes, next to the paper's Table I.

    python experiments/costs.py                      # table on stdout
    python experiments/costs.py --json               # the same numbers as JSON
    python experiments/costs.py --measure-occupancy  # re-measure the set occupancy (~1 min)

What the columns count: xrl_jax/benchmarks/table_one.py; the occupancy: xrl_jax/benchmarks/occupancy.py
and the table it writes beside it, set_occupancy.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser

from xrl_jax.benchmarks import format_table_one, measure_table_one
from xrl_jax.benchmarks.occupancy import measure_occupancy


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="costs.py", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument(
        "--measure-occupancy",
        action="store_true",
        help="drive every scenario and rewrite xrl_jax/benchmarks/set_occupancy.json (objects per set)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.measure_occupancy:
        for scenario, entry in measure_occupancy().items():
            print(
                f"{scenario:<14} {entry['observations']:>7} observations, {entry['slots']} slots: mean "
                f"{entry['mean']}, p50 {entry['p50']}, p90 {entry['p90']}, p99 {entry['p99']}, "
                f"max {entry['max']}"
            )
        return 0
    rows = measure_table_one()
    if args.json:
        json.dump(rows, sys.stdout, indent=2)
        print()
        return 0
    print("\n".join(format_table_one(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
