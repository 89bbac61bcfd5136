"""Train SAC / DSAC / XSAC / XDSAC on a CarEnv scenario: ``python experiments/run.py --env tracking``,
or on your own env (``--import`` the module that registers it, docs/ecosystem.md).

All seeds of a run, and all points of a hyper-parameter sweep (``--sweep kappa=0,0.01``), train in
one program: the whole SAC loop is one compiled chunk, vmapped over members (seed x sweep point) and
spread over every device (``--devices``) and, with ``--coordinator``, over several processes (see
``xrl_jax/train/``). Results land in one folder (``--out``) that ``--resume`` can continue; a
stopped and resumed run gives exactly the metrics of an uninterrupted one.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import IMPORT_HELP, OneLineParser, fail, import_user_modules, non_negative_int, positive_int

from xrl_jax.config import PRESETS, TRAINED_ALGOS, settings_help  # jax-free: --help stays fast
from xrl_jax.config.scenarios import known_envs

PROG = "run.py"
ROOT = Path(__file__).resolve().parents[1]
EXIT_DIVERGED = 3
EXIT_FAILED = 1  # a failure the message explains (full disk, no usable checkpoint, a lost process)


EPILOG = """\
presets:
  paper  the per-configuration hyper-parameters of docs/algorithms.md §5.7 (1e6 steps, buffer
         1e6, batch 256, 4 envs per seed, evaluation every 1e5 steps on 100 fixed tracks)
  quick  240k steps per seed on Tracking, 320k on Country Road (evaluated every 40k; 80k, every
         5k, for an env of your own), a buffer that keeps every transition, width-64 networks
         (Tracking's SAC, DSAC and XSAC: 128), batch 128, and optimisation constants for a short
         budget (initial alpha 0.005, alpha lr 1e-3, actor and critic lr 6e-4, all three
         decaying linearly to zero by the last update, gamma 0.98); the README's Results give
         each run's wall time
  smoke  a few hundred steps with tiny networks, for tests
  intersection (multi-agent, one shared policy): paper = the released configs (5e6 env steps,
         buffer 1.5e7 agent transitions, batch 512, 2 envs, re-initialisation every 500,001 steps,
         evaluation on 20 episodes of 60 s with 8 vehicles); quick = 200k env steps, width 64,
         batch 128, fixed alpha 0.005, lr 6e-4, evaluation every 10k steps on 10 episodes

--set KEY=VALUE overrides one setting (repeatable); values are parsed with the setting's type
  (integers also as 1e6, optional ones as none). Unknown keys fail with the list of allowed ones.

{settings}

sweeps (--sweep FIELD=V1,V2,..., repeatable; the grid is the product of the lists):
  every point x every seed trains in the same program. Sweepable: the traced agent settings
  actor_lr, critic_lr, alpha_lr, gamma, tau, kappa, target_entropy and the initial alpha
  (init_alpha); widths, depths and other static settings need one run per value. The same seed
  starts from the same weights and tracks at every point, so the points differ by their values
  alone. Files are named point_<p>_seed_<i>; summary.json reports every point (IQM, 95 % CI),
  and sweep.png plots final return and early-termination rate against the swept value
  (--baseline DIR adds another run's final score as a line, as in the paper's Fig. 8).

devices and hosts (README "Scaling out"):
  members are spread over all devices JAX sees (--devices N: the first N per process) and run in
  groups when they do not fit a device's memory. Several processes join with --coordinator
  HOST:PORT --num-processes N --process-id I, or the variables JAX_COORDINATOR_ADDRESS,
  JAX_NUM_PROCESSES, JAX_PROCESS_ID, or under SLURM (srun) with no flags at all; every process
  gets the same options and --out (a shared file system), trains its share, and process 0 writes
  the summary. A job whose processes have not all joined (or whose coordinator does not answer)
  within --coordinator-timeout ends in one line. A process that dies mid-run ends the job: the
  others stop with one line when a collective reports it (at once on CPU), but when only JAX's
  missed heartbeats reveal it (a collective that waits for the lost peer, as a GPU's may; a
  process lost before the job's first collective; or one busy for over 100 s), XLA aborts them
  with a page of C++ stack that Python cannot catch (status 134). Either way the committed
  checkpoints are kept. Resume by starting every process again with --resume DIR.

results folder:
  config.json (resolved config, versions, git commit), metrics/seed_<i>.jsonl (every
  log_interval steps), eval/seed_<i>.jsonl, checkpoints/, summary.json (IQM and 95 % stratified
  bootstrap CI over seeds, at the end and at every evaluation step) and learning_curve.png
  (sweeps: point_<p>_seed_<i> files and sweep.png).
  An existing folder is never overwritten: use --resume to continue it. One run writes into a
  folder at a time (a second one is refused); a resume checks that the files it continues are all
  there, and falls back to the previous checkpoint (two are kept) when the newest is damaged.

stopping and failures:
  Ctrl-C (SIGINT) or SIGTERM stops the run at once, or after the running chunk with a checkpoint when
  that ends within XRL_JAX_STOP_GRACE_S (default 30) seconds; the message says what is kept and how
  to resume. Exit status: 0 done, 1 a failure the message explains (full disk, no usable checkpoint,
  a lost process), 2 bad input (also a job that did not assemble), 3 a seed diverged (a non-finite
  loss or parameter: the run stops at once, naming the seed, the step and the quantity, and keeps
  the last good checkpoint), 130/143 stopped by SIGINT/SIGTERM. Right after the second chunk with
  updates the run prints its estimated duration; the progress bar shows the time left.

environment: XRL_JAX_CACHE_DIR (default ~/.cache/xrl-jax) caches generated tracks and compiled code.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=PROG,
        description="Train explainable mixture-policy agents (and SAC baselines) on CarEnv scenarios, "
        "all seeds of a run vectorised in one process.",
        epilog=EPILOG.format(settings=settings_help()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--env", choices=known_envs(), default=None, help="scenario to train on (default: tracking)"
    )
    parser.add_argument(
        "--import", dest="imports", metavar="MODULE", action="append", default=[], help=IMPORT_HELP
    )
    parser.add_argument("--algo", choices=TRAINED_ALGOS, default=None, help="agent (default: xsac)")
    parser.add_argument(
        "--seeds", type=positive_int, default=None, help="independent seeds trained at once (default: 1)"
    )
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="environment steps per seed, a multiple of num_envs (default: the preset's)",
    )
    parser.add_argument(
        "--preset", choices=PRESETS, default=None, help="hyper-parameter preset (default: paper)"
    )
    parser.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=None,
        help="override one setting or hyper-parameter (see below); repeatable",
    )
    parser.add_argument(
        "--out",
        default=None,
        help="results folder, must not exist yet (default: results/<env>-<algo>-<time>)",
    )
    parser.add_argument(
        "--resume",
        default=None,
        metavar="DIR",
        help="continue the run stored in DIR (other options, if given, must match its config)",
    )
    parser.add_argument(
        "--sweep",
        metavar="FIELD=V1,V2,...",
        action="append",
        default=None,
        help="train every value of a traced hyper-parameter in the same program (see below); repeatable",
    )
    parser.add_argument(
        "--baseline", metavar="DIR", default=None, help="a finished run drawn as a line in sweep.png"
    )
    parser.add_argument(
        "--devices", type=positive_int, default=None, help="devices per process to use (default: all)"
    )
    hosts = parser.add_argument_group("several processes (default: JAX's variables, or SLURM's)")
    hosts.add_argument("--coordinator", metavar="HOST:PORT", default=None, help="process 0's address")
    hosts.add_argument("--num-processes", type=positive_int, default=None, help="processes in the job")
    hosts.add_argument("--process-id", type=non_negative_int, default=None, help="this process's index")
    hosts.add_argument(
        "--coordinator-timeout",
        type=positive_int,
        default=120,
        metavar="S",
        help="seconds to wait for the coordinator and the other processes (default 120)",
    )
    parser.add_argument(
        "--log",
        action="append",
        choices=("tensorboard", "wandb"),
        default=[],
        help="also send the records to TensorBoard (<out>/tensorboard) or W&B (project $WANDB_PROJECT, "
        "default xrl-jax; WANDB_MODE=offline works without a network); repeatable; needs the extra of "
        "the same name",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no log lines")
    return parser


def main(argv: list[str] | None = None) -> int:
    from xrl_jax.interrupts import StopController

    # Installed before anything slow (a user's module and the jax it imports): from here on SIGINT and
    # SIGTERM end the run cleanly at any moment.
    with StopController() as stop:
        split_cpu_host_early(sys.argv[1:] if argv is None else argv)
        problem = import_user_modules(argv)  # first: the envs they register become --env choices
        if problem:
            return fail(PROG, problem)
        return _main(build_parser().parse_args(argv), argv, stop)


def split_cpu_host_early(argv: list[str]) -> None:
    """Split a CPU host into its XLA devices (xrl_jax.train.cpu_devices) before a user's module can
    start JAX's backend (registering an env runs a few resets): by --devices, by the run that --resume
    continues, or by the rule for the members that --seeds, --sweep and --set max_group_size ask for.
    Bad or missing values are left to the full parse, which reports them; a job of several processes
    splits nothing."""
    from xrl_jax.config import SCENARIOS, ConfigError, parse_overrides, parse_sweep, scenario
    from xrl_jax.train import cpu_devices, hosts
    from xrl_jax.train.kinds import KINDS

    early = argparse.ArgumentParser(add_help=False)
    for option in ("--env", "--seeds", "--devices", "--resume", "--coordinator", "--num-processes"):
        early.add_argument(option)
    early.add_argument("--sweep", action="append", default=[])
    early.add_argument("--set", action="append", default=[])
    try:
        known, _ = early.parse_known_args(argv)
        if known.coordinator or known.num_processes or hosts.wanted():
            return
        if known.devices:
            cpu_devices.split_cpu_host(int(known.devices))
        elif known.resume:
            stored = json.loads((Path(known.resume) / "config.json").read_text())["config"]["num_devices"]
            if stored:
                cpu_devices.split_cpu_host(int(stored))
        else:
            points = math.prod(len(values) for _, values in parse_sweep(known.sweep))
            members = int(known.seeds or 1) * points
            group = int(parse_overrides(known.set).get("max_group_size", 0))
            members = min(members, group) if group > 0 else members
            per_core = KINDS[scenario(known.env).kind].cpu_devices_per_core if known.env in SCENARIOS else 1
            count = cpu_devices.devices_for_members(members, cpu_devices.cpu_cores(), per_core)
            cpu_devices.split_cpu_host(count)
    except (ConfigError, OSError, ValueError, KeyError, TypeError, SystemExit):
        return


def _request(args):
    from xrl_jax.train.start import RunRequest

    return RunRequest(
        env=args.env,
        algo=args.algo,
        seeds=args.seeds,
        steps=args.steps,
        preset=args.preset,
        sets=args.set,
        sweep=args.sweep,
        devices=args.devices,
        out=args.out,
        resume=args.resume,
        baseline=args.baseline,
        coordinator=args.coordinator,
        num_processes=args.num_processes,
        process_id=args.process_id,
        coordinator_timeout=args.coordinator_timeout,
        trackers=tuple(dict.fromkeys(args.log)),
    )


def _main(args, argv, stop) -> int:
    from xrl_jax.runs.folder import RunFolderError
    from xrl_jax.train import ConfigError, DiskFullError, hosts
    from xrl_jax.train.start import join_job, prepare_run

    request = _request(args)
    try:
        # A job whose other processes never join ends from JAX's waiting thread, in one line.
        join_job(request, on_stall=lambda message: hosts.leave_at_once(fail(PROG, message)))
        prepared = prepare_run(request, ROOT / "results")
    except (ConfigError, RunFolderError, hosts.CoordinatorError) as err:
        return fail(PROG, err)
    except DiskFullError as err:
        return fail(PROG, err, EXIT_FAILED)
    for note in prepared.notes:
        print(f"run.py: {note}", file=sys.stderr)
    if prepared.resume:
        stop.keep(f"the checkpoints in {prepared.out} are kept")
    return _train(args, argv, prepared, stop)


def _train(args, argv, prepared, stop) -> int:
    """Train the prepared run (a new run's config.json is written by the trainer, under the folder's
    lock); every failure ends in one line and a status."""
    from xrl_jax.checkpoint import NoGoodCheckpointError
    from xrl_jax.interrupts import RunInterrupted, exit_status
    from xrl_jax.runs import format_curve, format_table
    from xrl_jax.runs.folder import RunFolderError
    from xrl_jax.runs.trackers import TrackerMirror
    from xrl_jax.train import (
        ConfigError,
        DiskFullError,
        DivergenceError,
        FolderWriteError,
        MemoryPlanError,
        hosts,
    )
    from xrl_jax.train.start import LostProcessError, enable_compilation_cache, train_prepared

    enable_compilation_cache()
    cfg, out = prepared.cfg, prepared.out
    primary = hosts.is_primary()  # process 0 talks for the job; the others train quietly
    quiet = args.quiet or not primary
    log = (lambda *a, **k: None) if quiet else (lambda msg: print(msg, file=sys.stderr))
    warn = lambda msg: print(msg, file=sys.stderr)
    command = [str(Path(__file__)), *(sys.argv[1:] if argv is None else argv)]  # into config.json
    imports = "".join(f" --import {target}" for target in args.imports)
    logs = "".join(f" --log {name}" for name in prepared.trackers)
    resume_command = f"python experiments/run.py --resume {out}{imports}{logs}"
    stop.resume_hint = resume_command  # from now on the folder can be resumed
    points = f" x {cfg.num_points} sweep points" if cfg.num_points > 1 else ""
    log(
        f"run.py: {cfg.env}/{cfg.algo} preset {cfg.preset}, "
        f"{cfg.num_seeds} seed(s){points} x {cfg.total_steps} steps -> {out}"
    )
    # The trackers of --log mirror every member's records: process 0 sends them, as they are written.
    mirror = TrackerMirror(out, cfg, prepared.trackers, warn) if prepared.trackers and primary else None
    try:
        summary = train_prepared(
            prepared,
            progress=not quiet,
            log=log,
            stop=stop,
            command=command,
            progress_fns=() if mirror is None else (mirror,),
        )
    except (MemoryPlanError, ConfigError, RunFolderError) as err:
        return fail(PROG, err)
    except DivergenceError as err:
        print(f"run.py: diverged: {err}", file=sys.stderr)
        return EXIT_DIVERGED
    except (DiskFullError, FolderWriteError, NoGoodCheckpointError) as err:
        return fail(PROG, err, EXIT_FAILED)
    except LostProcessError as err:  # JAX's exit handlers would wait for the lost process, then abort
        hosts.leave_at_once(fail(PROG, err, EXIT_FAILED))
    except RunInterrupted as err:
        print(f"\nrun.py: {err}; continue with: {resume_command}", file=sys.stderr)
        return exit_status(err.signum)
    finally:
        if mirror is not None:  # what the trackers received is then on their disk
            mirror.close()
    if summary is None:
        print(f"run.py: stopped early; continue with: {resume_command}", file=sys.stderr)
        return EXIT_FAILED
    if not primary:
        return 0
    print(format_curve(summary))
    print()
    print(format_table(summary))
    print(f"results: {out}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    status = main()
    from xrl_jax.train.cpu_devices import end_process

    end_process(status)  # a split CPU host ends without its teardown
