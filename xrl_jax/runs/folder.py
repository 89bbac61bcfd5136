"""The results folder of a run, its one owner: the only module that spells the folder's file names.
Its layout, crash-safe writes, the one JSON-lines reader, the readers of ``config.json`` and
``plan.json`` (one-line errors), the writer's lock, and the checks a resume makes before it
continues what is there.

Every file is written so that a crash at any moment loses at most the line being written: JSON
lines are appended and forced to disk, whole documents are replaced atomically. One process writes
into a folder at a time (an ``flock`` on ``.lock``, which the kernel releases when the holder dies,
so a lock left by a killed run never blocks the next one).
"""

from __future__ import annotations

import errno
import fcntl
import json
import math
import os
import socket
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from xrl_jax.config import TrainConfig
from xrl_jax.config.scenarios import known_envs
from xrl_jax.config.user_envs import record_differences, user_env_record

LOCK_NAME = ".lock"
TEMP_MARK = ".tmp"  # ``.<name>.tmp<pid>``: what write_atomic leaves behind when it is killed mid-write


class RunFolderError(RuntimeError):
    """A results folder cannot be used as asked; the message is one line and says what to do."""


def run_paths(out: Path) -> dict[str, Path]:
    return {
        "config": out / "config.json",
        "plan": out / "plan.json",
        "metrics": out / "metrics",
        "eval": out / "eval",
        "checkpoints": out / "checkpoints",
        "summary": out / "summary.json",
        "curve": out / "learning_curve.png",
        "sweep": out / "sweep.png",
        "timing": out / "timing.jsonl",
        "trackers": out / "trackers.json",  # what the trackers of runs.trackers have received
        "tensorboard": out / "tensorboard",
        "explain": out / "explain",  # experiments/explain.py's figures and attributions, by default
        "explain_stats": out / "explain" / "stats",  # explain.py --stats: stats.json and its figures
    }


def metrics_file(out: Path, stem: str) -> Path:
    """Member ``stem``'s training metrics, one JSON line every ``log_interval`` steps."""
    return Path(out) / "metrics" / f"{stem}.jsonl"


def eval_file(out: Path, stem: str) -> Path:
    """Member ``stem``'s evaluations, one JSON line every ``eval_interval`` steps."""
    return Path(out) / "eval" / f"{stem}.jsonl"


def checkpoint_dir(out: Path, group: int) -> Path:
    """The checkpoints of seed group ``group`` (each group is restored as a whole)."""
    return Path(out) / "checkpoints" / f"group_{group}"


def evaluation_file(out: Path, tracks: str, mode: str) -> Path:
    """Where a later evaluation of the run's agents goes: ``evaluation_<tracks>.json`` for the
    evaluation protocol's own mode, ``evaluation_<tracks>_<mode>.json`` for another."""
    suffix = "" if mode == "eval" else f"_{mode}"
    return Path(out) / f"evaluation_{tracks}{suffix}.json"


def member_stem(cfg, member: int) -> str:
    """The file name (without suffix) of member ``member``'s metrics and evaluations: ``seed_<s>``
    in a plain run, ``point_<p>_seed_<s>`` in a sweep (``cfg`` is the run's TrainConfig)."""
    point, seed = cfg.member_point_seed(member)
    return f"seed_{seed}" if cfg.num_points == 1 else f"point_{point}_seed_{seed}"


def member_fields(cfg, member: int) -> dict:
    """What every record of member ``member`` says about it: its seed, its sweep point and the
    point's swept values (empty in a plain run)."""
    point, seed = cfg.member_point_seed(member)
    return {"seed": seed, "point": point, "sweep": cfg.sweep_points[point]}


# ------------------------------------------------------------------------------------------------
# Writing
# ------------------------------------------------------------------------------------------------


