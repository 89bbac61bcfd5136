"""Two versions of the project timed side by side (``bench.py compare --against REV``): the working
tree and REV, checked out as a detached git worktree in a temporary folder, each run ``bench.py
train`` with the same options in a fresh process of their own, in turn, for several rounds; the
report gives each configuration's per-round rates, the per-round ratios (working tree / REV), their
median, min–max and a distribution-free interval.

Why this shape: a speed claim between two commits is only as good as the noise it rises above. Fresh
processes keep one version's compilation caches, allocator state and imported modules from the
other's; alternating the order each round (AB, BA, AB, …) lets slow drift of a shared machine (other
jobs, thermal state) fall on both sides alike; a ratio per round pairs runs that ran next to each
other. Jax-free: the parent only orchestrates (on a GPU host, a parent holding the device would take
the memory its children need).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

TREE, REV = "tree", "rev"  # the working tree (as it is, uncommitted changes included) and --against
KEY_FIELDS = ("env", "algo", "width", "seeds")  # what names one of bench.py train's rows
# What each timed step does and where: reported where the sides differ (the devices do when each side
# spreads its seeds as its own default says: that difference is often what is being measured).
WORK_FIELDS = ("num_envs", "batch_size", "devices")
INTERVAL_CONFIDENCE = 0.9
INTERVAL_NOTE = (
    "interval: order statistics of the per-round ratios that hold the median ratio with the stated "
    f"confidence (the sign test's interval, distribution-free; exact if the rounds are independent and "
    f"alike); the narrowest with confidence >= {INTERVAL_CONFIDENCE}, or else min-max with less "
    "(3 rounds: 0.75, 4: 0.875; 5 rounds reach 0.94)"
)
STDERR_LINES_QUOTED = 3

# Run in each tree before its first timed run (cwd = the tree, its own PYTHONPATH): does its bench.py
# have a train sub-command, does that accept the options, and do its imports come from the tree? A
# string, not a function of this module: REV need not have this module.
PREFLIGHT = r"""
import argparse, contextlib, importlib.util, io, json, os, pathlib, sys
train_args = json.loads(sys.argv[1])
module_spec = importlib.util.spec_from_file_location("bench_preflight", "experiments/bench.py")
bench = importlib.util.module_from_spec(module_spec)
sys.modules["bench_preflight"] = bench
module_spec.loader.exec_module(bench)

class Parsed(Exception):
    pass

original_parse_args = argparse.ArgumentParser.parse_args

def parse_then_stop(self, *args, **kwargs):
    original_parse_args(self, *args, **kwargs)
    raise Parsed

def parse(argv):
    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            if hasattr(bench, "build_parser"):
                parser = bench.build_parser()
                args = parser.parse_args(argv)
                if hasattr(bench, "check_arguments"):
                    bench.check_arguments(parser, args)
            else:  # an older bench.py builds its parser inside main: main stops once it has parsed
                argparse.ArgumentParser.parse_args = parse_then_stop
                bench.main(argv)
    except Parsed:
        pass
    except SystemExit as exc:
        return "" if exc.code in (0, None) else (err.getvalue().strip().splitlines() or ["?"])[-1]
    return ""

root = os.path.realpath(os.getcwd())
tops = {p.name.removesuffix(".py") for p in pathlib.Path(root).iterdir()}
foreign = sorted(
    f"{name} from {module.__file__}" for name, module in list(sys.modules.items())
    if name.split(".")[0] in tops and getattr(module, "__file__", None)
    and not os.path.realpath(module.__file__).startswith(root + os.sep)
)
no_train = parse(["train", "--help"])
print(json.dumps({"no_train": no_train, "rejects": "" if no_train else parse(["train", *train_args]),
                  "foreign": foreign}))
