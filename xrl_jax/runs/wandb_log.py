"""What a W&B run's transaction logs under a run folder hold: the history steps W&B has on disk.

W&B writes every run (offline and online alike) to ``<dir>/wandb/<offline->run-<time>-<id>/run-<id>.wandb``:
its records (protocol buffers, ``wandb.proto.wandb_internal_pb2.Record``) in LevelDB's log format,
blocks of 32 KiB of checksummed fragments behind a 7-byte header. Its service writes a block only
once it is full or the run finishes, so a killed session's log lacks the last records it was sent;
:class:`~xrl_jax.runs.trackers.TrackerMirror` reads the logs back to send those again. wandb 0.30
removed its own reader of this format (``wandb.sdk.internal.datastore``), so this is ours.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

HEADER = struct.pack("<4sHB", b":W&B", 0xBEE1, 0)  # ident, magic, version
BLOCK = 32768
_FRAGMENT = struct.Struct("<IHB")  # crc32 of type and data, data length, type
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4
_TYPE_CRC = {kind: zlib.crc32(bytes([kind])) for kind in (FULL, FIRST, MIDDLE, LAST)}


def read_records(path: str | Path) -> Iterator[bytes]:
    """The complete records of one ``.wandb`` file, in order; reading stops quietly at the first
    fragment that is cut short or fails its checksum (where a killed writer stopped)."""
    data = Path(path).read_bytes()
    if not data.startswith(HEADER):
        return
    offset, pending = len(HEADER), None
    while True:
        if BLOCK - offset % BLOCK < _FRAGMENT.size:  # a block's tail too short for a fragment: padding
            offset += BLOCK - offset % BLOCK
        if offset + _FRAGMENT.size > len(data):
            return
        checksum, length, kind = _FRAGMENT.unpack_from(data, offset)
        body = data[offset + _FRAGMENT.size : offset + _FRAGMENT.size + length]
        if kind not in _TYPE_CRC or len(body) < length or zlib.crc32(body, _TYPE_CRC[kind]) != checksum:
            return
        offset += _FRAGMENT.size + length
        if kind == FULL:
            yield body
        elif kind == FIRST:
            pending = body
        elif pending is not None:
            pending += body
            if kind == LAST:
                yield pending
                pending = None


def run_logs(folder: str | Path, run_id: str) -> list[Path]:
    """The transaction logs of W&B run ``run_id`` under ``folder/wandb`` (one per session), oldest first."""
    root = Path(folder, "wandb")
    if not root.is_dir():
        return []
    sessions = [d for d in root.iterdir() if d.name.endswith(f"-{run_id}") and not d.is_symlink()]
    logs = [d / f"run-{run_id}.wandb" for d in sorted(sessions, key=lambda d: d.name.split("run-", 1)[-1])]
    return [path for path in logs if path.is_file()]


def history_rows(folder: str | Path, run_id: str) -> Iterator[tuple[int, dict[str, str]]]:
    """``(step, {key: JSON value})`` of every history row W&B holds on disk for run ``run_id``."""
    from wandb.proto import wandb_internal_pb2

    for path in run_logs(folder, run_id):
        for data in read_records(path):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(data)
            if record.WhichOneof("record_type") == "history":
                items = record.history.item
                row = {item.key or "/".join(item.nested_key): item.value_json for item in items}
                yield record.history.step.num, row


def last_history_step(folder: str | Path, run_id: str) -> int:
    """The last step of run ``run_id`` that W&B holds on disk under ``folder`` (-1: none)."""
    return max((step for step, _ in history_rows(folder, run_id)), default=-1)