def encode_metric(value) -> Any:
    """A metric as JSON: numbers as they are, non-finite floats as the strings ``"nan"``, ``"inf"``
    and ``"-inf"`` (JSON has no such numbers). ``None`` is kept for "no data yet", so the two never
    read alike. Arrays become nested lists."""
    value = np.asarray(value)
    if value.ndim:
        return [encode_metric(v) for v in value]
    item = value.item()
    if isinstance(item, float) and not math.isfinite(item):
        return "nan" if math.isnan(item) else ("inf" if item > 0 else "-inf")
    return item


def append_lines(path: Path, rows: list[dict]) -> None:
    """Append JSON lines and force them to disk (a crash loses at most the line being written)."""
    with open(path, "a") as f:
        for row in rows:
            f.write(json.dumps(row, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` all at once: readers see the old or the new file, never a part."""
    tmp = path.with_name(f".{path.name}{TEMP_MARK}{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_rows(path: Path) -> list[dict]:
    """The complete JSON lines of ``path`` (a line cut by a crash is skipped)."""
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict):
            rows.append(row)
    return rows


_NONFINITE = ("nan", "inf", "-inf")  # encode_metric's spelling of non-finite values


def _is_nonfinite(value) -> bool:
    if isinstance(value, list):
        return any(_is_nonfinite(item) for item in value)
    return isinstance(value, str) and value in _NONFINITE


class Divergence(NamedTuple):
    """Where a run's records first hold a non-finite value (ordered by step)."""

    step: int
    member: str  # the member's file stem
    metric: str

    def __str__(self) -> str:
        return f"{self.member.replace('_', ' ')} by step {self.step:,} ({self.metric} not finite)"


def first_nonfinite_metric(folder: str | Path) -> Divergence | None:
    """The earliest metrics line holding a non-finite value: the run diverged by that step (the trainer
    stops there, keeping the last good checkpoint); None if no line does."""
    found = []
    for path in sorted(run_paths(Path(folder))["metrics"].glob("*.jsonl")):
        for row in read_rows(path):
            bad = [key for key, value in row.items() if _is_nonfinite(value)]
            if bad and isinstance(row.get("step"), int):
                found.append(Divergence(row["step"], path.stem, bad[0]))
                break
    return min(found, default=None)


def read_document(path: Path, what: str) -> dict:
    """A JSON document of the folder, or :class:`RunFolderError` in one line (missing, unreadable,
    or not a JSON object)."""
    try:
        document = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise RunFolderError(f"{path.parent} has no {path.name} ({what})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RunFolderError(f"{path} is unreadable ({what}): {err}") from None
    if not isinstance(document, dict):
        raise RunFolderError(f"{path} is not a JSON object ({what})")
    return document


def read_run_config(folder: str | Path):
    """The full :class:`~xrl_jax.config.TrainConfig` of a results folder (its ``config.json``). A run on
    a user's env is refused (one line) when the env registered now is not the run's: another layout,
    action space, time limit or registering module (:mod:`xrl_jax.config.user_envs`)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RunFolderError(f"results folder {folder} does not exist")
    path = run_paths(folder)["config"]
    if not path.is_file():
        raise RunFolderError(f"{folder} is not a results folder (no config.json)")
    document = read_document(path, "the run's configuration")
    env = read_run_env(folder)
    if env is not None and env not in known_envs():  # a user's env this process has not registered
        raise RunFolderError(
            f"{folder} trained on {env!r}, an env this process has not registered: --import the module "
            "that registers it (xrl_jax.register_env)"
        )
    stored = document.get("user_env")
    if isinstance(stored, dict):  # a user's env: the one registered now must be the run's
        differences = record_differences(stored, user_env_record(env))
        if differences:
            raise RunFolderError(
                f"{folder} trained on {env!r} as module {stored.get('module')!r} registered it, not as this "
                f"process has it ({'; '.join(differences)}): --import the module the run was trained with"
            )
    try:
        return TrainConfig.from_dict(document["config"])
    except (ValueError, KeyError, TypeError) as err:
        raise RunFolderError(f"{path} is unreadable or from another version ({err})") from None


def read_run_env(folder: str | Path) -> str | None:
    """The scenario a results folder's ``config.json`` names, without validating the rest (so that a
    run of an unsupported scenario is refused by name); None when there is no readable one."""
    try:
        env = read_document(run_paths(Path(folder))["config"], "the run's configuration")["config"]["env"]
    except (RunFolderError, KeyError, TypeError):
        return None
    return env if isinstance(env, str) else None


def has_config(folder: str | Path) -> bool:
    """Whether ``folder`` holds a run's ``config.json``: a run was started there (so ``--resume``
    continues it), whether or not it finished."""
    return run_paths(Path(folder))["config"].is_file()


def read_summary(folder: str | Path) -> dict:
    """The ``summary.json`` a finished (or stopped) run wrote, or :class:`RunFolderError` in one line
    saying that there is no readable one and why."""
    path = run_paths(Path(folder))["summary"]
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise RunFolderError(f"no readable {path.name} ({getattr(err, 'strerror', None) or err})") from None
    if not isinstance(document, dict):
        raise RunFolderError(f"no readable {path.name} (not a JSON object)")
    return document


def is_complete(folder: str | Path) -> bool:
    """Whether the run in ``folder`` finished: its summary says every member reached its last step.
    A missing or unreadable summary is an unfinished run."""
    try:
        return bool(read_summary(folder).get("complete"))
    except RunFolderError:
        return False


def read_checkpoint_plan(folder: str | Path, num_members: int) -> tuple[list[list[int]], int]:
    """The member groups of the run's checkpoints and the device count they were padded to
    (``plan.json``; one group on one device when it is missing, as in runs older than the plan)."""
    path = run_paths(Path(folder))["plan"]
    if not path.is_file():
        return [list(range(num_members))], 1
    plan = read_document(path, "the run's seed groups")
    try:
        groups = [[int(m) for m in group] for group in plan["groups"]]
        return groups, int(plan.get("devices", 1))
    except (KeyError, TypeError, ValueError) as err:
        raise RunFolderError(f"{path} does not describe the seed groups ({err!r})") from None


def truncate_lines(path: Path, max_step: int) -> None:
    """Keep only complete lines with ``step <= max_step`` (atomic rewrite), for a resumed run."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a crash
        if isinstance(row, dict) and row.get("step", 0) <= max_step:
            kept.append(line)
    write_atomic(path, "".join(line + "\n" for line in kept))


def disk_full_reason(error: BaseException | None) -> str | None:
    """Why ``error`` (or what caused it, as orbax wraps it) is a full disk: "No space left on device"
    or "Disk quota exceeded"; None for any other error."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
            return os.strerror(error.errno)
        for reason in (os.strerror(errno.ENOSPC), os.strerror(errno.EDQUOT)):
            if reason in str(error):
                return reason
        error = error.__cause__ or error.__context__
    return None


def is_disk_full(error: BaseException) -> bool:
    """Whether ``error`` (or what caused it, as orbax wraps it) is a full disk or an exceeded quota."""
    return disk_full_reason(error) is not None


def refused_write(error: BaseException | None) -> OSError | None:
    """The write that ``error`` (or what caused it, as orbax wraps it) failed on for want of
    permission or on a read-only file system, or None for any other error."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            return error
        error = error.__cause__ or error.__context__
    return None


def disk_full_message(out: Path, resume: bool, error: BaseException) -> str:
    """What to do about a disk (or quota) that filled up while a run wrote into ``out``, in one line.
    Before the run's first results (only its start-up files are there, see :func:`holds_results`)
    the same command starts it again; later, the committed checkpoints are intact and ``--resume``
    continues them."""
    reason = disk_full_reason(error) or os.strerror(errno.ENOSPC)
    if not resume and not (out.is_dir() and holds_results(out)):
        return (
            f"the disk of {out} is full ({reason}) before the run wrote any results: free some space "
            "(or choose another --out) and start it again"
        )
    return (
        f"the disk of {out} is full ({reason}); committed checkpoints are intact: "
        f"free some space and continue with --resume {out}"
    )


# ------------------------------------------------------------------------------------------------
# One writer per folder
# ------------------------------------------------------------------------------------------------


class RunLock:
    """An exclusive, non-blocking lock on a results folder for the lifetime of one run.

    ``flock`` is tied to the open file: the kernel drops it when the process exits or is killed, so
    a stale lock file (a holder that died) is recognised by simply being lockable again. The file
    records who holds it, for the message the second writer gets. The trainer takes it once, for the
    whole run; a second lock on the folder, even in the same process, is refused.
    """

    def __init__(self, folder: str | Path, process: int = 0):
        # The processes of a multi-host run share the folder; each holds a lock of its own.
        name = LOCK_NAME if process == 0 else f"{LOCK_NAME}.process_{process}"
        self.path = (Path(folder) / name).absolute()
        self._file = None

    def acquire(self) -> RunLock:
        handle = open(self.path, "a+")  # noqa: SIM115 - held open for the lock's lifetime
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            if err.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            raise RunFolderError(
                f"results folder {self.path.parent} is in use by {holder}; "
                "wait for that run to end (or stop it) before resuming it"
            ) from None
        handle.seek(0)
        handle.truncate()
        started = time.strftime("%Y-%m-%d %H:%M:%S")
        handle.write(f"process {os.getpid()} on {socket.gethostname()} (since {started})\n")
        handle.flush()
        self._file = handle
        return self

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing the descriptor releases the flock
            self._file = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ------------------------------------------------------------------------------------------------
# Fresh folders and resumed ones
# ------------------------------------------------------------------------------------------------


def holds_results(folder: Path) -> bool:
    """Whether ``folder`` holds anything a run produced: a metric or evaluation line, a checkpoint,
    a summary, or a file the project does not know. Leftovers of a start that failed before the
    first chunk (the config, the plan, empty sub-folders, temporary files, the lock) do not count,
    so a retry may use the same folder."""
    paths = run_paths(folder)
    startup = {paths["config"].name, paths["plan"].name, LOCK_NAME}
    for entry in folder.iterdir():
        lock = entry.name.startswith(f"{LOCK_NAME}.process_")
        if entry.name in startup or lock or (entry.name.startswith(".") and TEMP_MARK in entry.name):
            continue
        if entry.is_dir() and entry.name in ("metrics", "eval", "checkpoints"):
            if any(p.is_file() and p.stat().st_size for p in entry.rglob("*")):
                return True
            continue
        return True
    return False


def remove_leftovers(folder: Path) -> None:
    """Delete temporary files that a killed writer left in ``folder`` (never anything else)."""
    for entry in folder.iterdir():
        if entry.is_file() and entry.name.startswith(".") and TEMP_MARK in entry.name:
            entry.unlink(missing_ok=True)


def check_history(path: Path, expected_steps: list[int], what: str) -> None:
    """Raise :class:`RunFolderError` unless ``path`` holds a row for every step in ``expected_steps``.

    A resumed run continues the checkpoint's state, but the rows written before it cannot be
    recomputed from that state: if they are gone, the run's history (and the learning curve) would
    silently lose them."""
    if not expected_steps:
        return
    have = {row.get("step") for row in read_rows(path)}
    missing = [s for s in expected_steps if s not in have]
    if not missing:
        return
    if not path.exists():
        found = "is missing"
    else:
        found = f"lacks {len(missing)} of its {len(expected_steps)} {what} rows (steps {_span(missing)})"
    raise RunFolderError(
        f"cannot resume: {path.parent.name}/{path.name} {found}; rows up to the checkpoint (step "
        f"{expected_steps[-1]}) cannot be recomputed: restore the file or start a new run with --out"
    )


def _span(steps: list[int]) -> str:
    return str(steps[0]) if len(steps) == 1 else f"{steps[0]}…{steps[-1]}"
