"""TensorBoard and Weights & Biases mirrors of a run folder (``run.py --log tensorboard|wandb``).

A :class:`TrackerMirror` is a progress callback of the host loop (``train(..., progress_fns=(mirror,))``,
as Brax's ``progress_fn``): after every chunk it receives the records the loop has just written to
the folder and sends them on. The folder's JSON-lines files stay the source of truth: a tracker only
ever receives what they hold. A session's first call reads them once, to send what the trackers have
not received yet (a resumed run, or a ``--resume`` with ``--log`` that an earlier session did not
have); after that the records arrive as they are written.

``trackers.json`` remembers, per tracker and run, the last step the tracker holds on disk, and the
W&B run ids, which a resume reuses so that each member's W&B run continues rather than starts anew.
TensorBoard holds a step once its event files are flushed, after every chunk. W&B's service writes
its transaction log in blocks of 32 KiB and all of it only when the run finishes, so its steps are
recorded at the end of a session; a session killed before that (``kill -9``) leaves fewer steps in
W&B's logs than it sent, and the next one reads the logs back (:mod:`xrl_jax.runs.wandb_log`) to
send the rest again: nothing is lost and no step is sent twice.

What each member (seed, or sweep point × seed) gets, as one tracker run named by its file stem and
grouped under the run folder's name: its training metrics every ``log_interval`` steps (under their own
names: ``rollout/...``, ``train/...``, ``buffer/...``), its evaluations (``eval/...``) and the
hyper-parameters (the resolved config, flattened). The learning-curve IQM over seeds, with its 95 % CI,
is one more run (``iqm``, or ``point_<p>_iqm`` in a sweep), extended whenever every seed has evaluated
at a step.

A tracker that fails (a full disk, W&B's service gone) is reported once and dropped; training and the
folder's files go on.
"""

from __future__ import annotations

import copy
import json
import os
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from xrl_jax.config import ConfigError
from xrl_jax.runs.folder import eval_file, member_stem, metrics_file, read_rows, run_paths, write_atomic
from xrl_jax.runs.summary import curve_over_seeds
from xrl_jax.runs.wandb_log import last_history_step

TRACKERS = ("tensorboard", "wandb")
# The record fields that say which member a line belongs to, and lists (per-episode values): not scalars.
_NOT_SCALARS = ("step", "seed", "point", "sweep")


def check_trackers(names: Sequence[str]) -> None:
    """Fail in one line, before anything runs, when a tracker is unknown or its extra is missing."""
    for name in names:
        if name not in TRACKERS:
            raise ConfigError(f"unknown tracker {name!r}; known: {', '.join(TRACKERS)}")
        try:
            if name == "tensorboard":
                import tensorboard  # noqa: F401
            else:
                quiet_offline_wandb()
                import wandb  # noqa: F401
        except ImportError:
            raise ConfigError(f"--log {name} needs the {name} extra: pip install 'xrl-jax[{name}]'") from None


def flatten_config(document: dict, prefix: str = "") -> dict[str, Any]:
    """Nested settings as ``{"agent.actor_lr": 3e-4, ...}`` with scalar values (lists as text)."""
    flat = {}
    for key, value in document.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat |= flatten_config(value, f"{name}.")
        elif value is None or isinstance(value, bool | int | float | str):
            flat[name] = value
        else:
            flat[name] = json.dumps(value)
    return flat


def scalar_values(row: dict, prefix: str = "") -> dict[str, float]:
    """A record's numbers as tracker scalars named ``prefix + key``: ``"nan"``/``"inf"`` strings (the
    folder's spelling of non-finite values) become floats; "no data yet" (None), lists and member fields
    are left out."""
    values = {}
    for key, value in row.items():
        if key in _NOT_SCALARS or value is None or isinstance(value, list | dict):
            continue
        if isinstance(value, str):
            if value not in ("nan", "inf", "-inf"):
                continue
            value = float(value)
        values[f"{prefix}{key}"] = float(value)
    return values


