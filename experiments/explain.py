"""Draw a trained policy's explanations over one evaluation episode: ``python experiments/explain.py``.

    python experiments/explain.py --run RESULTS_DIR [--seed i] [--episode j] [--step k] [--slot s]
        [--format png|gif|mp4 | --out FILE]
    python experiments/explain.py --stats RESULTS_DIR [--out DIR]

The agent of seed ``i`` is restored from the run's newest checkpoint and drives evaluation track
``j`` (the fixed tracks of the run's evaluations) in its evaluation mode; the episode is one
compiled ``lax.scan``. The format decides what is written: ``png`` the frame of step ``k``, ``gif`` /
``mp4`` the whole episode, by default into the run's folder (``RESULTS_DIR/explain/seed<i>_episode<j>
_step<k>.png``, ``.../seed<i>_episode<j>.gif``), or into ``--out FILE`` (its suffix the format). The
per-step attributions (every object's weight and world position) go to JSON lines next to it. See
``xrl_jax/explain/figures.py`` for how to read a figure.

Intersection runs replay evaluation episode ``j`` (8 vehicles, the evaluation's traffic), every
car driven by the agent; the figure follows vehicle slot ``s`` (default: the first slot holding a
car at step 0) and shows that car's explanation: weight index 0 is the neutral (state-only)
component, drawn at the ego car, index k >= 1 the vehicle in row k-1 of its observation. A slot is
refilled by a new car after its car finished or crashed; the frames follow the slot (the title
names the car and marks a new one) and show the top view without glyphs while the slot is empty.

``--stats`` explains every seed's whole evaluation instead (the racing runs: every held-out track;
the Intersection: every evaluation episode, every car) and writes what the X agents attend to: where
the weight goes in the ego frame, by object kind, distance and time to contact, how many objects
carry 90 % of it (by speed), how much it moves from step to step and how alike the seeds are on the
same observations (``xrl_jax/explain/run_statistics.py``; docs/results.md reads them).

Runs on a user's env (``--import`` the module that registers it) replay evaluation episode ``j`` from
its fixed reset and draw one PNG: the objects at step ``k`` by weight, and every slot's weight over
the episode (docs/ecosystem.md).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import (
    IMPORT_HELP,
    OneLineParser,
    fail,
    fraction,
    import_user_modules,
    non_negative_int,
    positive_int,
)

FORMATS = (".png", ".gif", ".mp4")
DELETION_EPISODES = 20  # --stats: evaluation episodes of the deletion curves' returns
PROG = "explain.py"


EPILOG = """\
reading the figure:
  each object with mixture weight >= --threshold carries a glyph whose area is proportional to
  its weight; the glyph is that object's own action distribution (discrete: 3x4 probability
  matrix, columns steering, rows throttle / coast / both / brake; continuous: probability mass
  over steering (x) x throttle-minus-brake (y)). The inset (top left) is the combined policy, the
  weighted sum of the glyphs. SAC / DSAC baselines have no objects and show only the inset.

attributions (JSON lines, one per step): step, ego pose, action, control, reward and per object
  index, weight, world x, y and its type (cone colour / trajectory index / vehicle row / neutral).

--stats RESULTS_DIR: every seed's whole evaluation explained (racing: every held-out track; the
  Intersection: every episode and car). stats.json and stats.png: where the weight goes (ego-frame
  map, object kind, distance, time to contact), how many objects carry 90 % of it (by speed), its
  step-to-step change, how alike the seeds are, the last 2 s before an early end; deletion.png: the
  policy's change and the evaluation when the top-ranked objects are removed (X agents by weight,
  baselines by occlusion and gradient x input) against random removal (docs/results.md).

