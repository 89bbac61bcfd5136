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


IMPORT_HELP = (
    "a Python module (dotted name) or .py file to import first, e.g. one that registers your own env "
    "with xrl_jax.register_env (docs/ecosystem.md); repeatable"
)


def import_user_modules(argv: list[str] | None) -> str | None:
    """Import every ``--import`` target of ``argv`` (before the full parser, whose ``--env`` choices
    then include the envs they register); returns a one-line problem, or None."""
    import importlib
    import importlib.util
    from pathlib import Path

    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--import", dest="imports", action="append", default=[])
    targets = pre.parse_known_args(sys.argv[1:] if argv is None else argv)[0].imports
    for target in targets:
        try:
            if target.endswith(".py"):
                path = Path(target)
                spec = importlib.util.spec_from_file_location(path.stem, path)
                if spec is None or not path.is_file():
                    return f"--import {target}: no such file"
                module = importlib.util.module_from_spec(spec)
                sys.modules[path.stem] = module
                spec.loader.exec_module(module)
            else:
                importlib.import_module(target)
        except Exception as err:  # the user's code: whatever it raises is reported in one line
            lines = str(err).strip().splitlines()
            return f"--import {target}: {type(err).__name__}: {lines[0] if lines else ''}"
    return None