def _wait_past_latest_event_file(folder: Path) -> None:
    """TensorBoard reads a run's event files in name order and a name starts with the second it was
    created in; a file that sorted before the previous session's would replay its steps out of order
    (and TensorBoard drops steps that go backwards). So a session that starts within the second of
    the latest file waits for the next second (never more than one: a file from a clock that has
    since been set back cannot be sorted after anyway)."""
    names = (f.name.split(".") for f in folder.glob("events.out.tfevents.*"))
    seconds = [int(parts[3]) for parts in names if len(parts) > 3 and parts[3].isdigit()]
    delay = max(seconds, default=0) + 1 - time.time()
    if 0 < delay <= 1:
        time.sleep(delay)


class TensorBoardTracker:
    """One TensorBoard run per member: ``<folder>/tensorboard/<member>/``, event files written with
    TensorBoard's own writer (no TensorFlow needed). A resumed session adds an event file beside
    the earlier ones; TensorBoard reads a run's files as one."""

    name = "tensorboard"

    def __init__(self, out: Path, group: str, state: dict):
        from tensorboard.compat.proto import event_pb2, summary_pb2
        from tensorboard.plugins.hparams import summary_v2
        from tensorboard.summary.writer.event_file_writer import EventFileWriter

        self._event, self._summary, self._hparams = event_pb2.Event, summary_pb2.Summary, summary_v2
        self._file_writer = EventFileWriter
        self.root = run_paths(out)["tensorboard"]
        self.writers: dict[str, Any] = {}

    def held_step(self, run: str) -> int:
        return -1  # nothing beyond trackers.json: a flushed step is on disk

    def start(self, run: str, hparams: dict[str, Any]) -> None:
        folder = self.root / run
        _wait_past_latest_event_file(folder)
        writer = self.writers[run] = self._file_writer(str(folder))
        known = {k: v for k, v in hparams.items() if v is not None}
        summary = self._hparams.hparams_pb(known, trial_id=run)
        writer.add_event(self._event(wall_time=time.time(), step=0, summary=summary))

    def log(self, run: str, step: int, values: dict[str, float]) -> None:
        entries = [self._summary.Value(tag=tag, simple_value=value) for tag, value in values.items()]
        self.writers[run].add_event(
            self._event(wall_time=time.time(), step=step, summary=self._summary(value=entries))
        )

    def flush(self) -> bool:
        """Write what was logged to the event files; True: it is on disk now."""
        for writer in self.writers.values():
            writer.flush()
        return True

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
        self.writers.clear()


def _wandb_offline() -> bool:
    return os.environ.get("WANDB_MODE", "").lower() in ("offline", "dryrun", "disabled")


def quiet_offline_wandb() -> None:
    """An offline W&B run reports nothing to W&B's error service either (its retries printed three
    warnings on a machine without network); set before wandb starts its service."""
    if _wandb_offline():
        os.environ.setdefault("WANDB_ERROR_REPORTING", "false")


class WandbTracker:
    """One W&B run per member in the project ``$WANDB_PROJECT`` (default ``xrl-jax``), grouped by the
    run folder's name, its files under ``<folder>/wandb/``. ``WANDB_MODE=offline`` works without a
    network (``wandb sync`` uploads later). The ids are kept in the state, so a resume continues each
    member's run (``resume="allow"``)."""

    name = "wandb"

    def __init__(self, out: Path, group: str, state: dict):
        quiet_offline_wandb()
        import wandb

        self._wandb = wandb
        self.out, self.group = out, group
        self.ids: dict[str, str] = state.setdefault("ids", {})
        self.runs: dict[str, Any] = {}

    def held_step(self, run: str) -> int:
        """The last step W&B's transaction logs hold of ``run`` (-1: none), which a killed session
        may have sent without it reaching them."""
        return last_history_step(self.out, self.ids[run]) if run in self.ids else -1

    def start(self, run: str, hparams: dict[str, Any]) -> None:
        run_id = self.ids.setdefault(run, f"{self.group}-{run}-{uuid.uuid4().hex[:8]}")
        self.runs[run] = self._wandb.init(
            project=os.environ.get("WANDB_PROJECT", "xrl-jax"), group=self.group, name=run, id=run_id,
            resume=None if _wandb_offline() else "allow",  # offline, W&B ignores it with a warning
            dir=str(self.out), config=hparams, reinit="create_new",
        )  # fmt: skip

    def log(self, run: str, step: int, values: dict[str, float]) -> None:
        self.runs[run].log(values, step=step)

    def flush(self) -> bool:
        return False  # W&B's service writes whole blocks; everything is on disk once a run finishes

    def close(self) -> None:
        for run in self.runs.values():
            run.finish()
        self.runs.clear()


