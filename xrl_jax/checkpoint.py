"""Save and restore the whole run state with orbax, atomically.

A checkpoint holds one pytree (all seeds' agent states, replay buffers, env states, observations,
keys, episode trackers) and a small JSON document (the host loop's counters). Orbax writes into a
temporary folder and renames it only once everything is on disk, and the previous checkpoint is
deleted only after the new one is committed, so a crash at any moment leaves the last good
checkpoint readable. Saving is synchronous: the trainer donates the state to its next compiled
chunk, so the arrays must be copied out before the call returns.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp


class Checkpointer:
    """Keeps the newest ``max_to_keep`` checkpoints of one run state in ``directory``."""

    def __init__(self, directory: str | Path, max_to_keep: int = 1):
        if int(max_to_keep) < 1:
            raise ValueError(f"max_to_keep must be a positive integer, got {max_to_keep}")
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(
            max_to_keep=int(max_to_keep), create=True, enable_async_checkpointing=False
        )
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def save(self, step: int, state: Any, metadata: dict) -> None:
        """Write ``state`` and the JSON-serialisable ``metadata`` as checkpoint ``step`` (an int)."""
        args = ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(metadata))
        self._manager.save(int(step), args=args, force=True)
        self._manager.wait_until_finished()

    def latest_step(self) -> int | None:
        """The step of the newest committed checkpoint, or None when there is none."""
        self._manager.reload()
        return self._manager.latest_step()

    def restore(self, abstract_state: Any, step: int | None = None) -> tuple[Any, dict]:
        """``(state, metadata)`` of checkpoint ``step`` (default: newest).

        ``abstract_state`` gives the structure, shapes and dtypes (``jax.eval_shape`` of the
        initialiser), so nothing is allocated twice.
        """
        step = self.latest_step() if step is None else int(step)
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        target = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
        args = ocp.args.Composite(state=ocp.args.StandardRestore(target), meta=ocp.args.JsonRestore())
        restored = self._manager.restore(step, args=args)
        return restored.state, dict(restored.meta)

    def metadata(self, step: int | None = None) -> dict:
        """The metadata of checkpoint ``step`` (default: newest) without reading the state, e.g. to
        check that the checkpoint belongs to the expected configuration before restoring it."""
        step = self.latest_step() if step is None else int(step)
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        restored = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        return dict(restored.meta)

    def close(self) -> None:
        self._manager.close()


def save_checkpoint(
    directory: str | Path, step: int, state: Any, metadata: dict, max_to_keep: int = 1
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
