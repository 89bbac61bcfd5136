"""Throughput benchmarks; every sub-command prints one JSON document to stdout.

    python experiments/bench.py env      [--scenarios tracking country_road] [--batches 1 64 1024 4096 8192]
    python experiments/bench.py intersection [--vehicles 1 2 4 8] [--batches 1 64 1024 4096] [--discrete]
    python experiments/bench.py matmul   [--size 2048]
    python experiments/bench.py update   [--env tracking] [--algos sac dsac xsac xdsac] [--widths 64 128 256]
                                         [--seeds 1 5 20] [--preset paper] [--batch-size B]
    python experiments/bench.py train    [--env tracking] [--algos xsac xdsac] [--seeds 1 5 20]
                                         [--widths 256 64] [--chunks 2] [--set KEY=VALUE ...]
                                         [--devices auto 1 2]  (members spread over that many devices;
                                         auto, the default: one CPU device per core the seeds fill)
    python experiments/bench.py compare  --against REV [--rounds 3] [train's options ...]
    python experiments/bench.py tracks   [--seeds 1 4 20] [--count 64]
    python experiments/bench.py profile  [--env tracking] [--algo xdsac] [--seeds 2] [--width 64]
                                         [--preset quick] [--depth 3] [--set KEY=VALUE ...]

Numbers are wall-clock rates after compilation (compile time is reported separately), measured with
``block_until_ready`` on the default JAX device (``train --devices``: on that many devices; on a
CPU-only machine the host is split into that many XLA devices). Tests never assert timings; these
scripts do.

``profile`` traces one updating chunk on one device with ``jax.profiler`` and sums its ops' time by
the model part that the optimised HLO names (forward and backward apart), with the slowest ops
(xrl_jax.benchmarks.profile; docs/performance.md, "Where an update's time goes").

``compare`` times ``train`` in this working tree (uncommitted changes included) and in REV (a commit,
checked out as a detached git worktree in a temporary folder, removed at the end), each run a fresh
process with the same options (train options left out: each side's own defaults), the order alternating
each round (AB, BA, AB, ...); it prints each configuration's rates per round, the per-round ratios
(working tree / REV), their median, min-max and an interval for the median (xrl_jax.benchmarks.compare).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, fail, fraction, positive_int

from xrl_jax.benchmarks import REJAX_PIECES  # jax-free: compare's parent imports no jax
from xrl_jax.config import PRESETS, ConfigError, parse_overrides

ROOT = Path(__file__).resolve().parents[1]  # the working tree that `compare` times against another commit
# What `bench.py env` drives with one random action per env (envs.registry's single-agent names).
RACING_SCENARIOS = ("tracking", "country_road", "tracking_discrete", "country_road_discrete")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="bench.py", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    env_parser = sub.add_parser("env", help="environment steps per second (random actions, auto-reset)")
    env_parser.add_argument(
        "--scenarios", nargs="+", default=["tracking", "country_road"], choices=RACING_SCENARIOS,
        help="racing scenarios (the Intersection: bench.py intersection)",
    )  # fmt: skip
    env_parser.add_argument("--batches", nargs="+", type=positive_int, default=[1, 64, 1024, 4096, 8192])
    env_parser.add_argument("--steps", type=positive_int, default=100, help="steps per timed call")
    env_parser.add_argument("--repeats", type=positive_int, default=3)
    ix_parser = sub.add_parser(
        "intersection", help="intersection env-steps/s and agent-steps/s (random actions, 8 slots)"
    )
    ix_parser.add_argument("--vehicles", nargs="+", type=positive_int, default=[1, 2, 4, 8])
    ix_parser.add_argument("--batches", nargs="+", type=positive_int, default=[1, 64, 1024, 4096])
    ix_parser.add_argument("--steps", type=positive_int, default=100, help="steps per timed call")
    ix_parser.add_argument("--repeats", type=positive_int, default=3)
    ix_parser.add_argument("--discrete", action="store_true", help="the Discrete(12) variant")
    mm_parser = sub.add_parser("matmul", help="float32 matmul GFLOP/s of the default device")
    mm_parser.add_argument("--size", type=positive_int, default=2048)
    up_parser = sub.add_parser(
        "update", help="agent updates/s per seed on real batches, packed beside dense, FLOPs per update"
    )
    up_parser.add_argument("--env", default="tracking", choices=["tracking", "country_road", "intersection"])
    up_parser.add_argument("--preset", default="paper", choices=PRESETS, help="the agents' preset")
    up_parser.add_argument("--batch-size", type=positive_int, default=None, help="default: the preset's")
    up_parser.add_argument(
        "--algos",
        nargs="+",
        default=["sac", "dsac", "xsac", "xdsac"],
        choices=["sac", "dsac", "xsac", "xdsac"],
    )
    up_parser.add_argument("--widths", nargs="+", type=positive_int, default=[64, 128, 256])
    up_parser.add_argument("--seeds", nargs="+", type=positive_int, default=[1, 5, 20])
    up_parser.add_argument("--repeats", type=positive_int, default=5)
    tr_parser = sub.add_parser(
        "train", help="end-to-end training env-steps/s (updates included), compile, memory"
    )
    add_train_arguments(tr_parser)
    cmp_parser = sub.add_parser(
        "compare", help="train's env-steps/s of the working tree over another commit's, runs in turn"
    )
    cmp_parser.add_argument("--against", required=True, metavar="REV", help="the commit to compare with")
    cmp_parser.add_argument("--rounds", type=positive_int, default=3, help="runs per side, order alternating")
    for action in add_train_arguments(cmp_parser):  # passed on as given: unset, each side's own default
        action.default = argparse.SUPPRESS
    pf_parser = sub.add_parser("profile", help="one chunk's op time by model part (jax.profiler)")
    pf_parser.add_argument("--env", default="tracking", choices=["tracking", "country_road", "intersection"])
    pf_parser.add_argument("--algo", default="xdsac", choices=["sac", "dsac", "xsac", "xdsac"])
    pf_parser.add_argument("--seeds", type=positive_int, default=2, help="members on the one device")
    pf_parser.add_argument("--width", type=positive_int, default=None, help="actor/critic width")
    pf_parser.add_argument("--preset", default="quick", choices=PRESETS)
    pf_parser.add_argument("--depth", type=positive_int, default=3, help="module path components per part")
    pf_parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="extra config overrides")
    rj_parser = sub.add_parser(
        "rejax", help="our PPO beside rejax's on Tracking at an equal budget: returns, env-steps/s"
    )
    rj_parser.add_argument("--seeds", type=positive_int, default=8, help="members of each side")
    rj_parser.add_argument("--steps", type=positive_int, default=1_048_576, help="env steps per seed")
    rj_parser.add_argument("--envs", type=positive_int, default=16)
    rj_parser.add_argument("--rollout-steps", type=positive_int, default=128)
    rj_parser.add_argument("--epochs", type=positive_int, default=4)
    rj_parser.add_argument("--minibatches", type=positive_int, default=8)
    rj_parser.add_argument("--width", type=positive_int, default=64)
    rj_parser.add_argument("--depth", type=positive_int, default=2)
    rj_parser.add_argument(
        "--truncation", default="bootstrap", choices=["bootstrap", "terminal"],
        help="how our side values the 60 s time limit: bootstrap (ours) or terminal (rejax's reading)",
    )  # fmt: skip
    rj_parser.add_argument(
        "--rejax-with", default=(), type=rejax_pieces, metavar="PIECE[,PIECE...]",
        help="rejax's side given pieces of ours (default: none, its own PPO): its Gaussian sampled before "
        "a tanh the env applies (squash); log sigma a head of the features (state_std); our flat "
        "encoding of the observation (observation); the gradient's global norm clipped, not each "
        "element (global_clip)",
    )  # fmt: skip
    rj_parser.add_argument(
        "--ent-coef", type=fraction, default=None,
        help="both sides' entropy bonus (default: the quick preset's 0.01); 0 removes the term whose "
        "form differs (rejax: the Gaussian's before the squash; ours: the squashed policy's)",
    )  # fmt: skip
    rj_parser.add_argument(
        "--value-clip", action="store_true",
        help="our side clips the value's move per rollout at the clip range, as rejax's value loss does",
    )  # fmt: skip
    tk_parser = sub.add_parser("tracks", help="fresh-track refill cost per track, FLOPs per track")
    tk_parser.add_argument("--seeds", nargs="+", type=positive_int, default=[1, 4, 20])
    tk_parser.add_argument(
        "--count", type=positive_int, default=64, help="tracks per seed and refill (half a feed)"
    )
    tk_parser.add_argument("--repeats", type=positive_int, default=3)
    return parser


def add_train_arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """``train``'s options, which ``compare`` passes on to both sides."""
    return [
        parser.add_argument(
            "--env", default="tracking", choices=["tracking", "country_road", "intersection"]
        ),
        parser.add_argument(
            "--algos", nargs="+", default=["xsac", "xdsac"], choices=["sac", "dsac", "xsac", "xdsac"]
        ),
        parser.add_argument("--seeds", nargs="+", type=positive_int, default=[1, 5, 20]),
        parser.add_argument(
            "--widths",
            nargs="+",
            type=positive_int,
            default=[256, 64],
            help="actor/critic widths (paper: 256)",
        ),
        parser.add_argument("--chunks", type=positive_int, default=2, help="timed chunks after the first"),
        parser.add_argument(
            "--devices",
            nargs="+",
            type=device_count,
            default=["auto"],
            help="device counts to spread the seeds over; auto (default): on a CPU, one device per core "
            "that the seeds fill evenly, as a run splits its host (xrl_jax.train.cpu_devices); else 1",
        ),
        parser.add_argument("--preset", default="paper", choices=PRESETS),
        parser.add_argument(
            "--set", nargs="*", default=[], metavar="KEY=VALUE", help="extra config overrides"
        ),
    ]