_BACKENDS = {"tensorboard": TensorBoardTracker, "wandb": WandbTracker}
Row = tuple[int, str, dict]  # (step, kind: "metrics", "eval" or "iqm", scalar values)


def _record_row(kind: str, line: dict) -> Row:
    """A metrics or evaluation line as a tracker row; the training metrics are named by group already
    (``rollout/...``, ``train/...``, ``buffer/...``), the evaluations go under ``eval/``."""
    return line["step"], kind, scalar_values(line, "eval/" if kind == "eval" else "")


class TrackerMirror:
    """Sends a run folder's records to the chosen trackers (module docstring): a progress callback
    of :func:`xrl_jax.train.train`, called after every chunk with what the host loop wrote (an
    object with ``metrics`` and ``evaluations``, lists of ``(member, line)``); ``close()`` at the end
    of the session (also on a stop: nothing is lost, the next session sends the rest)."""

    def __init__(self, out: str | Path, cfg, names: Sequence[str], warn: Callable[[str], None] = print):
        self.out, self.cfg, self.names, self.warn = Path(out), cfg, tuple(names), warn
        self.state_path = run_paths(self.out)["trackers"]
        self.members = [member_stem(cfg, m) for m in range(cfg.num_members)]
        self.curves = ["iqm" if cfg.num_points == 1 else f"point_{p}_iqm" for p in range(cfg.num_points)]
        self.hparams = flatten_config(cfg.to_dict())
        self.trackers: dict[str, Any] = {}
        self.state: dict[str, Any] = {}
        self.sent: dict[str, dict[str, dict[str, int]]] = {}  # handed to the tracker in this session
        self.started: set[tuple[str, str]] = set()  # (tracker, run) started in this session
        self.held: dict[tuple[str, str], int] = {}  # (tracker, run): the last step on its disk
        self.evaluations: list[dict[int, dict]] = []  # per member, its evaluation rows by step
        self.opened = False

    # ---- the progress callback ------------------------------------------------------------------
    def __call__(self, progress) -> None:
        """Send one chunk's records (``progress.metrics``, ``progress.evaluations``)."""
        if not self.opened:
            self._open()  # the first call comes with the folder locked and its files written
        rows: dict[str, list[Row]] = {}
        for kind, records in (("metrics", progress.metrics), ("eval", progress.evaluations)):
            for member, line in records:
                rows.setdefault(self.members[member], []).append(_record_row(kind, line))
        for member, line in progress.evaluations:
            self.evaluations[member][line["step"]] = line
        steps = {line["step"] for _, line in progress.evaluations}
        for point, run in enumerate(self.curves):
            rows[run] = self._curve_rows(point, steps)
        self._send_everywhere(rows)

    def _open(self) -> None:
        """Start the trackers and send what the folder holds that they lack (its files, read once)."""
        self.opened = True
        self.state = json.loads(self.state_path.read_text()) if self.state_path.exists() else {}
        group = self.out.resolve().name
        for name in self.names:
            tracker_state = self.state.setdefault(name, {})
            self.sent[name] = copy.deepcopy(tracker_state.setdefault("sent", {}))
            try:
                self.trackers[name] = _BACKENDS[name](self.out, group, tracker_state)
            except Exception as err:  # a tracker must never end the run
                self._dropped(name, err)
        metrics = [read_rows(metrics_file(self.out, stem)) for stem in self.members]
        evaluations = [read_rows(eval_file(self.out, stem)) for stem in self.members]
        rows = {
            stem: [_record_row("metrics", r) for r in metrics[m]]
            + [_record_row("eval", r) for r in evaluations[m]]
            for m, stem in enumerate(self.members)
        }
        self.evaluations = [{r["step"]: r for r in member_rows} for member_rows in evaluations]
        for point, run in enumerate(self.curves):
            rows[run] = self._curve_rows(point, None)
        self._send_everywhere(rows)

    def _curve_rows(self, point: int, steps: set[int] | None) -> list[Row]:
        """The curve over the point's seeds at ``steps`` (None: every step) that all of them evaluated."""
        evaluations = [self.evaluations[m] for m in self.cfg.point_members(point)]
        if steps is not None:
            evaluations = [{s: rows[s] for s in steps if s in rows} for rows in evaluations]
        out = []
        for entry in curve_over_seeds(evaluations, self.cfg.env):
            values = {}
            for key, stats in entry.items():
                if key != "step":
                    values |= {f"iqm/{key}": stats["estimate"], f"iqm/{key}_ci_low": stats["low"],
                               f"iqm/{key}_ci_high": stats["high"]}  # fmt: skip
            out.append((entry["step"], "iqm", values))
        return out

    # ---- sending ----------------------------------------------------------------------------------
    def _send_everywhere(self, rows: dict[str, list[Row]]) -> None:
        """Send ``rows`` by run to every tracker; a failing tracker is dropped with a warning."""
        for name in list(self.trackers):
            try:
                for run, run_rows in rows.items():
                    self._send(name, run, run_rows)
                if self.trackers[name].flush():
                    self.state[name]["sent"] = copy.deepcopy(self.sent[name])
            except Exception as err:  # a tracker must never end the run
                self._dropped(name, err)
        self._save_state()

    def _send(self, tracker: str, run: str, rows: list[Row]) -> None:
        """Rows not sent yet, in step order (W&B ignores a step below its last)."""
        if not rows:
            return
        backend = self.trackers[tracker]
        sent = self.sent[tracker].setdefault(run, {})
        if (tracker, run) not in self.held:  # what a killed session sent that reached the tracker
            self.held[tracker, run] = backend.held_step(run)
        held = self.held[tracker, run]
        fresh = sorted((r for r in rows if r[0] > max(sent.get(r[1], -1), held)), key=lambda r: (r[0], r[1]))
        if not fresh:
            return
        if (tracker, run) not in self.started:
            backend.start(run, self._run_hparams(run))
            self.started.add((tracker, run))
        for step, kind, values in fresh:
            if values:
                backend.log(run, step, values)
            sent[kind] = step

    def _run_hparams(self, run: str) -> dict[str, Any]:
        if run in self.curves:
            point = self.curves.index(run)
            return self.hparams | self._point_values(point)
        point, seed = self.cfg.member_point_seed(self.members.index(run))
        return self.hparams | self._point_values(point) | {"seed": seed}

    def _point_values(self, point: int) -> dict[str, Any]:
        return {f"sweep.{name}": value for name, value in self.cfg.sweep_points[point].items()}

    def _save_state(self) -> None:
        write_atomic(self.state_path, json.dumps(self.state, indent=2, sort_keys=True) + "\n")

    # ---- failures and the end -----------------------------------------------------------------------
    def _dropped(self, name: str, err: Exception) -> None:
        self.warn(
            f"xrl-jax: the {name} tracker failed and is dropped ({type(err).__name__}: {err}); the "
            "run's files hold everything, and a later --resume with --log sends the rest"
        )
        if name in self.trackers:
            self._close(name, durable=False)

    def _close(self, name: str, durable: bool = True) -> None:
        tracker = self.trackers.pop(name)
        try:
            tracker.close()
        except Exception as err:
            self.warn(f"xrl-jax: closing the {name} tracker failed ({type(err).__name__}: {err})")
            return
        if durable:  # every step sent is on the tracker's disk now
            self.state[name]["sent"] = copy.deepcopy(self.sent[name])

    def close(self) -> None:
        """Finish every tracker run; what they received is then on disk and in ``trackers.json``."""
        if not self.opened:
            return
        for name in list(self.trackers):
            self._close(name)
        self._save_state()
