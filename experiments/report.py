"""Summarise result folders in one report: tables, figures and improvement probabilities.

    python experiments/report.py RUN_DIR [RUN_DIR ...] --out DIR

Writes DIR/report.md with, per env, a results table (Markdown and CSV: final return and
early-termination rate, or trips and early terminations on the intersection, as IQM [95 % CI] over
seeds, with the paper's published value beside runs of the paper's protocol), a figure of final
performance and learning curves per agent (the paper's Fig. 5-7), the sweep figure of every sweep
run with its baseline (Fig. 8), and P(explainable agent > its baseline) with its CI, at the end and
early in the run (Fig. 7). --controller adds each scenario's yardstick on the same evaluation: the
hand-written centre-line driver on the racing tracks, the scripted driver on the Intersection.
Folders that are still running or lost a seed are reported as far as they go, and marked
incomplete; a folder given twice (under any path), or also as DIR/runs's copy of its records, is
reported once, with a note. DIR/runs keeps a copy of what was read of each run (config and
evaluations), so that `report.py DIR/runs/* NEW_RUN_DIR --out DIR` adds a run after the original
folders are gone. Runs of one protocol from different base
seeds (`--set seed=S`: a protocol's seeds trained a few at a time) are pooled into one row.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import IMPORT_HELP, OneLineParser, fail, fraction, import_user_modules, positive_speed

PROG = "report.py"
DRIVERS_DEFAULT = 0.0  # --controller without a speed: each driver's own (not a str: argparse would parse it)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR", help="results folders of experiments/run.py")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder of the report (created)")
    parser.add_argument(
        "--import", dest="imports", metavar="MODULE", action="append", default=[], help=IMPORT_HELP
    )
    parser.add_argument("--controller", nargs="?", type=positive_speed, const=DRIVERS_DEFAULT,
                        metavar="M_PER_S",
                        help="also drive each scenario's yardstick on the runs' evaluation and show "
                             "it in the tables and figures (it drives every evaluation episode): the "
                             "hand controller of docs/carenv-single-agent.md §8.3 on the racing tracks "
                             "(default 8 m/s), the scripted driver of envs/intersection_driver.py on the "
                             "Intersection (default cruise speed 10 m/s); a speed given here is used for "
                             "every scenario")  # fmt: skip
    parser.add_argument("--early", type=fraction, default=0.25, metavar="FRACTION",
                        help="also compare each explainable agent with its baseline at the evaluation "
                             "nearest this fraction of the run (default 0.25: Fig. 7's 'early stages of "
                             "training')")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    problem = import_user_modules(argv)  # runs on a user's env need the module that registers it
    if problem:
        return fail(PROG, problem)
    args = build_parser().parse_args(argv)
    from xrl_jax.benchmarks.table_one import policy_costs
    from xrl_jax.report import ReportError, write_report

    speed = None if args.controller in (None, DRIVERS_DEFAULT) else args.controller  # None: the defaults
    try:
        report = write_report(
            args.runs,
            args.out,
            speed,
            args.controller is not None,
            args.early,
            note=lambda message: print(f"{PROG}: note: {message}", file=sys.stderr),
            policy_costs=policy_costs,
        )
    except ReportError as err:
        return fail(PROG, err)
    print(report.read_text())
    print(f"written: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
