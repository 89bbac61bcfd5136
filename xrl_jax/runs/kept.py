"""What a report keeps of its runs, which folders hold one run, and which runs are one protocol.

A report copies the records it reads (``config.json``, ``eval/``) into ``runs/`` beside it, so that it
can be written again, or with a run added, after the run folders are gone; it reads a run given both
as its folder and as such a copy once; and it pools runs that differ only in how they were carried
out, each from its own base seed, into one row.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from xrl_jax.runs.folder import read_rows, run_paths

RECORDS = "runs"  # the report's copy of the records of every run it reports
RECORD_DROPS = ("episode_returns",)  # per-episode values: the bulk of an evaluation row, unused there

# How a run was carried out, not what it measures: runs whose settings differ only in these (their
# base seeds differing) are one protocol, and the report pools their seeds into one row.
EXECUTION_SETTINGS = frozenset(
    {"seed", "num_seeds", "max_group_size", "memory_budget_gb", "checkpoint_minutes", "num_devices",
     "checkpoint_interval"}
)  # fmt: skip


def distinct_runs(folders: list[str | Path], note=None) -> list[Path]:
    """``folders`` with each run once, in the order given; ``note`` takes a line per folder left out.

    One folder under two names (a link, another path) counts once, and so does a run given both as
    its folder and as a report's copy of its records: the copy has the run's ``config.json``, byte for
    byte, and its evaluation lines, less their per-episode values, up to when it was made. Of the two,
    the one with more evaluations stays (the run may have gone on); on a tie, the first. Two runs of
    one command at one commit (two machines) share a ``config.json`` but not their evaluations.
    """
    chosen: list[Path] = []
    by_path: dict[Path, Path] = {}
    same_config: dict[bytes, list[int]] = {}  # config.json contents -> indices in ``chosen``
    for folder in map(Path, folders):
        first = by_path.setdefault(folder.resolve(), folder)
        if first is not folder:
            again = "given twice" if first == folder else f"the same folder as {first}"
            _note(note, f"{folder} is {again}; reported once")
            continue
        contents = _config_bytes(folder)  # None: not a run, which reading the runs reports
        earlier = same_config.setdefault(contents, []) if contents is not None else []
        history = _evaluations(folder) if earlier else {}
        index = next((i for i in earlier if _one_history(history, _evaluations(chosen[i]))), None)
        if index is None:
            earlier.append(len(chosen))
            chosen.append(folder)
            continue
        other = chosen[index]
        longer = sum(map(len, history.values())) > sum(map(len, _evaluations(other).values()))
        stays, leaves = (folder, other) if longer else (other, folder)
        chosen[index] = stays
        _note(note, f"{leaves} holds the same run as {stays} (its records); reported once")
    return chosen


def _config_bytes(folder: Path) -> bytes | None:
    try:
        return run_paths(folder)["config"].read_bytes()
    except OSError:  # not a run, or unreadable: reading its runs says so in one line
        return None


def _evaluations(folder: Path) -> dict[str, list[dict]]:
    """Each member's evaluation lines as a report keeps them (without :data:`RECORD_DROPS`)."""
    return {
        lines.name: [{k: v for k, v in row.items() if k not in RECORD_DROPS} for row in read_rows(lines)]
        for lines in sorted(run_paths(folder)["eval"].glob("*.jsonl"))
    }


def _one_history(a: dict[str, list[dict]], b: dict[str, list[dict]]) -> bool:
    """Every member's evaluations in one are the start of its evaluations in the other."""
    return all(a.get(name, [])[: len(b.get(name, []))] == b.get(name, [])[: len(a.get(name, []))]
               for name in {*a, *b})  # fmt: skip


def _note(note, line: str) -> None:
    if note is not None:
        note(line)


