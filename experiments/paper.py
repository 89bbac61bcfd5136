"""The paper's whole protocol as one resumable campaign, then the report.

    python experiments/paper.py --out DIR [--dry-run] [--preset paper] [--seeds 20] [--only PATTERN ...]

Runs, one results folder each under DIR: every env x agent at the preset (20 seeds; Fig. 5-7), the
kappa sweep of Fig. 8 (discrete Country Road, kappa = -0.01 ... 0.1) and the Table I variants (XSAC on
Country Road with its mixture weights from hidden layer 1 and 2; layer 3 is the main XSAC run).
A finished run is skipped, a started one resumed, so the same command continues a stopped campaign
(Ctrl-C or SIGTERM stop the running run cleanly and end the campaign). At the end it writes the
report (experiments/report.py, with each scenario's yardstick unless --no-controller) to
DIR/report. ``--dry-run`` prints the plan instead: every run, its
members, the memory per member and the groups on this machine's devices, the FLOPs per update as
it runs (XLA's cost analysis of the packed per-object layers, weighted with the measured chance
that a batch holds too many objects for them; beside it the every-slot count; docs/performance.md)
and the hours they take, each for what would run (a started or finished run's own config.json; a
new one's preset, --seeds and --set): on this machine by its calibrations (seconds per vector step
and per evaluation, measured for each configuration and its members per device, and cached in
XRL_JAX_CACHE_DIR; the missing ones are measured first, a minute or more each), or with
--no-calibrate by the FLOP model (the updates' FLOPs at a measured CPU rate); on an H100 by the FLOP
model at --utilisation.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, fail, positive_int

from xrl_jax.campaign import (
    CampaignSettings,
    campaign,
    check_sets,
    format_plan,
    plan,
    run_campaign,
    select_runs,
)
from xrl_jax.config import PRESETS, ConfigError

PROG = "paper.py"
__all__ = ["campaign", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=PROG,
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 2)[2],
    )
    parser.add_argument(
        "--out", required=True, metavar="DIR", help="campaign folder (one sub-folder per run)"
    )
    parser.add_argument("--dry-run", action="store_true", help="print the plan and its cost; run nothing")
    parser.add_argument(
        "--preset", choices=PRESETS, default="paper", help="preset of every run (default paper)"
    )
    parser.add_argument("--seeds", type=positive_int, default=20, help="seeds per configuration (default 20)")
    parser.add_argument(
        "--only",
        action="append",
        default=None,
        metavar="PATTERN",
        help="only the runs of this name or shell-style pattern (repeatable), e.g. 'tracking-*'",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a run setting for every run this command starts (repeatable), e.g. checkpoint_minutes=10; "
        "resumed runs keep their own",
    )
    parser.add_argument(
        "--no-controller",
        action="store_true",
        help="leave the yardsticks out of the report (hand controller, scripted Intersection driver; "
        "they drive every evaluation episode)",
    )
    parser.add_argument(
        "--no-calibrate",
        action="store_true",
        help="--dry-run: count CPU hours with the FLOP model instead of this machine's calibrations "
        "(measuring the missing ones takes a minute or more each)",
    )
    parser.add_argument(
        "--utilisation",
        type=float,
        default=0.25,
        help="fraction of an H100's float32 rate the updates reach, for the estimate (0.25)",
    )
    return parser


def continue_command(argv: list[str]) -> str:
    """The command that continues a stopped campaign: this one again, with its preset, seeds and
    --only (a bare --out would go on with the whole paper at its default preset); shell-quoted."""
    return shlex.join(["python", "experiments/paper.py", *argv])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    if not 0.0 < args.utilisation <= 1.0:
        return fail(PROG, f"--utilisation must be in (0, 1], got {args.utilisation}")
    try:
        runs = select_runs(args.only)
        check_sets(runs, args.set, args.preset, args.seeds)
    except ConfigError as err:
        return fail(PROG, err)
    out = Path(args.out)
    from xrl_jax.train import cpu_devices, hosts  # imports jax: not before --help

    if not hosts.wanted():  # a job of several processes starts its backend in jax.distributed
        # Once for every run of the campaign, before JAX's backend starts; each run takes its own count
        # of these devices (the Intersection a device per member, up to two per core). The backend
        # starts now: a run's own split (run.py's) would replace the count.
        import jax

        cpu_devices.split_cpu_host(cpu_devices.most_cpu_devices(cpu_devices.cpu_cores()))
        jax.devices()
    if args.dry_run:
        return dry_run(args, runs, out)
    import run as run_cli

    settings = CampaignSettings(args.preset, args.seeds, tuple(args.set), controller=not args.no_controller)
    return run_campaign(
        runs,
        out,
        settings,
        run_one=run_cli.main,
        say=lambda message: print(f"{PROG}: {message}", file=sys.stderr),
        show=print,
        again=continue_command(argv),
    )


def dry_run(args: argparse.Namespace, runs: list, out: Path) -> int:
    """Print the plan (:func:`~xrl_jax.campaign.plan`), measuring the missing calibrations each in a
    fresh process split as its run would be, unless --no-calibrate."""
    from xrl_jax.benchmarks import calibration
    from xrl_jax.runs.folder import RunFolderError

    try:
        rows = plan(
            runs, out, args.preset, args.seeds, args.utilisation, tuple(args.set),
            calibrate=None if args.no_calibrate else calibration.calibrate_in_child,
            say=lambda message: print(f"{PROG}: {message}", file=sys.stderr),
        )  # fmt: skip
    except RunFolderError as err:  # a started run's config.json unreadable: say which, not a trace
        return fail(PROG, err)
    for line in format_plan(rows, args.utilisation):
        print(line)
    return 0


if __name__ == "__main__":
    status = main()
    from xrl_jax.train.cpu_devices import end_process

    end_process(status)  # a split CPU host ends without its teardown
