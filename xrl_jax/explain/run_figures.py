"""A trained run's explanations over one evaluation episode (``experiments/explain.py``): the agent of
one seed restored from the run's newest good checkpoint, its episode rolled out on the device, and
the frames (PNG, GIF, MP4) and per-step attributions written.

Racing runs drive one of the run's fixed evaluation tracks; Intersection runs replay one of its
evaluation episodes (8 vehicles, the evaluation's traffic) with every car driven by the agent,
following one vehicle slot; runs on a user's env replay one of its evaluation episodes
(:mod:`xrl_jax.explain.set_figure`). It restores agents through :func:`xrl_jax.train.load_trained_agent`,
so it sits above the trainer; the figure modules need matplotlib.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from xrl_jax.config import ConfigError
from xrl_jax.explain.explanations import (
    make_episode_rollout,
    make_multiagent_episode_rollout,
    single_track_params,
)


class ExplainError(ValueError):
    """A figure that cannot be drawn as asked (an option out of range); the message is one line."""


@dataclass(frozen=True)
class FigureRequest:
    """What to draw: the run's ``seed`` (at sweep ``point``), evaluation ``episode``, the frame of
    ``step`` (PNG) or the whole episode (GIF, MP4) into ``out``, and the attributions' file."""

    run: Path
    out: Path
    attributions: Path
    seed: int = 0
    point: int = 0
    episode: int = 0
    step: int = 0
    key: int = 0
    threshold: float = 0.05
    max_steps: int | None = None
    width: int = 1280
    height: int = 720
    fps: int = 10
    mirrored: bool = False
    slot: int | None = None  # intersection: the vehicle slot followed (None: first occupied at step 0)
    all_slots: bool = False  # intersection: attributions of every occupied slot

    @property
    def is_video(self) -> bool:
        return self.out.suffix.lower() != ".png"


def explain_run(request: FigureRequest, note=print) -> str:
    """Draw ``request``'s figure and write its attributions; returns one line saying what was written.
    ``note`` takes a remark (a baseline has no per-object explanations). Raises
    :class:`ExplainError` or :class:`~xrl_jax.runs.folder.RunFolderError` (one line) for a request
    the run cannot answer."""
    from xrl_jax.runs.folder import read_run_env
    from xrl_jax.train import load_trained_agent
    from xrl_jax.train.kinds import scenario_kind

    env = read_run_env(request.run)  # None: no readable config, which the restore reports
    try:
        kind = None if env is None else scenario_kind(env)
    except ConfigError as err:  # a user's env that this process has not registered
        raise ExplainError(str(err)) from None
    figure = FIGURES[kind.figure if kind is not None else "track"]
    slots = kind.slots_explained if kind is not None else 0
    if figure.png_only and (
        request.is_video or request.slot is not None or request.all_slots or request.mirrored
    ):
        raise ExplainError(f"{env} is a user's env: its figure is one PNG (no video, --slot or --mirrored)")
    if not slots and (request.slot is not None or request.all_slots):
        raise ExplainError("--slot and --all-slots are for intersection runs only")
    if slots and request.slot is not None and request.slot >= slots:
        raise ExplainError(f"--slot {request.slot} out of range: the intersection has slots 0..{slots - 1}")
    cfg, trainer, agent_state = load_trained_agent(request.run, request.seed, request.point)
    if request.episode >= cfg.eval_episodes:
        raise ExplainError(
            f"episode {request.episode} out of range: the run evaluates {figure.episodes} "
            f"0..{cfg.eval_episodes - 1}"
        )
    if not trainer.agent.config.is_mixture:
        note(
            f"{cfg.algo} is a baseline without per-object explanations; "
            "the figure shows only its action distribution"
        )
    return figure.draw(request, cfg, trainer, agent_state)


def _check_step(request: FigureRequest, length: int) -> None:
    if not request.is_video and request.step >= length:
        raise ExplainError(f"--step {request.step} is beyond the episode ({length} steps: 0..{length - 1})")


def _write(request: FigureRequest, figures, title: str, step_title: str, attributions) -> None:
    """The frame of ``request.step`` or the whole episode, then the attributions (``attributions()``:
    the rows)."""
    from envs.render import save_png, save_video
    from xrl_jax.explain.figures import write_attributions

    options = {"threshold": request.threshold, "width": request.width, "height": request.height}
    if request.is_video:
        save_video(figures.frames(title=title, **options), request.out, fps=request.fps)
    else:
        frame, _ = figures.frame(request.step, title=step_title, **options)
        save_png(frame, request.out)
    write_attributions(attributions(), request.attributions)