def protocol(cfg) -> str:
    """What a run measures: its settings without :data:`EXECUTION_SETTINGS`, as one string; of a
    sweep, the fields it sweeps but not their values, so that pieces of one sweep (some values each,
    trained a session at a time) are one protocol."""
    settings = {k: v for k, v in cfg.to_dict().items() if k not in EXECUTION_SETTINGS}
    if cfg.sweep:
        settings["sweep"] = [name for name, _ in cfg.sweep]
    return json.dumps(settings, sort_keys=True, default=str)


def protocol_groups(configs: list[tuple[Path, Any]], note=None) -> list[list[tuple[Path, Any]]]:
    """``(folder, cfg)`` of every run, grouped: the runs of one :func:`protocol` are one group, in
    order of base seed (a protocol's seeds trained a few at a time, in runs of ``--set seed=S``; a
    sweep's values or seeds, in pieces), unless two of them trained one seed of one sweep point (the
    same base seed and a point both swept, or two plain runs from one base seed): then each is a group
    of its own; ``note`` takes a line about that and about every pool."""
    groups: dict[str, list[tuple[Path, Any]]] = {}
    for folder, cfg in configs:
        groups.setdefault(protocol(cfg), []).append((folder, cfg))
    out = []
    for parts in groups.values():
        if len(parts) == 1 or not _trained_apart(parts):
            if len(parts) > 1 and note is not None:
                names = ", ".join(folder.name for folder, _ in parts)
                where = "a sweep point both swept" if parts[0][1].sweep else "one protocol"
                note(f"{names} trained the same seeds of {where} (one base seed); reported separately")
            out += [[part] for part in parts]
            continue
        out.append(sorted(parts, key=lambda part: part[1].seed))
        if note is not None:
            pooled = ", ".join(f"{f.name}: {c.num_seeds} from base seed {c.seed}" for f, c in out[-1])
            note(f"one protocol's seeds pooled into one row ({pooled})")
    return out


def _trained_apart(parts: list[tuple[Path, Any]]) -> bool:
    """Whether no two of the runs trained one seed of one sweep point (a plain run: one point)."""
    trained = [
        (cfg.seed, json.dumps(values, sort_keys=True)) for _, cfg in parts for values in cfg.sweep_points
    ]
    return len(set(trained)) == len(trained)


def keep_records(folders: list[Path], out: Path) -> None:
    """Copy what the report reads of each run folder into ``out/runs/<folder name>``: its
    ``config.json``, its evaluation lines without their per-episode values and its explanation
    statistics (``explain/stats/stats.json``, where ``explain.py --stats`` wrote them).
    ``report.py out/runs/* NEW_RUN --out out`` then writes the report again with a run added, after
    the run folders are gone (a user's clone, another machine). The copies replace the folder's
    earlier ones as a whole, so it holds exactly the runs of this report; given as sources
    themselves, they are read before they are replaced. Runs whose folders share a name are kept as
    ``<name>``, ``<name>-2``, ..."""
    staging, kept, former = out / f".{RECORDS}.new", out / RECORDS, out / f".{RECORDS}.old"
    if former.exists() and not kept.exists():  # a report stopped between the two renames below
        former.rename(kept)
    for leftover in (staging, former):  # of a report that was stopped half-way
        shutil.rmtree(leftover, ignore_errors=True)
    names: list[str] = []
    for folder in folders:
        name, index = folder.name, 1
        while name in names:
            index += 1
            name = f"{folder.name}-{index}"
        names.append(name)
        source, copy = run_paths(folder), run_paths(staging / name)
        copy["eval"].mkdir(parents=True)
        shutil.copyfile(source["config"], copy["config"])
        for name, rows in _evaluations(folder).items():
            (copy["eval"] / name).write_text("".join(json.dumps(row) + "\n" for row in rows))
        stats = source["explain_stats"] / "stats.json"  # explain.py --stats, where the run has them
        if stats.is_file():
            copy["explain_stats"].mkdir(parents=True)
            shutil.copyfile(stats, copy["explain_stats"] / "stats.json")
    if kept.exists():  # swapped, never deleted first: the old copies may be this report's sources
        kept.rename(former)
    staging.rename(kept)
    shutil.rmtree(former, ignore_errors=True)
