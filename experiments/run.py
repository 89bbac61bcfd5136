"""Train SAC / DSAC / XSAC / XDSAC on a CarEnv scenario: ``python experiments/run.py --env tracking``.

The command-line surface is fixed here; the vectorised trainer behind it lands with the trainer issue.
"""

from __future__ import annotations

import argparse
import sys

ENVS = ("country_road", "tracking", "intersection")
ALGOS = ("sac", "dsac", "xsac", "xdsac")
PRESETS = ("paper", "quick", "smoke")


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1, with a one-line error otherwise."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run.py",
        description="Train explainable mixture-policy agents (and SAC baselines) on CarEnv scenarios, "
        "all seeds of a run vectorised in one process.",
    )
    parser.add_argument(
        "--env", choices=ENVS, default="tracking", help="scenario to train on (default: %(default)s)"
    )
    parser.add_argument("--algo", choices=ALGOS, default="xsac", help="agent (default: %(default)s)")
    parser.add_argument("--seeds", type=positive_int, default=1, help="independent seeds trained at once")
    parser.add_argument(
        "--steps", type=positive_int, default=None, help="environment steps per seed (default: preset)"
    )
    parser.add_argument(
        "--preset", choices=PRESETS, default="paper", help="hyper-parameter preset (default: %(default)s)"
    )
    parser.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override one hyper-parameter; repeatable",
    )
    parser.add_argument("--out", default=None, help="results folder (default: results/<env>-<algo>-<time>)")
    parser.add_argument("--resume", default=None, metavar="DIR", help="continue the run stored in DIR")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for item in args.set:
        if "=" not in item or not item.split("=", 1)[0]:
            print(f"run.py: error: --set expects KEY=VALUE, got {item!r}", file=sys.stderr)
            return 2
    print(
        "run.py: error: the vectorised trainer is not available in this version yet; "
        "see the README for what can be run today",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    sys.exit(main())