def _explain_track(request: FigureRequest, cfg, trainer, agent_state) -> str:
    """A racing run: drive evaluation track ``request.episode`` with the ego car explained."""
    from xrl_jax.explain.figures import EpisodeFigures

    params = single_track_params(trainer.eval_params, request.episode)
    max_steps = int(trainer.eval_params.max_steps) + 1
    if request.max_steps is not None:
        max_steps = min(max_steps, request.max_steps)
    agent = trainer.agent
    rollout = make_episode_rollout(trainer.env, agent, max_steps)
    record = jax.device_get(rollout(jax.random.PRNGKey(request.key), params, agent_state))
    figures = EpisodeFigures(
        cfg.env_name,
        trainer.env,
        params,
        record,
        neutral=bool(getattr(agent.config, "neutral_object", False)),
        mirrored=request.mirrored,
    )
    length = figures.length
    _check_step(request, length)
    title = f"{cfg.env} {cfg.algo} seed {request.seed} track {request.episode}"
    _write(request, figures, title, f"{title} step {request.step}", figures.attributions)
    if bool(record.terminated[length - 1]):
        ended = "terminated"
    elif bool(record.truncated[length - 1]):
        ended = "truncated"
    else:
        ended = "stopped (--max-steps)"
    total = float(record.rewards[:length].sum())
    return (
        f"{request.out} ({length} steps, episode {ended}, return {total:.2f}); "
        f"attributions: {request.attributions}"
    )


def _explain_intersection(request: FigureRequest, cfg, trainer, agent_state) -> str:
    """An Intersection run: replay evaluation episode ``request.episode`` and follow one slot."""
    from xrl_jax.explain.figures import IntersectionEpisodeFigures, first_alive_slot

    params = trainer.eval_params
    max_steps = int(params.episode_steps)
    if request.max_steps is not None:
        max_steps = min(max_steps, request.max_steps)
    _check_step(request, max_steps)
    agent = trainer.agent
    rollout = make_multiagent_episode_rollout(trainer.env, agent, max_steps)
    record = jax.device_get(rollout(request.episode, jax.random.PRNGKey(request.key), params, agent_state))
    slot = first_alive_slot(record) if request.slot is None else request.slot
    if slot is None:
        raise ExplainError(f"no car at step 0 of episode {request.episode}; pick one with --slot")
    figures = IntersectionEpisodeFigures(
        params,
        record,
        slot,
        neutral=bool(getattr(agent.config, "neutral_object", False)),
        mirrored=request.mirrored,
    )
    title = f"{cfg.env} {cfg.algo} seed {request.seed} episode {request.episode}"
    step_title = figures.title(request.step, title) if not request.is_video else title
    _write(request, figures, title, step_title, lambda: figures.attributions(all_slots=request.all_slots))
    acted = np.asarray(record.acted)
    total = float(np.sum(np.where(acted, np.asarray(record.rewards), 0.0)))
    cars = len({int(c) for c in np.asarray(record.states.spawn_seq)[:, slot][acted[:, slot]]})
    return (
        f"{request.out} ({figures.length} steps, slot {slot}: {int(acted[:, slot].sum())} steps occupied by "
        f"{cars} car(s); return of all agents {total:.2f}); attributions: {request.attributions}"
    )


def _explain_custom(request: FigureRequest, cfg, trainer, agent_state) -> str:
    """A user's env: replay evaluation episode ``request.episode`` (its fixed reset) and draw one step."""
    from envs.render import save_png
    from xrl_jax.explain.episodes import write_attributions
    from xrl_jax.explain.set_figure import draw_set_step, make_set_episode_rollout, set_attributions

    facts = cfg.scenario
    max_steps = (
        facts.max_episode_steps
        if request.max_steps is None
        else min(request.max_steps, facts.max_episode_steps)
    )
    rollout = make_set_episode_rollout(trainer.env, trainer.agent, facts.set_key, max_steps)
    key = jax.random.PRNGKey(request.key)
    record = jax.device_get(
        rollout(request.episode, cfg.eval_track_seed, key, trainer.eval_params, agent_state)
    )
    length = int(np.sum(record["valid"]))
    _check_step(request, length)
    title = f"{cfg.env} {cfg.algo} seed {request.seed} episode {request.episode} step {request.step}"
    save_png(
        draw_set_step(record, request.step, facts.object_xy, title, (request.width, request.height)),
        request.out,
    )
    write_attributions(set_attributions(record, request.threshold), request.attributions)
    total = float(np.sum(np.where(record["valid"], record["reward"], 0.0)))
    return f"{request.out} ({length} steps, return {total:.2f}); attributions: {request.attributions}"


@dataclass(frozen=True)
class RunFigure:
    """One explanation figure of a trained run: how it is drawn, what the run's evaluation episodes
    are called in a message, and whether it is one PNG only (no video, slot or mirror)."""

    draw: Callable[..., str]  # (request, cfg, trainer, agent_state) -> what was written
    episodes: str
    png_only: bool = False


# The figure each scenario kind names (xrl_jax.train.kinds: ScenarioKind.figure).
FIGURES = {
    "track": RunFigure(_explain_track, "on tracks"),  # the bird view of one car on an evaluation track
    "slots": RunFigure(_explain_intersection, "episodes"),  # the bird view following one agent slot
    "set": RunFigure(_explain_custom, "episodes", png_only=True),  # a user's env's objects by weight
}
