"""Summarise result folders in one report: tables, figures and improvement probabilities.

    python experiments/report.py RUN_DIR [RUN_DIR ...] --out DIR

Writes DIR/report.md with, per env, a results table (Markdown and CSV: final return and
early-termination rate, or trips and early terminations on the intersection, as IQM [95 % CI] over
seeds, with the paper's published value beside runs of the paper's protocol), a figure of final
performance and learning curves per agent (the paper's Fig. 5-7), the sweep figure of every sweep
run with its baseline (Fig. 8), and P(explainable agent > its baseline) with its CI. --controller
adds the hand-written centre-line driver's score on the same evaluation tracks to the racing
tables. Folders that are still running or lost a seed are reported as far as they go, and marked
incomplete.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, positive_speed


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="report.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR", help="results folders of experiments/run.py")
    parser.add_argument("--out", required=True, metavar="DIR", help="folder of the report (created)")
    parser.add_argument("--controller", nargs="?", type=positive_speed, const=8.0, metavar="M_PER_S",
                        help="also drive the hand controller of docs/carenv-single-agent.md §8.3 on the "
                             "racing runs' evaluation tracks at this target speed (default 8 m/s) and "
                             "show it in the tables and figures (~30 s per env)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from xrl_jax.report import ReportError, write_report

    try:
        report = write_report(args.runs, args.out, args.controller)
    except ReportError as err:
        print(f"report.py: error: {err}", file=sys.stderr)
        return 2
    print(report.read_text())
    print(f"written: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
