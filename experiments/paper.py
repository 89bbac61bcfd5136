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
and the device-hours they take at a stated throughput.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, positive_int

from xrl_jax.config import ALGOS, ENVS, PRESETS, ConfigError, parse_overrides

KAPPAS = "-0.01,-0.001,0,0.001,0.01,0.1"
# Device throughput for the estimate, in FLOP/s the update achieves. This CPU: bench.py update measured
# 96-103 GFLOP/s for the width-256 X agents on 2 cores (README, Benchmarks). An H100 SXM: 67 TFLOP/s
# float32 on its datasheet, of which these small networks reach a fraction: --utilisation.
CPU_FLOPS = 100e9
H100_FLOPS = 67e12


@dataclass(frozen=True)
class PlannedRun:
    name: str
    env: str
    algo: str
    sets: tuple[str, ...] = ()
    sweep: tuple[str, ...] = ()
    figure: str = ""

    def args(self, preset: str, seeds: int) -> list[str]:
        out = ["--env", self.env, "--algo", self.algo, "--preset", preset, "--seeds", str(seeds)]
        for item in self.sets:
            out += ["--set", item]
        for item in self.sweep:
            out += ["--sweep", item]
        return out


def campaign() -> list[PlannedRun]:
    runs = [
        PlannedRun(
            f"{env}-{algo}",
            env,
            algo,
            figure={"country_road": "Fig. 5", "tracking": "Fig. 6", "intersection": "Fig. 7"}[env],
        )
        for env in ENVS
        for algo in ALGOS
    ]
    runs.append(
        PlannedRun(
            "country_road-xdsac-kappa", "country_road", "xdsac", sweep=(f"kappa={KAPPAS}",), figure="Fig. 8"
        )
    )
    for depth in (1, 2):
        runs.append(
            PlannedRun(
                f"country_road-xsac-weights{depth}",
                "country_road",
                "xsac",
                sets=(f"weight_depth={depth}",),
                figure="Table I",
            )
        )
    return runs


def run_status(folder: Path) -> str:
    """ "done" (a complete summary), "started" (a config, so --resume continues it) or "new"."""
    summary = folder / "summary.json"
    if summary.is_file():
        try:
            if json.loads(summary.read_text()).get("complete"):
                return "done"
        except ValueError:
            pass
    return "started" if (folder / "config.json").is_file() else "new"


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="paper.py",
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
        "~30 s per env)",
    )
    parser.add_argument(
        "--utilisation",
        type=float,
        default=0.25,
        help="fraction of an H100's float32 rate the updates reach, for the estimate (0.25)",
    )
    return parser


def fail(message: str) -> int:
    print(f"paper.py: error: {message}", file=sys.stderr)
    return 2


def check_sets(runs: list[PlannedRun], sets: list[str]) -> str | None:
    """Why the ``--set`` items cannot reach the runs (one malformed, a setting given twice, or one that
    a run sets itself), or None: checked before the first run starts rather than when a later run
    refuses them and ends the campaign halfway."""
    try:
        parse_overrides(sets)
    except ConfigError as err:
        return str(err)
    for planned in runs:
        try:
            parse_overrides([*planned.sets, *sets])
        except ConfigError as err:
            return f"{planned.name} sets this itself: {err}"
    return None


def plan(runs: list[PlannedRun], out: Path, preset: str, seeds: int, utilisation: float) -> list[dict]:
    """One row per run: its status, members, memory and groups on this machine, FLOPs and device-hours."""
    from xrl_jax.config import parse_sweep, resolve_config
    from xrl_jax.occupancy import load_occupancy, update_cost
    from xrl_jax.resources import format_bytes
    from xrl_jax.train import get_trainer, plan_memory

    occupancy = load_occupancy()
    rows = []
    for run in runs:
        cfg = resolve_config(
            run.env,
            run.algo,
            preset,
            num_seeds=seeds,
            overrides=parse_overrides(list(run.sets)),
            sweep=parse_sweep(list(run.sweep)),
        )
        trainer = get_trainer(cfg)
        memory = plan_memory(trainer, cfg)
        # FLOPs as they run: the packed update, or every slot when a batch overflows (by the measured
        # occupancy of docs/set_occupancy.json, members sharing their branches as on one device).
        cost = update_cost(trainer.agent, cfg.batch_size, cfg.num_members, occupancy)
        flops = cost["expected"]
        per_member = max(cfg.total_steps - cfg.warmup_steps, 0)
        if cfg.multi_agent:  # one update per acting vehicle: as many as measured per env step
            per_member *= occupancy["intersection"]["acting_vehicles_per_env_step"]
        total = flops * per_member * cfg.num_members
        rows.append(
            {
                "run": run.name,
                "figure": run.figure,
                "status": run_status(out / run.name),
                "members": cfg.num_members,
                "steps": cfg.total_steps,
                "memory_per_member": format_bytes(memory["per_seed_bytes"]["total"]),
                "groups": len(memory["groups"]),
                "devices": memory["devices"],
                "gflop_per_update": flops / 1e9,
                "dense_gflop_per_update": cost["dense"] / 1e9,
                "fallback_probability": cost["fallback_probability"],
                "pflop_total": total / 1e15,
                "cpu_hours": total / CPU_FLOPS / 3600,
                "h100_hours": total / (H100_FLOPS * utilisation) / 3600,
            }
        )
    return rows


