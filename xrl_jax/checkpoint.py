"""Save and restore the whole run state with orbax, atomically, and verify it before it is trusted.

A checkpoint holds one pytree (all seeds' agent states, replay buffers, env states, observations,
keys, episode trackers) and a small JSON document (the host loop's counters). Orbax writes into a
temporary folder and renames it only once everything is on disk, and the older checkpoints are
deleted only after the new one is committed, so a crash at any moment leaves the last good
checkpoint readable. Saving is synchronous: the trainer donates the state to its next compiled
chunk, so the arrays must be copied out before the call returns.

Atomic writes do not protect against what happens to the files afterwards (a bad disk, a copy cut
short, a stray write). Every checkpoint therefore carries a manifest with a digest of each of its
files, and :meth:`Checkpointer.restore_newest_good` verifies them before orbax reads anything,
checks the restored state with a caller's test (the trainer checks that the agent is finite), and
falls back to the previous checkpoint when the newest is damaged; two are kept for that reason. The
manifest is written after orbax's commit, so a kill in between leaves a committed checkpoint without
one: a verified checkpoint is always preferred to it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import orbax.checkpoint as ocp

MANIFEST_NAME = "xrl_manifest.json"  # per checkpoint: a digest of every file orbax wrote


class CorruptCheckpointError(RuntimeError):
    """One checkpoint cannot be trusted: unreadable, a file unlike its digest, or a failed check."""


class NoGoodCheckpointError(RuntimeError):
    """No checkpoint of a folder can be trusted; the message lists why, one reason per checkpoint."""


def _zeros(shape: jax.ShapeDtypeStruct) -> jax.Array:
    """Zeros laid out as the restored arrays are (the same sharding, e.g. over a run's devices)."""
    make = lambda: jax.numpy.zeros(shape.shape, shape.dtype)
    sharding = getattr(shape, "sharding", None)
    return jax.jit(make, out_shardings=sharding)() if sharding is not None else make()


def file_digests(folder: Path) -> dict[str, str]:
    """``{path relative to folder: blake2b digest}`` of every file below ``folder`` but the manifest.

    Files rather than arrays: a damaged file is found before orbax reads it (orbax and tensorstore
    report damage inconsistently, and some damage they do not notice at all), the metadata files
    are covered too, and nothing is copied off the device. Hashing is cheap next to writing the
    same bytes."""
    out = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST_NAME):
        digest = hashlib.blake2b(digest_size=16)
        with open(path, "rb") as f:
            for block in iter(lambda f=f: f.read(1 << 22), b""):
                digest.update(block)
        out[path.relative_to(folder).as_posix()] = digest.hexdigest()
    return out


