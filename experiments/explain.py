"""Draw a trained policy's explanations over one evaluation episode: ``python experiments/explain.py``.

    python experiments/explain.py --run RESULTS_DIR [--seed i] [--episode j] [--step k] [--slot s] --out FILE

The agent of seed ``i`` is restored from the run's newest checkpoint and drives evaluation track
``j`` (the fixed tracks of the run's evaluations) in its evaluation mode; the episode is one
compiled ``lax.scan``. ``--out`` decides what is written: ``.png`` the frame of step ``k``,
``.gif`` / ``.mp4`` the whole episode. The per-step attributions (every object's weight and world
position) go to JSON lines next to it. See ``xrl_jax/explain/figures.py`` for how to read a figure.

Intersection runs replay evaluation episode ``j`` (8 vehicles, the evaluation's traffic), every
car driven by the agent; the figure follows vehicle slot ``s`` (default: the first slot holding a
car at step 0) and shows that car's explanation: weight index 0 is the neutral (state-only)
component, drawn at the ego car, index k >= 1 the vehicle in row k-1 of its observation. A slot is
refilled by a new car after its car finished or crashed; the frames follow the slot (the title
names the car and marks a new one) and show the top view without glyphs while the slot is empty.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cli_args import OneLineParser, fraction, non_negative_int, positive_int

FORMATS = (".png", ".gif", ".mp4")
EPISODE_ENVS = ("country_road", "tracking")  # single-agent scenarios with fixed evaluation tracks
MULTI_AGENT_ENVS = ("intersection",)  # evaluation episodes with fixed env keys, one slot followed
NUM_SLOTS = 8  # envs.intersection.MAX_AGENTS


def _stored_env(run: Path) -> str | None:
    """The scenario of a results folder, or None when its config cannot be read (reported later)."""
    from xrl_jax.runs.folder import read_run_env

    return read_run_env(run)


EPILOG = """\
reading the figure:
  each object with mixture weight >= --threshold carries a glyph whose area is proportional to
  its weight; the glyph is that object's own action distribution (discrete: 3x4 probability
  matrix, columns steering, rows throttle / coast / both / brake; continuous: probability mass
  over steering (x) x throttle-minus-brake (y)). The inset (top left) is the combined policy, the
  weighted sum of the glyphs. SAC / DSAC baselines have no objects and show only the inset.

attributions (JSON lines, one per step): step, ego pose, action, control, reward and per object
  index, weight, world x, y and its type (cone colour / trajectory index / vehicle row / neutral).

intersection: --slot picks the followed vehicle slot (default: first occupied at step 0); weight
  index 0 is the neutral (state-only) component at the ego car, index k the vehicle in observation
  row k-1 (its slot and car number are in the attributions). Rows also carry slot, car (spawn
  number; a slot is refilled by a new car after its car ended) and alive; --all-slots writes one
  row per occupied slot and step instead.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="explain.py",
        description="Render a trained agent's evaluation episode with its per-object explanations.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--run", required=True, metavar="RESULTS_DIR", help="results folder of experiments/run.py"
    )
    parser.add_argument("--seed", type=non_negative_int, default=0, help="which seed of the run (default 0)")
    parser.add_argument(
        "--point", type=non_negative_int, default=0, help="which point of a sweep run (default 0)"
    )
    parser.add_argument(
        "--episode", type=non_negative_int, default=0, help="evaluation track index (default 0)"
    )
    parser.add_argument("--step", type=non_negative_int, default=0, help="step drawn into a .png (default 0)")
    parser.add_argument("--out", required=True, metavar="FILE", help="output: .png (one step), .gif or .mp4")
    parser.add_argument(
        "--attributions",
        default=None,
        metavar="FILE",
        help="JSON-lines attributions (default: <out without suffix>.attributions.jsonl)",
    )
    parser.add_argument("--key", type=non_negative_int, default=0, help="PRNG key of the episode (default 0)")
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