def print_plan(rows: list[dict], utilisation: float) -> None:
    header = (
        f"{'run':<30} {'for':<8} {'status':<8} {'members':>7} {'memory/member':>13} {'groups':>6} "
        f"{'GFLOP/upd':>9} {'dense':>7} {'CPU h':>10} {'H100 h':>8}"
    )
    print(header)
    for r in rows:
        print(
            f"{r['run']:<30} {r['figure']:<8} {r['status']:<8} {r['members']:>7} "
            f"{r['memory_per_member']:>13} {r['groups']:>6} {r['gflop_per_update']:>9.3g} "
            f"{r['dense_gflop_per_update']:>7.3g} {r['cpu_hours']:>10,.1f} {r['h100_hours']:>8,.2f}"
        )
    todo = [r for r in rows if r["status"] != "done"]
    cpu, h100 = sum(r["cpu_hours"] for r in todo), sum(r["h100_hours"] for r in todo)
    print(
        f"total still to run: {cpu:,.0f} CPU hours at {CPU_FLOPS / 1e9:.0f} GFLOP/s (this 2-core CPU), "
        f"{h100:,.1f} H100 hours at {utilisation:.0%} of {H100_FLOPS / 1e12:.0f} TFLOP/s; updates only "
        "(on this CPU a vector step of the envs costs ~22 us against ~40 ms for an update: bench.py tracks)"
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not 0.0 < args.utilisation <= 1.0:
        return fail(f"--utilisation must be in (0, 1], got {args.utilisation}")
    runs = campaign()
    if args.only:
        runs = [r for r in runs if any(fnmatch.fnmatchcase(r.name, pattern) for pattern in args.only)]
        if not runs:
            return fail(
                f"--only {' '.join(args.only)} matches no run; runs: {', '.join(r.name for r in campaign())}"
            )
    problem = check_sets(runs, args.set)
    if problem:
        return fail(problem)
    out = Path(args.out)
    if args.dry_run:
        print_plan(plan(runs, out, args.preset, args.seeds, args.utilisation), args.utilisation)
        return 0
    import run as run_cli

    out.mkdir(parents=True, exist_ok=True)
    failed = []
    for planned in runs:
        folder = out / planned.name
        status = run_status(folder)
        if status == "done":
            print(f"paper.py: {planned.name}: done, skipped", file=sys.stderr)
            continue
        if status == "started":
            argv_run = ["--resume", str(folder), "--quiet"]
        else:
            extra = [word for item in args.set for word in ("--set", item)]
            argv_run = [*planned.args(args.preset, args.seeds), *extra, "--out", str(folder), "--quiet"]
        print(
            f"paper.py: {planned.name}: {'resuming' if status == 'started' else 'starting'}",
            file=sys.stderr,
        )
        code = run_cli.main(argv_run)
        if code in (130, 143):  # stopped by a signal: the run kept its checkpoint; end the campaign
            print(
                f"paper.py: stopped; continue with: python experiments/paper.py --out {out}", file=sys.stderr
            )
            return code
        if code == 2:
            return code
        if code != 0:
            failed.append(planned.name)
    from xrl_jax.report import write_report

    folders = [out / r.name for r in runs if (out / r.name / "config.json").is_file()]
    report = write_report(folders, out / "report", controller=not args.no_controller)
    print(f"report: {report}")
    if failed:
        print(
            f"paper.py: these runs did not finish: {', '.join(failed)} (see their messages above)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