def _first_line(error: BaseException, limit: int = 160) -> str:
    text = (str(error).strip().splitlines() or [type(error).__name__])[0]
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _sync(name: str) -> None:
    """A barrier of all processes of a multi-host run (orbax writes one checkpoint together)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


class Checkpointer:
    """Keeps the newest ``max_to_keep`` checkpoints of one run state in ``directory``."""

    def __init__(self, directory: str | Path, max_to_keep: int = 2):
        if int(max_to_keep) < 1:
            raise ValueError(f"max_to_keep must be a positive integer, got {max_to_keep}")
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(
            max_to_keep=int(max_to_keep), create=True, enable_async_checkpointing=False
        )
        # The items' handlers named up front: a fresh manager (a resume, a new process) otherwise knows
        # only the items it was asked to restore, and reading the state's metadata alone (the fields
        # an older version did not write) found nothing, with a warning.
        handlers = {"state": ocp.StandardCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()}
        self._manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handlers)
        self.unverified_steps: list[int] = []  # steps restored without a digest manifest

    def save(self, step: int, state: Any, metadata: dict) -> None:
        """Write ``state`` and the JSON-serialisable ``metadata`` as checkpoint ``step`` (an int),
        then the digests of its files (a checkpoint without them restores unverified, with a warning)."""
        args = ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(metadata))
        self._manager.save(int(step), args=args, force=True)
        self._manager.wait_until_finished()
        if jax.process_index() == 0:  # in a multi-host run, once all processes' files are written
            folder = self.directory / str(int(step))
            manifest = json.dumps({"files": file_digests(folder)}, indent=1, sort_keys=True)
            tmp = folder / f".{MANIFEST_NAME}.tmp"
            with open(tmp, "w") as f:
                f.write(manifest)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, folder / MANIFEST_NAME)
        _sync(f"xrl-jax checkpoint {self.directory.name}/{int(step)}")

    def verify_files(self, step: int) -> bool:
        """Check checkpoint ``step``'s files against its manifest: True when verified, False when it
        has no manifest; raises :class:`CorruptCheckpointError` naming the first damaged file."""
        folder = self.directory / str(int(step))
        try:
            expected = json.loads((folder / MANIFEST_NAME).read_text())["files"]
        except FileNotFoundError:
            return False
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise CorruptCheckpointError(f"its manifest is unreadable ({_first_line(err)})") from None
        actual = file_digests(folder)
        missing = sorted(set(expected) - set(actual))
        if missing:
            raise CorruptCheckpointError(f"file {missing[0]} is missing ({len(missing)} in all)")
        damaged = sorted(name for name in expected if expected[name] != actual[name])
        if damaged:
            raise CorruptCheckpointError(f"file {damaged[0]} differs from its digest ({len(damaged)} in all)")
        return True

    def all_steps(self) -> list[int]:
        """Committed checkpoint steps, newest first."""
        self._manager.reload()
        return sorted(self._manager.all_steps(), reverse=True)

    def latest_step(self) -> int | None:
        """The step of the newest committed checkpoint, or None when there is none."""
        steps = self.all_steps()
        return steps[0] if steps else None

    def restore(self, abstract_state: Any, step: int | None = None) -> tuple[Any, dict]:
        """``(state, metadata)`` of checkpoint ``step`` (default: newest), its files verified first.

        ``abstract_state`` gives the structure, shapes and dtypes (``jax.eval_shape`` of the
        initialiser), so nothing is allocated twice. Raises :class:`CorruptCheckpointError` with a
        one-line reason when the checkpoint does not match its digests or cannot be read.
        """
        step = self.latest_step() if step is None else int(step)
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        self.verify_files(step)
        return self._read(abstract_state, step)

    def _read(self, abstract_state: Any, step: int) -> tuple[Any, dict]:
        target = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
        absent = self._fields_added_since(target, step)
        read_as = target
        if absent:  # read what the older version wrote; the fields it did not have start from zero
            read_as = flax.serialization.to_state_dict(target)
            for name in absent:
                del read_as[name]
        args = ocp.args.Composite(state=ocp.args.StandardRestore(read_as), meta=ocp.args.JsonRestore())
        try:
            restored = self._manager.restore(step, args=args)
            state, meta = restored.state, dict(restored.meta)
        except Exception as err:  # orbax and tensorstore raise many types for damaged files
            raise CorruptCheckpointError(f"unreadable ({_first_line(err)})") from err
        if absent:
            state = dict(state) | {name: jax.tree.map(_zeros, getattr(target, name)) for name in absent}
            state = flax.serialization.from_state_dict(target, state)
        return state, meta

    def _fields_added_since(self, target: Any, step: int) -> list[str]:
        """The fields of ``target`` that checkpoint ``step`` lacks because an older version wrote it:
        only those its class lists in ``FIELDS_ADDED_LATER`` (each one whose zero is what the older
        versions implied), so that any other difference still fails as unreadable."""
        added = [n for n in getattr(type(target), "FIELDS_ADDED_LATER", ()) if getattr(target, n) is not None]
        if not added:
            return []
        try:
            stored = self._manager.item_metadata(step)["state"].tree
        except Exception:  # damaged metadata: the restore itself reports it
            return []
        return [name for name in added if name not in stored]

    def metadata(self, step: int | None = None) -> dict:
        """The metadata of checkpoint ``step`` (default: newest) without reading the state, e.g. to
        check that the checkpoint belongs to the expected configuration before restoring it."""
        step = self.latest_step() if step is None else int(step)
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        except Exception as err:
            raise CorruptCheckpointError(f"unreadable metadata ({_first_line(err)})") from err
        return dict(restored.meta)

    def restore_newest_good(
        self,
        abstract_state: Any,
        check: Callable[[Any, dict], str | None] | None = None,
        log: Callable[[str], None] = print,
        set_aside: bool = True,
    ) -> tuple[Any, dict]:
        """``(state, metadata)`` of the newest checkpoint that reads, matches its digests and passes
        ``check(state, metadata)`` (which returns None, or a one-line reason to reject it).

        A checkpoint without a digest manifest (written by an older version, or cut short between
        its commit and its manifest) is tried only after every one that has a manifest: a verified
        checkpoint is preferred to a newer unverified one, and one restored unverified has its step
        added to ``unverified_steps``. Each checkpoint passed over (damaged, rejected by ``check``, or
        newer than the one restored) is reported through ``log`` in one line and, with ``set_aside``
        (the run's writer; never a reader of a folder), moved aside (to ``<directory>.rejected/<step>``),
        so that it is never restored and a later save of the same step is not blocked. Raises
        :class:`NoGoodCheckpointError` when none is good.
        """
        steps = self.all_steps()
        if not steps:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        with_digests = [s for s in steps if self._has_manifest(s)]
        order = with_digests + [s for s in steps if s not in with_digests]
        reasons = []
        for position, step in enumerate(order):
            try:
                verified = self.verify_files(step)
                if not verified:
                    log(f"checkpoint {self.directory.name}/{step} has no file digests (written by an older "
                        "version or cut short after its commit): restored unverified")  # fmt: skip
                state, meta = self._read(abstract_state, step)
                problem = check(state, meta) if check is not None else None
                if problem:
                    raise CorruptCheckpointError(problem)
            except CorruptCheckpointError as err:
                reasons.append(f"step {step}: {err}")
                older = order[position + 1] if position + 1 < len(order) else None
                fallback = f"falling back to step {older}" if older is not None else "no older checkpoint"
                log(f"checkpoint {self.directory.name}/{step} is damaged ({err}); {fallback}")
                if set_aside:
                    self._set_aside(step)
                continue
            if not verified:
                self.unverified_steps.append(step)
            for newer in (s for s in order[position + 1 :] if s > step):  # no digests, newer
                log(f"checkpoint {self.directory.name}/{newer} has no file digests (cut short between its "
                    f"commit and its digests): passed over for the verified step {step}")  # fmt: skip
                if set_aside:
                    self._set_aside(newer)
            return state, meta
        raise NoGoodCheckpointError(f"no usable checkpoint in {self.directory} ({'; '.join(reasons)})")

    def _has_manifest(self, step: int) -> bool:
        return (self.directory / str(int(step)) / MANIFEST_NAME).is_file()

    @property
    def rejected_directory(self) -> Path:
        """Where damaged checkpoints are set aside: ``<directory>.rejected/<step>-<time>``."""
        return self.directory.with_name(self.directory.name + ".rejected")

    def _set_aside(self, step: int) -> None:
        if jax.process_index() == 0:  # every process reached the same verdict on the shared files
            rejected = self.rejected_directory
            rejected.mkdir(parents=True, exist_ok=True)
            target = rejected / f"{step}-{time.strftime('%Y%m%d-%H%M%S')}"
            shutil.move(str(self.directory / str(step)), str(target))
        _sync(f"xrl-jax set aside {self.directory.name}/{step}")
        self._manager.reload()

    def close(self) -> None:
        self._manager.close()


def save_checkpoint(
    directory: str | Path, step: int, state: Any, metadata: dict, max_to_keep: int = 2
) -> None:
    """One-shot :meth:`Checkpointer.save`."""
    checkpointer = Checkpointer(directory, max_to_keep)
    try:
        checkpointer.save(step, state, metadata)
    finally:
        checkpointer.close()


def restore_checkpoint(
    directory: str | Path, abstract_state: Any, step: int | None = None
) -> tuple[Any, dict]:
    """One-shot :meth:`Checkpointer.restore`."""
    checkpointer = Checkpointer(directory)
    try:
        return checkpointer.restore(abstract_state, step)
    finally:
        checkpointer.close()


def latest_step(directory: str | Path) -> int | None:
    """Newest committed checkpoint step in ``directory`` (None if the folder or checkpoints are missing)."""
    if not Path(directory).is_dir():
        return None
    checkpointer = Checkpointer(directory)
    try:
        return checkpointer.latest_step()
    finally:
        checkpointer.close()