def fail(message: str) -> int:
    print(f"explain.py: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    suffix = out.suffix.lower()
    if suffix not in FORMATS:
        return fail(
            f"unsupported output format {out.suffix or '(none)'!r} for --out {out}; use .png, .gif or .mp4"
        )
    if suffix == ".mp4":
        import shutil

        if shutil.which("ffmpeg") is None:
            return fail("writing .mp4 needs the ffmpeg program on PATH; install it or use .gif")
    if not out.parent.exists():
        return fail(f"the folder of --out {out} does not exist")
    if args.width < 16 or args.height < 16:
        return fail(f"frame size must be at least 16x16 pixels, got {args.width}x{args.height}")
    attributions = (
        Path(args.attributions) if args.attributions else out.with_name(out.stem + ".attributions.jsonl")
    )

    import jax

    from xrl_jax.explain import make_episode_rollout, single_track_params
    from xrl_jax.explain.figures import EpisodeFigures, write_attributions
    from xrl_jax.runs.folder import RunFolderError
    from xrl_jax.train import load_trained_agent

    env = _stored_env(Path(args.run))
    if env is not None and env not in EPISODE_ENVS + MULTI_AGENT_ENVS:
        return fail(
            f"episodes of {env} runs are not supported (only {', '.join(EPISODE_ENVS + MULTI_AGENT_ENVS)})"
        )
    multi_agent = env in MULTI_AGENT_ENVS
    if not multi_agent and (args.slot is not None or args.all_slots):
        return fail("--slot and --all-slots are for intersection runs only")
    if multi_agent and args.slot is not None and args.slot >= NUM_SLOTS:
        return fail(f"--slot {args.slot} out of range: the intersection has slots 0..{NUM_SLOTS - 1}")
    try:
        cfg, trainer, agent_state = load_trained_agent(args.run, args.seed, args.point)
    except RunFolderError as err:
        return fail(str(err))
    if args.episode >= cfg.eval_episodes:
        what = "episodes" if multi_agent else "on tracks"
        return fail(
            f"episode {args.episode} out of range: the run evaluates {what} 0..{cfg.eval_episodes - 1}"
        )
    if not trainer.agent.config.is_mixture:
        print(
            f"explain.py: {cfg.algo} is a baseline without per-object explanations; "
            "the figure shows only its action distribution",
            file=sys.stderr,
        )
    if multi_agent:
        return explain_intersection(args, out, suffix, attributions, cfg, trainer, agent_state)
    params = single_track_params(trainer.eval_params, args.episode)
    max_steps = int(trainer.eval_params.max_steps) + 1
    if args.max_steps is not None:
        max_steps = min(max_steps, args.max_steps)
    agent = trainer.agent
    rollout = make_episode_rollout(trainer.env, agent, max_steps)
    record = jax.device_get(rollout(jax.random.PRNGKey(args.key), params, agent_state))
    figures = EpisodeFigures(
        cfg.env_name,
        trainer.env,
        params,
        record,
        neutral=bool(getattr(agent.config, "neutral_object", False)),
        mirrored=args.mirrored,
    )
    length = figures.length
    if suffix == ".png" and args.step >= length:
        return fail(f"--step {args.step} is beyond the episode ({length} steps: 0..{length - 1})")

    from envs.render import save_png, save_video

    title = f"{cfg.env} {cfg.algo} seed {args.seed} track {args.episode}"
    options = {"threshold": args.threshold, "width": args.width, "height": args.height}
    if suffix == ".png":
        frame, _ = figures.frame(args.step, title=f"{title} step {args.step}", **options)
        save_png(frame, out)
    else:
        save_video(figures.frames(title=title, **options), out, fps=args.fps)
    write_attributions(figures.attributions(), attributions)
    ended = (
        "terminated"
        if bool(record.terminated[length - 1])
        else "truncated"
        if bool(record.truncated[length - 1])
        else "stopped (--max-steps)"
    )
    print(
        f"{out} ({length} steps, episode {ended}, return {float(record.rewards[:length].sum()):.2f}); "
        f"attributions: {attributions}"
    )
    return 0


def explain_intersection(args, out: Path, suffix: str, attributions: Path, cfg, trainer, agent_state) -> int:
    """The Intersection branch of :func:`main`: replay evaluation episode ``--episode``, follow ``--slot``."""
    import jax
    import numpy as np

    from envs.render import save_png, save_video
    from xrl_jax.explain import make_multiagent_episode_rollout
    from xrl_jax.explain.figures import IntersectionEpisodeFigures, first_alive_slot, write_attributions

    params = trainer.eval_params
    max_steps = int(params.episode_steps)
    if args.max_steps is not None:
        max_steps = min(max_steps, args.max_steps)
    if suffix == ".png" and args.step >= max_steps:
        return fail(f"--step {args.step} is beyond the episode ({max_steps} steps: 0..{max_steps - 1})")
    agent = trainer.agent
    rollout = make_multiagent_episode_rollout(trainer.env, agent, max_steps)
    record = jax.device_get(rollout(args.episode, jax.random.PRNGKey(args.key), params, agent_state))
    slot = first_alive_slot(record) if args.slot is None else args.slot
    if slot is None:
        return fail(f"no car at step 0 of episode {args.episode}; pick one with --slot")
    figures = IntersectionEpisodeFigures(
        params,
        record,
        slot,
        neutral=bool(getattr(agent.config, "neutral_object", False)),
        mirrored=args.mirrored,
    )
    title = f"{cfg.env} {cfg.algo} seed {args.seed} episode {args.episode}"
    options = {"threshold": args.threshold, "width": args.width, "height": args.height}
    if suffix == ".png":
        frame, _ = figures.frame(args.step, title=figures.title(args.step, title), **options)
        save_png(frame, out)
    else:
        save_video(figures.frames(title=title, **options), out, fps=args.fps)
    write_attributions(figures.attributions(all_slots=args.all_slots), attributions)
    acted = np.asarray(record.acted)
    total = float(np.sum(np.where(acted, np.asarray(record.rewards), 0.0)))
    cars = len({int(c) for c in np.asarray(record.states.spawn_seq)[:, slot][acted[:, slot]]})
    print(
        f"{out} ({figures.length} steps, slot {slot}: {int(acted[:, slot].sum())} steps occupied by "
        f"{cars} car(s); return of all agents {total:.2f}); attributions: {attributions}"
    )
    return 0


if __name__ == "__main__":
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    sys.exit(main())
