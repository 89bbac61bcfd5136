"""What the host loop writes after a chunk, and what it checks: one metrics line per member, the
rows a resumed member's files must already hold, and the one-line divergence verdict."""

from __future__ import annotations

import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.runs.folder import encode_metric, member_fields
from xrl_jax.train.chunk import ChunkReport
from xrl_jax.train.restore import first_nonfinite_leaf


def metric_lines(
    cfg: TrainConfig, step: int, members: list[int], rows: list[int], report: ChunkReport
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


def divergence_message(
    report: ChunkReport,
    seeds: list,
    chunk_end: int,
    loss_names: tuple[str, ...],
    agent_of_row,
    rows: list[int] | None = None,
) -> str | None:
    """None when every member of the chunk is healthy, else one line naming the first member to go
    non-finite (``seeds[row]``: its name), the step and the quantity (``agent_of_row(row)`` gives
    that member's agent state). Only ``rows`` (default: all) are read; when none of them diverged
    but ``report.unhealthy_members`` says that a member of another process did, the line says so."""
    health = report.health
    loss_step = np.asarray(health.first_nonfinite_step)
    rows = range(len(seeds)) if rows is None else rows
    bad_rows = [r for r in rows if loss_step[r] >= 0 or not health.agent_finite[r]]
    if not bad_rows:
        if int(np.asarray(report.unhealthy_members)) > 0:
            return (
                f"a member held by another process diverged by step {chunk_end} (its process's log names it)"
            )
        return None
    first_step = {r: int(loss_step[r]) if loss_step[r] >= 0 else chunk_end for r in bad_rows}
    row = min(bad_rows, key=lambda r: (first_step[r], r))
    if loss_step[row] >= 0:
        name = loss_names[int(health.first_nonfinite_loss[row])]
        what = f"{name} became non-finite"
    else:
        what = f"the agent's {first_nonfinite_leaf(agent_of_row(row))} became non-finite"
    others = len(bad_rows) - 1
    also = f" ({others} other{'s' if others > 1 else ''} too)" if others else ""
    return f"{seeds[row]} diverged at step {first_step[row]}{also}: {what}"


def expected_rows(cfg: TrainConfig, next_chunk: int) -> tuple[list[int], list[int]]:
    """The metric and evaluation steps a seed's files must hold when ``next_chunk`` chunks are done."""
    ends = [cfg.chunk_end_step(c) for c in range(next_chunk)]
    evals = [s for s in ends if cfg.evaluates_at(s)]
    return ends, evals