"""


class CompareError(Exception):
    """A comparison that cannot go on, in one line; ``status`` 2 for a request that cannot be carried
    out as given (bad REV, not a repository, an option a side rejects), 1 for a run that failed."""

    def __init__(self, message: str, status: int = 2):
        super().__init__(message)
        self.status = status


def round_order(rounds: int) -> list[tuple[str, str]]:
    """Which side runs first in each round: the working tree, then REV, then the other way round
    (ABBA…), so that a machine slowing down or speeding up over the rounds favours neither."""
    return [(TREE, REV) if r % 2 == 0 else (REV, TREE) for r in range(rounds)]


def render_options(options: Iterable[tuple[str, object]]) -> list[str]:
    """Command-line words for (option, value) pairs as argparse parsed them: a list gives its items
    (an empty one the bare option, as ``--set`` with nothing), anything else its ``str``."""
    words: list[str] = []
    for option, value in options:
        words += [option, *map(str, value if isinstance(value, list | tuple) else [value])]
    return words


def configuration_key(row: dict) -> tuple:
    """One of bench.py train's rows named by its loop variables but the devices (see
    :data:`WORK_FIELDS`)."""
    return tuple(row.get(field) for field in KEY_FIELDS)


def keyed_rows(rows: list[dict]) -> dict[tuple, dict]:
    """The rows by :func:`configuration_key`, with the row's rank among rows of the same key appended
    (several ``--devices`` values time one configuration several times, in the same order per side).
    Rows of older versions, which had no ``devices``, ran on one device."""
    seen: dict[tuple, int] = {}
    keyed = {}
    for row in rows:
        key = configuration_key(row)
        seen[key] = seen.get(key, -1) + 1
        keyed[(*key, seen[key])] = {"devices": 1} | row
    return keyed


def parse_train_report(text: str) -> dict:
    """The JSON document ``bench.py train`` printed (the last one, should anything else share its
    standard output) as ``{"machine": ..., "rows": {configuration_key: row}}``."""
    decoder = json.JSONDecoder()
    starts = [0] + [i + 1 for i, char in enumerate(text) if char == "\n" and text[i + 1 : i + 2] == "{"]
    for start in reversed(starts):
        try:
            report, _ = decoder.raw_decode(text[start:].lstrip())
        except json.JSONDecodeError:
            continue
        rows = report.get("results") if isinstance(report, dict) else None
        if isinstance(rows, list) and rows and all("env_steps_per_s" in row for row in rows):
            return {"machine": report.get("machine"), "rows": keyed_rows(rows)}
    raise CompareError("bench.py train printed no JSON report with env_steps_per_s in every row", 1)


def median_interval(values: list[float], confidence: float = INTERVAL_CONFIDENCE) -> dict:
    """An interval that holds the median of the distribution ``values`` are drawn from: the k-th
    smallest to the k-th largest value holds it with probability 1 - 2·P(Binomial(n, ½) < k) (the sign
    test's interval, whatever the distribution). The narrowest with at least ``confidence``; with too
    few values for that, min–max and the confidence it has (n = 3: 0.75)."""
    ordered = sorted(values)
    n = len(ordered)

    def coverage(k: int) -> float:
        return 1.0 - 2.0 * sum(math.comb(n, i) for i in range(k)) / 2.0**n

    k = max([k for k in range(1, (n + 1) // 2 + 1) if coverage(k) >= confidence], default=1)
    return {"low": ordered[k - 1], "high": ordered[n - k], "confidence": coverage(k)}


def ratio_statistics(tree_rates: list[float], rev_rates: list[float]) -> dict:
    """Per-round ratios (working tree / REV, rounds paired) and their median, min, max and interval."""
    ratios = [tree / rev for tree, rev in zip(tree_rates, rev_rates, strict=True)]
    return {
        "ratios": ratios,
        "median_ratio": statistics.median(ratios),
        "min_ratio": min(ratios),
        "max_ratio": max(ratios),
        "interval": median_interval(ratios),
    }


def last_lines(text: str, count: int = STDERR_LINES_QUOTED) -> str:
    """The last ``count`` non-blank lines of a child's output, joined into one line."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return " | ".join(lines[-count:]) or "(nothing on standard error)"


def git(root: Path, *args: str) -> str:
    """``git -C root args`` 's standard output; its one-line complaint as a CompareError."""
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
    except FileNotFoundError:
        raise CompareError("git is not installed: compare checks --against out with git worktree") from None
    if done.returncode != 0:
        raise CompareError(f"git {args[0]}: {last_lines(done.stderr, 1)}")
    return done.stdout.strip()


def repository_prefix(root: Path) -> str:
    """Where ``root`` lies inside its git repository ("" at its top, else "sub/dir/")."""
    try:
        return git(root, "rev-parse", "--show-prefix")
    except CompareError as err:
        raise CompareError(
            f"{root} is not in a git repository: compare checks --against out with git"
        ) from err


def resolve_revision(root: Path, rev: str, prefix: str = "") -> str:
    """REV's commit sha, refused in one line where it names no commit or has no experiments/bench.py."""
    try:
        sha = git(root, "rev-parse", "--verify", "--quiet", "--end-of-options", f"{rev}^{{commit}}")
    except CompareError:
        raise CompareError(f"--against {rev}: not a commit of this repository") from None
    try:
        git(root, "cat-file", "-e", f"{sha}:{prefix}experiments/bench.py")
    except CompareError:
        raise CompareError(f"--against {rev}: its tree has no experiments/bench.py") from None
    return sha


def tree_state(root: Path) -> dict:
    """The working tree's HEAD and whether it differs from it (changed or untracked files)."""
    return {
        "path": str(root),
        "head": git(root, "rev-parse", "HEAD"),
        "dirty": bool(git(root, "status", "--porcelain", "--", ".")),
    }


@contextlib.contextmanager
def checked_out(root: Path, sha: str, prefix: str = "") -> Iterator[Path]:
    """``sha`` as a detached git worktree in a temporary folder, for the duration of the block; the
    project's root inside it. Removed however the block ends (an error, a Ctrl-C)."""
    scratch = Path(tempfile.mkdtemp(prefix="xrl-jax-compare-"))
    checkout = scratch / "tree"
    try:
        git(root, "worktree", "add", "--detach", "--quiet", str(checkout), sha)
        yield checkout / prefix
    finally:
        try:
            git(root, "worktree", "remove", "--force", str(checkout))
        except CompareError:  # half made, or its folder gone: git forgets worktrees whose folder is gone
            shutil.rmtree(scratch, ignore_errors=True)
            with contextlib.suppress(CompareError):
                git(root, "worktree", "prune")
        shutil.rmtree(scratch, ignore_errors=True)


def child_environment(tree: Path) -> dict:
    """The parent's environment with PYTHONPATH = the tree alone: both sides see the same variables
    and each imports its own package, not an installed one."""
    return {**os.environ, "PYTHONPATH": str(tree)}


def preflight(tree: Path, train_args: list[str], label: str) -> None:
    """Refuse, before any timed run, a side whose bench.py has no train sub-command, rejects the
    options, or would import the project from outside its tree."""
    done = subprocess.run(
        [sys.executable, "-c", PREFLIGHT, json.dumps(train_args)],
        cwd=tree, env=child_environment(tree), capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        raise CompareError(f"{label}: its bench.py does not load: {last_lines(done.stderr)}", 1)
    found = json.loads(done.stdout.strip().splitlines()[-1])
    found.update({k: found[k].split("error: ", 1)[-1] for k in ("no_train", "rejects")})  # argparse's prefix
    if found["no_train"]:
        raise CompareError(f"{label}: its bench.py has no train sub-command ({found['no_train']})")
    if found["rejects"]:
        raise CompareError(f"{label}: its bench.py train rejects the options: {found['rejects']}")
    if found["foreign"]:
        raise CompareError(f"{label}: its run would import {found['foreign'][0]}, outside its tree", 1)


def run_train(tree: Path, train_args: list[str], label: str) -> dict:
    """One ``bench.py train`` in a fresh process in ``tree``, its report parsed; a failure as a
    CompareError that quotes the child's last lines of standard error."""
    done = subprocess.run(
        [sys.executable, os.path.join("experiments", "bench.py"), "train", *train_args],
        cwd=tree, env=child_environment(tree), capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        raise CompareError(
            f"{label}: bench.py train failed (exit status {done.returncode}): {last_lines(done.stderr)}", 1
        )
    return parse_train_report(done.stdout)


def check_same_configurations(reports: dict[str, list[dict]]) -> None:
    """Refuse, after the first round, sides whose runs timed different configurations (their defaults
    differ, say): there would be nothing to pair."""
    tree_keys, rev_keys = set(reports[TREE][0]["rows"]), set(reports[REV][0]["rows"])
    if tree_keys != rev_keys:
        only = sorted(tree_keys ^ rev_keys, key=str)
        raise CompareError(
            f"the sides timed different configurations {KEY_FIELDS} (set the options that differ): {only}",
            1,
        )


def summarise(reports: dict[str, list[dict]]) -> list[dict]:
    """Per configuration: each side's rate per round, the work it timed where the sides differ, and
    the ratio statistics."""
    results = []
    for key in reports[TREE][0]["rows"]:
        rates = {side: [r["rows"][key]["env_steps_per_s"] for r in reports[side]] for side in (TREE, REV)}
        first = {side: reports[side][0]["rows"][key] for side in (TREE, REV)}
        work = {f: [first[TREE].get(f), first[REV].get(f)] for f in WORK_FIELDS}
        differ = {f: pair for f, pair in work.items() if pair[0] != pair[1]}
        results.append({
            **dict(zip(KEY_FIELDS, key[:-1], strict=True)),
            "tree_env_steps_per_s": rates[TREE],
            "rev_env_steps_per_s": rates[REV],
            **({"work_differs_tree_rev": differ} if differ else {}),
            **ratio_statistics(rates[TREE], rates[REV]),
        })  # fmt: skip
    return results


def compare(
    root: Path,
    against: str,
    rounds: int,
    train_args: list[str],
    progress: Callable[[str], None] = lambda line: None,
) -> dict:
    """Time ``bench.py train train_args`` in the working tree at ``root`` and in ``against``,
    alternating for ``rounds`` rounds; the report (:data:`INTERVAL_NOTE` says what its interval is)."""
    root = Path(root).resolve()
    prefix = repository_prefix(root)
    sha = resolve_revision(root, against, prefix)
    state = tree_state(root)
    labels = {TREE: "the working tree", REV: f"--against {against} ({sha[:12]})"}
    with checked_out(root, sha, prefix) as rev_tree:
        trees = {TREE: root, REV: rev_tree}
        for side in (TREE, REV):
            preflight(trees[side], train_args, labels[side])
        reports: dict[str, list[dict]] = {TREE: [], REV: []}
        order = round_order(rounds)
        for number, sides in enumerate(order, start=1):
            for side in sides:
                progress(f"round {number}/{rounds}: {labels[side]}")
                reports[side].append(run_train(trees[side], train_args, labels[side]))
            if number == 1:
                check_same_configurations(reports)
    return {
        "command": "compare",
        "train_options": train_args,
        "rounds": rounds,
        "order": [list(sides) for sides in order],
        "tree": state,
        "rev": {"against": against, "sha": sha},
        "machine": reports[TREE][0]["machine"],
        "interval_note": INTERVAL_NOTE,
        "results": summarise(reports),
    }