def train_options(args: argparse.Namespace) -> list[str]:
    """The ``train`` options a ``compare`` request gave, as command-line words for both sides."""
    from xrl_jax.benchmarks.compare import render_options

    given = add_train_arguments(argparse.ArgumentParser())
    return render_options(
        (action.option_strings[0], getattr(args, action.dest))
        for action in given
        if hasattr(args, action.dest)
    )


def stop_as_if_interrupted(signum, frame):
    raise KeyboardInterrupt


def compare(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``bench.py compare``: refuses options the working tree's ``train`` would, then times both sides
    (xrl_jax.benchmarks.compare) and prints the report."""
    from xrl_jax.benchmarks.compare import CompareError
    from xrl_jax.benchmarks.compare import compare as compare_trees

    forwarded = train_options(args)
    check_arguments(parser, parser.parse_args(["train", *forwarded]))
    progress = lambda line: print(f"bench.py compare: {line}", file=sys.stderr, flush=True)
    before = signal.signal(signal.SIGTERM, stop_as_if_interrupted)  # a kill, too, removes the checkout
    try:
        report = compare_trees(ROOT, args.against, args.rounds, forwarded, progress)
    except CompareError as err:
        return fail("bench.py", err, err.status)
    except KeyboardInterrupt:
        return fail("bench.py", "stopped (the checkout of --against is removed)", 130)
    finally:
        signal.signal(signal.SIGTERM, before)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


def device_count(text: str) -> int | str:
    """``--devices``: a positive integer, or ``auto``."""
    return "auto" if text == "auto" else positive_int(text)


def devices_for(seeds: int, devices: int | str) -> int:
    """The devices ``seeds`` members spread over on this host (``auto``: the run's rule on a CPU)."""
    if devices != "auto":
        return devices
    from xrl_jax.train import cpu_devices

    return cpu_devices.devices_for_members(seeds, cpu_devices.cpu_cores())


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse what the argument types cannot see, in one line, before anything is compiled."""
    if args.command == "intersection" and not all(n <= 8 for n in args.vehicles):
        parser.error("--vehicles must lie in 1..8")
    try:  # compare passes its --set on only when given
        parse_overrides(getattr(args, "set", []))
    except ConfigError as err:
        parser.error(str(err))
    if args.command == "rejax":
        import importlib.util

        rollout = args.envs * args.rollout_steps
        if args.steps % rollout or rollout % args.minibatches:
            parser.error(
                f"--steps must be a multiple of one rollout (--envs x --rollout-steps = {rollout}), "
                "which --minibatches must split"
            )
        if importlib.util.find_spec("rejax") is None:  # before our side trains for an hour
            parser.error("bench.py rejax needs rejax: pip install -e '.[gymnax-tests]'")
    if args.command != "train":
        return
    if any(seeds % devices_for(seeds, n) for seeds in args.seeds for n in args.devices):
        parser.error("every --seeds value must be a multiple of every --devices value")


def rejax_pieces(text: str) -> tuple[str, ...]:
    """``--rejax-with``'s comma-separated pieces of ours, each known and given once."""
    pieces = tuple(piece.strip() for piece in text.split(","))
    unknown = [piece for piece in pieces if piece not in REJAX_PIECES]
    if unknown or len(set(pieces)) < len(pieces):
        raise argparse.ArgumentTypeError(
            f"expected distinct pieces of {', '.join(REJAX_PIECES)}, got {text!r}"
        )
    return pieces


def rejax_changes(args: argparse.Namespace) -> dict[str, object]:
    """The settings ``bench.py rejax``'s ablation options change (ours alone, or both sides)."""
    changes: dict[str, object] = {"truncation": args.truncation}
    if args.ent_coef is not None:
        changes["ent_coef"] = args.ent_coef
    if args.value_clip:
        from xrl_jax.config import resolve_config

        # rejax clips the value by its ratio's range: the comparison's, which its preset sets.
        changes["value_clip_eps"] = resolve_config("tracking", "ppo", "quick").agent.clip_eps
    return changes


def results(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """The sub-command's measurements (``main`` split the host first, where it does)."""
    # Imported once the host is split: importing the envs may start the backend.
    import jax

    from xrl_jax import benchmarks as B
    from xrl_jax.benchmarks.occupancy import rollout_observations

    if args.command == "env":
        return [
            B.bench_env(scenario, batch, args.steps, args.repeats)
            for scenario in args.scenarios
            for batch in args.batches
        ]
    if args.command == "intersection":
        return [
            B.bench_intersection(n, batch, args.steps, args.repeats, args.discrete)
            for n in args.vehicles
            for batch in args.batches
        ]
    if args.command == "train":
        on_cpu = jax.default_backend() == "cpu"  # elsewhere auto is one accelerator
        counts = {
            (s, n): devices_for(s, n) if on_cpu or n != "auto" else 1
            for s in args.seeds
            for n in args.devices
        }
        if max(counts.values()) > len(jax.devices()):
            parser.error(f"--devices {max(counts.values())}: only {len(jax.devices())} device(s) here")
        return [
            B.bench_train(args.env, algo, seeds, width, args.chunks, args.preset, args.set, counts[seeds, n])
            for algo in args.algos
            for width in args.widths
            for seeds in args.seeds
            for n in args.devices
        ]
    if args.command == "update":
        observations = rollout_observations(args.env)["observations"]
        return [
            B.bench_update(
                args.env, algo, width, seeds, max(2, 40 * 64 // (width * seeds)),  # each call ~1 s or more
                args.repeats, observations, args.preset, args.batch_size,
            )
            for width in args.widths
            for seeds in args.seeds
            for algo in args.algos
        ]  # fmt: skip
    if args.command == "tracks":
        return [B.bench_tracks(seeds, args.count, args.repeats) for seeds in args.seeds]
    if args.command == "matmul":
        return B.bench_matmul(args.size)
    if args.command == "rejax":
        return B.ppo_against_rejax(
            args.seeds, args.steps, args.envs, args.rollout_steps, args.epochs, args.minibatches,
            args.width, args.depth, rejax_with=args.rejax_with, changes=rejax_changes(args),
        )  # fmt: skip
    if args.command == "profile":
        return B.bench_profile(
            args.env, args.algo, args.seeds, args.width, args.preset, args.set, depth=args.depth
        )
    raise AssertionError(f"bench.py: no measurement for {args.command!r}")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    if args.command == "compare":  # before jax: the runs are other processes
        return compare(parser, args)
    if args.command == "train":
        # A CPU host becomes that many XLA devices (when the backend starts, i.e. below).
        from xrl_jax.train import cpu_devices

        cpu_devices.split_cpu_host(max(devices_for(seeds, n) for seeds in args.seeds for n in args.devices))
    from xrl_jax import benchmarks as B

    report: dict = {"machine": B.machine_info(), "command": args.command}
    try:  # a --set naming no setting, or a value it cannot take: one line, before anything compiles
        report["results"] = results(parser, args)
    except ConfigError as err:
        return fail("bench.py", err)
    json.dump(report, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    status = main()
    from xrl_jax.train.cpu_devices import end_process

    end_process(status)  # a split CPU host ends without its teardown