intersection: --slot picks the followed vehicle slot (default: first occupied at step 0); weight
  index 0 is the neutral (state-only) component at the ego car, index k the vehicle in observation
  row k-1 (its slot and car number are in the attributions). Rows also carry slot, car (spawn
  number; a slot is refilled by a new car after its car ended) and alive; --all-slots writes one
  row per occupied slot and step instead.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=PROG,
        description="Render a trained agent's evaluation episode with its per-object explanations.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--run", metavar="RESULTS_DIR", help="results folder of experiments/run.py")
    what.add_argument(
        "--stats",
        metavar="RESULTS_DIR",
        help="statistics of the explanations over every seed's whole evaluation instead of one "
        "episode's figure: RESULTS_DIR/explain/stats/stats.json and stats.png (or into --out DIR)",
    )
    parser.add_argument(
        "--import", dest="imports", metavar="MODULE", action="append", default=[], help=IMPORT_HELP
    )
    parser.add_argument("--seed", type=non_negative_int, default=0, help="which seed of the run (default 0)")
    parser.add_argument(
        "--point", type=non_negative_int, default=0, help="which point of a sweep run (default 0)"
    )
    parser.add_argument(
        "--episode", type=non_negative_int, default=0, help="evaluation track index (default 0)"
    )
    parser.add_argument("--step", type=non_negative_int, default=0, help="step drawn into a .png (default 0)")
    output = parser.add_mutually_exclusive_group()
    output.add_argument(
        "--format",
        choices=[suffix[1:] for suffix in FORMATS],
        default=None,
        help="png (one step), gif or mp4 (the episode), written into RESULTS_DIR/explain/ (default png)",
    )
    output.add_argument(
        "--out", metavar="FILE", default=None, help="write here instead: .png (one step), .gif or .mp4"
    )
    parser.add_argument(
        "--attributions",
        default=None,
        metavar="FILE",
        help="JSON-lines attributions (default: <figure without suffix>.attributions.jsonl)",
    )
    parser.add_argument("--key", type=non_negative_int, default=0, help="PRNG key of the episode (default 0)")
    parser.add_argument(
        "--deletion-episodes",
        type=non_negative_int,
        default=DELETION_EPISODES,
        help="--stats: evaluation episodes on which the deletion curves' returns are measured "
        "(default 20; 0: no deletion curves)",
    )
    parser.add_argument(
        "--threshold",
        type=fraction,
        default=0.05,
        help="objects lighter than this are left unmarked (default 0.05)",
    )
    parser.add_argument(
        "--max-steps",
        type=positive_int,
        default=None,
        help="stop the episode after this many steps (default: the env's limit)",
    )
    parser.add_argument(
        "--width", type=positive_int, default=1280, help="frame width in pixels (default 1280)"
    )
    parser.add_argument(
        "--height", type=positive_int, default=720, help="frame height in pixels (default 720)"
    )
    parser.add_argument("--fps", type=positive_int, default=10, help="video frames per second (default 10)")
    parser.add_argument(
        "--mirrored", action="store_true", help="the original's mirrored view (as in the paper)"
    )
    parser.add_argument(
        "--slot",
        type=non_negative_int,
        default=None,
        help="intersection: the vehicle slot followed (default: first occupied at step 0)",
    )
    parser.add_argument(
        "--all-slots",
        action="store_true",
        help="intersection: attributions of every occupied slot (default: the followed slot only)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    problem = import_user_modules(argv)  # a run on a user's env needs the module that registers it
    if problem:
        return fail(PROG, problem)
    args = build_parser().parse_args(argv)
    if args.stats:
        return statistics(args)
    if args.deletion_episodes != DELETION_EPISODES:
        return fail(PROG, "--deletion-episodes is an option of --stats, not of one episode's figure")
    out = Path(args.out) if args.out else default_out(args)
    suffix = out.suffix.lower()
    if suffix not in FORMATS:
        return fail(
            PROG,
            f"unsupported output format {out.suffix or '(none)'!r} for --out {out}; use .png, .gif or .mp4",
        )
    if suffix == ".mp4":
        import shutil

        if shutil.which("ffmpeg") is None:
            return fail(PROG, "writing .mp4 needs the ffmpeg program on PATH; install it or use .gif")
    if args.out and not out.parent.exists():
        return fail(PROG, f"the folder of --out {out} does not exist")
    if args.width < 16 or args.height < 16:
        return fail(PROG, f"frame size must be at least 16x16 pixels, got {args.width}x{args.height}")
    attributions = (
        Path(args.attributions) if args.attributions else out.with_name(out.stem + ".attributions.jsonl")
    )
    from xrl_jax.explain.run_figures import ExplainError, FigureRequest, explain_run
    from xrl_jax.runs.folder import RunFolderError, run_paths

    fields = ("seed", "point", "episode", "step", "key", "threshold", "max_steps", "width", "height", "fps",
              "mirrored", "slot", "all_slots")  # fmt: skip
    request = FigureRequest(
        Path(args.run), out, attributions, **{name: getattr(args, name) for name in fields}
    )
    # The run's explain/ folder, made only in a run folder (else explain_run says what is wrong) and
    # taken away again when nothing was drawn into it.
    made = not args.out and run_paths(request.run)["config"].is_file() and not out.parent.exists()
    if made:
        out.parent.mkdir()
    try:
        written = explain_run(request, note=lambda message: print(f"{PROG}: {message}", file=sys.stderr))
    except (ExplainError, RunFolderError) as err:
        if made and not any(out.parent.iterdir()):
            out.parent.rmdir()
        return fail(PROG, err)
    print(written)
    return 0


# What --stats takes besides the run: the sweep point, the policy's key and where to write.
EPISODE_OPTIONS = ("seed", "episode", "step", "format", "attributions", "threshold", "max_steps", "width",
                   "height", "fps", "mirrored", "slot", "all_slots")  # fmt: skip


def statistics(args: argparse.Namespace) -> int:
    """``--stats RESULTS_DIR``: every seed's evaluation explained; the summary and its figure."""
    defaults = build_parser().parse_args(["--stats", args.stats])
    given = [name for name in EPISODE_OPTIONS if getattr(args, name) != getattr(defaults, name)]
    if given:
        options = ", ".join("--" + name.replace("_", "-") for name in given)
        return fail(
            PROG, f"{options}: options of one episode's figure, not of --stats (every seed, every episode)"
        )
    from xrl_jax.explain.run_statistics import write_statistics
    from xrl_jax.runs.folder import RunFolderError, run_paths

    run = Path(args.stats)
    out = Path(args.out) if args.out else run_paths(run)["explain_stats"]
    if args.out and out.suffix:
        return fail(PROG, f"--out {out} with --stats is a folder (stats.json and stats.png go into it)")
    try:
        written = write_statistics(
            run, out, args.point, args.key, args.deletion_episodes,
            note=lambda message: print(f"{PROG}: {message}", file=sys.stderr),
        )  # fmt: skip
    except (ValueError, RunFolderError) as err:
        return fail(PROG, err)
    except KeyboardInterrupt:  # Ctrl-C in minutes of explaining: one line, not a traceback
        return fail(PROG, "interrupted; stats.json is written only once every seed is done", status=130)
    print(written)
    return 0


def default_out(args: argparse.Namespace) -> Path:
    """The figure's default file, in the run's folder: ``explain/seed<i>_episode<j>_step<k>.png`` (a
    sweep's point and an Intersection's slot named too when given; a video has no step)."""
    from xrl_jax.runs.folder import run_paths

    parts = [f"point{args.point}"] if args.point else []
    parts += [f"seed{args.seed}", f"episode{args.episode}"]
    parts += [f"slot{args.slot}"] if args.slot is not None else []
    fmt = args.format or "png"
    parts += [f"step{args.step}"] if fmt == "png" else []
    return run_paths(Path(args.run))["explain"] / f"{'_'.join(parts)}.{fmt}"


if __name__ == "__main__":
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    sys.exit(main())
