"""Evaluate a finished run's agents again, on its training tracks or on its held-out tracks.

    python experiments/evaluate.py RESULTS_DIR [--tracks train|eval] [--episodes N] [--key K]
                                   [--mode eval|deterministic|stochastic] [--import MODULE]

Every seed's agent (every member's, in a sweep) is restored from the run's newest checkpoint and
driven with the run's evaluation
protocol (docs/algorithms.md §6.1) over the first N tracks of the chosen set, one episode per track:
``train`` is the fixed training bank of a run with ``train_tracks`` > 0 (the gap to ``eval`` is the
generalisation gap), ``eval`` the run's held-out evaluation tracks. Prints each seed's average return
and early-termination rate and their IQM with its 95 % stratified bootstrap CI over seeds, and
writes the same to ``RESULTS_DIR/evaluation_<tracks>.json`` (``evaluation_<tracks>_<mode>.json``
for the diagnostic modes: ``deterministic`` drives every agent greedily, XSAC too; ``stochastic``
samples every agent's policy, so a greedy agent's near-ties between actions no longer decide).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import IMPORT_HELP, OneLineParser, fail, import_user_modules, positive_int

PROG = "evaluate.py"


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a results folder of experiments/run.py (racing scenarios)")
    parser.add_argument(
        "--import", dest="imports", metavar="MODULE", action="append", default=[], help=IMPORT_HELP
    )
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
        choices=("eval", "deterministic", "stochastic"),  # xrl_jax.agents.EVAL_MODES: not imported for --help
        default="eval",
        help="eval: each agent's evaluation policy as in the reference (XSAC samples, the others are "
        "greedy; default); deterministic: greedy for every agent, XSAC at the approximate mode of its "
        "mixture (docs/algorithms.md §3.9); stochastic: a sample of every agent's policy, without "
        "exploration; both are diagnostics outside the paper's protocol",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    problem = import_user_modules(argv)  # a run on a user's env needs the module that registers it
    if problem:
        return fail(PROG, problem)
    args = build_parser().parse_args(argv)
    from xrl_jax.runs.folder import RunFolderError
    from xrl_jax.train import evaluate_run

    try:
        written = evaluate_run(args.run, args.tracks, args.episodes, args.key, args.mode, log=print)
    except RunFolderError as err:
        return fail(PROG, err)
    print(f"written: {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
