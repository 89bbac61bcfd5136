"""What the experiment scripts' command lines share: a parser that fails in one line, the one
way a script reports a failure, and the argument types. Jax-free, so ``--help`` and bad input
answer at once."""

from __future__ import annotations

import argparse
import math
import sys

BAD_INPUT = 2  # the exit status of a request the script cannot carry out as given


def fail(prog: str, message, status: int = BAD_INPUT) -> int:
    """Report a failure as ``<prog>: error: <message>`` in one line on standard error; returns
    ``status`` for ``main`` to return (2, bad input, unless told otherwise)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return status


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a bad value in one line (no usage block), exit status 2."""

    def error(self, message: str):
        self.exit(BAD_INPUT, f"{self.prog}: error: {message}\n")


def _integer(text: str, minimum: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a {what} integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected a {what} integer, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1, with a one-line error otherwise."""
    return _integer(text, 1, "positive")


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0, with a one-line error otherwise."""
    return _integer(text, 0, "non-negative")


def positive_speed(text: str) -> float:
    """argparse type: a finite speed > 0 in m/s, with a one-line error otherwise."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a speed in m/s, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive, finite speed in m/s, got {text}")
    return value


def fraction(text: str) -> float:
    """argparse type: a number in [0, 1], with a one-line error otherwise."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {value}")
    return value
