"""What the host loop writes after a chunk, and what it checks: one metrics line per member, one
evaluation line per member when it evaluates, the records a progress callback receives, the rows a
resumed member's files must already hold, and the one-line divergence verdict."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.evaluation import summarize_episodes
from xrl_jax.runs.folder import (
    append_lines,
    encode_metric,
    eval_file,
    member_fields,
    member_stem,
    metrics_file,
)
from xrl_jax.train.chunk import ChunkReport
from xrl_jax.train.restore import first_nonfinite_leaf


@dataclasses.dataclass(frozen=True)
class Progress:
    """What a progress callback of :func:`~xrl_jax.train.train` receives after every chunk (as
    Brax's ``progress_fn``): the records just written, ``(member, line)`` for every member of the
    running group, also those another process of the job writes."""

    step: int  # transitions per member at the end of the chunk
    group: int  # the member group (0-based)
    metrics: tuple[tuple[int, dict], ...]  # one metrics line per member
    evaluations: tuple[tuple[int, dict], ...] = ()  # one evaluation line per member, when it evaluated


class RecordWriter:
    """Appends the records of the members this process holds to their files in the folder, and hands
    every member's to the progress callbacks."""

    def __init__(self, cfg: TrainConfig, out: Path, progress_fns: Sequence[Callable[[Progress], None]] = ()):
        self.cfg, self.out, self.progress_fns = cfg, out, tuple(progress_fns)

    def files(self, member: int) -> tuple[Path, Path]:
        """Member ``member``'s metrics and evaluation files."""
        stem = member_stem(self.cfg, member)
        return metrics_file(self.out, stem), eval_file(self.out, stem)

    def metrics(self, step: int, members: list[int], own: list[int], report: ChunkReport) -> tuple:
        """Every member's metrics line; those of ``own`` (rows this process holds) written."""
        lines = metric_lines(self.cfg, step, members, range(len(members)), report)
        for row in own:
            append_lines(self.files(lines[row][0])[0], [lines[row][1]])
        return tuple(lines)

    def evaluations(self, step: int, members: list[int], own: list[int], episodes) -> tuple:
        """Every member's evaluation line (``episodes``: the evaluation's per-episode outputs, a
        leading member axis); those of ``own`` written."""
        lines = []
        for row, member in enumerate(members):
            per_episode = jax.tree.map(lambda x, r=row: np.asarray(x[r]), episodes)
            lines.append(
                (member, {"step": step, **member_fields(self.cfg, member), **summarize_episodes(per_episode)})
            )
        for row in own:
            append_lines(self.files(lines[row][0])[1], [lines[row][1]])
        return tuple(lines)

    def tell(self, progress: Progress) -> None:
        for progress_fn in self.progress_fns:
            progress_fn(progress)


def member_name(cfg: TrainConfig, member: int) -> str:
    """A member in words, for messages: ``seed 3``, or ``seed 3 at sweep point 1 (gamma=0.95)``."""
    point, seed = cfg.member_point_seed(member)
    if cfg.num_points == 1:
        return f"seed {seed}"
    values = ", ".join(f"{k}={v:g}" for k, v in cfg.sweep_points[point].items())
    return f"seed {seed} at sweep point {point} ({values})"


def metric_lines(
    cfg: TrainConfig, step: int, members: list[int], rows: Sequence[int], report: ChunkReport
) -> list[tuple[int, dict]]:
    """One metrics line per member (of ``rows``, the group's rows this process holds): ``null`` where
    an average has no data yet, non-finite values as the strings "nan"/"inf"/"-inf" (see
    :func:`xrl_jax.runs.folder.encode_metric`)."""
    lines = []
    for row in rows:
        line = {"step": step, **member_fields(cfg, members[row])}
        for name, values in report.metrics.items():
            present = report.has_data.get(name)
            line[name] = encode_metric(values[row]) if present is None or present[row] else None
        lines.append((members[row], line))
    return lines


_LEARNING_ADVICE = (
    "resuming would diverge again: start a new run with other settings, e.g. lower actor_lr and critic_lr"
)
_ENV_ADVICE = "the env produced them, not the learning: fix the env's step, then start a new run"
_ENV_OUTPUTS = {1: "reward", 2: "observation", 3: "reward and observation"}


def divergence_message(
    report: ChunkReport,
    seeds: list,
    chunk_end: int,
    loss_names: tuple[str, ...],
    agent_of_row,
    rows: Sequence[int] | None = None,
) -> tuple[str, str] | None:
    """None when every member of the chunk is healthy, else ``(line, advice)``: the line names the
    first member to go non-finite (``seeds[row]``: its name), the step and the quantity
    (``agent_of_row(row)`` gives that member's agent state), or the env's non-finite output where the
    env returned one first; the advice says what to do. Only ``rows`` (default: all) are read; when none
    of them diverged but ``report.unhealthy_members`` says that a member of another process did, the
    line says so."""
    health = report.health
    loss_step, env_step = np.asarray(health.first_nonfinite_step), np.asarray(health.first_nonfinite_env_step)
    rows = range(len(seeds)) if rows is None else rows
    bad_rows = [r for r in rows if loss_step[r] >= 0 or env_step[r] >= 0 or not health.agent_finite[r]]
    if not bad_rows:
        if int(np.asarray(report.unhealthy_members)) > 0:
            line = (
                f"a member held by another process diverged by step {chunk_end} (its process's log names it)"
            )
            return line, _LEARNING_ADVICE
        return None
    first_step = {
        r: min([int(s) for s in (loss_step[r], env_step[r]) if s >= 0] or [chunk_end]) for r in bad_rows
    }
    row = min(bad_rows, key=lambda r: (first_step[r], r))
    others = len(bad_rows) - 1
    also = f" ({others} other{'s' if others > 1 else ''} too)" if others else ""
    if env_step[row] >= 0 and env_step[row] == first_step[row]:
        what = _ENV_OUTPUTS[int(health.nonfinite_env_outputs[row])]
        return (
            f"{seeds[row]}: the env returned a non-finite {what} at step {first_step[row]}{also}",
            _ENV_ADVICE,
        )
    if loss_step[row] >= 0:
        what = f"{loss_names[int(health.first_nonfinite_loss[row])]} became non-finite"
    else:
        what = f"the agent's {first_nonfinite_leaf(agent_of_row(row))} became non-finite"
    return f"{seeds[row]} diverged at step {first_step[row]}{also}: {what}", _LEARNING_ADVICE


def expected_rows(cfg: TrainConfig, next_chunk: int) -> tuple[list[int], list[int]]:
    """The metric and evaluation steps a seed's files must hold when ``next_chunk`` chunks are done."""
    ends = [cfg.chunk_end_step(c) for c in range(next_chunk)]
    evals = [s for s in ends if cfg.evaluates_at(s)]
    return ends, evals
