"""TensorBoard and Weights & Biases mirrors of a run folder (``run.py --log tensorboard|wandb``).

The folder's JSON-lines files stay the source of truth: a tracker only ever receives what they hold,
read back after every chunk. So a tracker cannot show what the folder does not, and a resumed run, or
a later ``--resume`` with ``--log`` that the first session did not have, sends exactly what the tracker
has not received yet: ``trackers.json`` remembers, per tracker and member, the last step sent, and the
W&B run ids, which a resume reuses so that each member's W&B run continues rather than starts anew.

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

import json
import os
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from xrl_jax.config import ConfigError
from xrl_jax.runs.folder import eval_file, member_stem, metrics_file, read_rows, run_paths, write_atomic
from xrl_jax.runs.summary import learning_curve

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

    def flush(self) -> None:
        for writer in self.writers.values():
            writer.flush()

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
        self.writers.clear()


class WandbTracker:
    """One W&B run per member in the project ``$WANDB_PROJECT`` (default ``xrl-jax``), grouped by the
    run folder's name, its files under ``<folder>/wandb/``. ``WANDB_MODE=offline`` works without a
    network (``wandb sync`` uploads later). The ids are kept in the state, so a resume continues each
    member's run (``resume="allow"``)."""

    name = "wandb"

    def __init__(self, out: Path, group: str, state: dict):
        import wandb

        self._wandb = wandb
        self.out, self.group = out, group
        self.ids: dict[str, str] = state.setdefault("ids", {})
        self.runs: dict[str, Any] = {}

    def start(self, run: str, hparams: dict[str, Any]) -> None:
        run_id = self.ids.setdefault(run, f"{self.group}-{run}-{uuid.uuid4().hex[:8]}")
        self.runs[run] = self._wandb.init(
            project=os.environ.get("WANDB_PROJECT", "xrl-jax"), group=self.group, name=run, id=run_id,
            resume="allow", dir=str(self.out), config=hparams, reinit="create_new",
        )  # fmt: skip

    def log(self, run: str, step: int, values: dict[str, float]) -> None:
        self.runs[run].log(values, step=step)

    def flush(self) -> None:
        pass  # W&B writes its transaction log as it goes

    def close(self) -> None:
        for run in self.runs.values():
            run.finish()
        self.runs.clear()


_BACKENDS = {"tensorboard": TensorBoardTracker, "wandb": WandbTracker}


class TrackerMirror:
    """Sends a run folder's records to the chosen trackers (module docstring). ``sync()`` after every
    chunk, ``close()`` at the end (or on a stop: nothing is lost, the next session sends the rest)."""

    def __init__(self, out: str | Path, cfg, names: Sequence[str], warn: Callable[[str], None] = print):
        self.out, self.cfg, self.warn = Path(out), cfg, warn
        self.state_path = run_paths(self.out)["trackers"]
        self.state = json.loads(self.state_path.read_text()) if self.state_path.exists() else {}
        self.group = self.out.resolve().name
        self.trackers = {}
        for name in names:
            tracker_state = self.state.setdefault(name, {})
            self.trackers[name] = _BACKENDS[name](self.out, self.group, tracker_state)
        self.members = [member_stem(cfg, m) for m in range(cfg.num_members)]
        self.curves = ["iqm" if cfg.num_points == 1 else f"point_{p}_iqm" for p in range(cfg.num_points)]
        self.started: set[tuple[str, str]] = set()
        config = run_paths(self.out)["config"]
        self.hparams = flatten_config(json.loads(config.read_text())["config"]) if config.exists() else {}

    def _sent(self, tracker: str, run: str) -> dict[str, int]:
        return self.state[tracker].setdefault("sent", {}).setdefault(run, {})

    def _send(self, tracker: str, run: str, rows: list[tuple[int, str, dict]], hparams: dict) -> None:
        """Rows ``(step, kind, values)`` not sent yet, in step order (W&B ignores a step below its last)."""
        sent = self._sent(tracker, run)
        fresh = sorted((r for r in rows if r[0] > sent.get(r[1], -1)), key=lambda r: (r[0], r[1]))
        if not fresh:
            return
        backend = self.trackers[tracker]
        if (tracker, run) not in self.started:
            backend.start(run, hparams)
            self.started.add((tracker, run))
        for step, kind, values in fresh:
            if values:
                backend.log(run, step, values)
            sent[kind] = step

    def _member_rows(self, stem: str) -> list[tuple[int, str, dict]]:
        rows = []
        # The training metrics are named by group already (rollout/..., train/..., buffer/...).
        for kind, path, prefix in (("metrics", metrics_file, ""), ("eval", eval_file, "eval/")):
            rows += [(r["step"], kind, scalar_values(r, prefix)) for r in read_rows(path(self.out, stem))]
        return rows

    def _curve_rows(self, point: int) -> list[tuple[int, str, dict]]:
        rows = []
        for entry in learning_curve(self.out, self.cfg, point):
            values = {}
            for key, stats in entry.items():
                if key != "step":
                    values |= {f"iqm/{key}": stats["estimate"], f"iqm/{key}_ci_low": stats["low"],
                               f"iqm/{key}_ci_high": stats["high"]}  # fmt: skip
            rows.append((entry["step"], "iqm", values))
        return rows

    def _member_hparams(self, member: int) -> dict[str, Any]:
        point, seed = self.cfg.member_point_seed(member)
        return self.hparams | self._point_values(point) | {"seed": seed}

    def _point_values(self, point: int) -> dict[str, Any]:
        return {f"sweep.{name}": value for name, value in self.cfg.sweep_points[point].items()}

    def sync(self) -> None:
        """Send every record the trackers have not received; a failing tracker is dropped with a warning."""
        if not self.trackers:
            return
        member_rows = {stem: self._member_rows(stem) for stem in self.members}
        curve_rows = {run: self._curve_rows(point) for point, run in enumerate(self.curves)}
        for name in list(self.trackers):
            try:
                for member, stem in enumerate(self.members):
                    self._send(name, stem, member_rows[stem], self._member_hparams(member))
                for point, run in enumerate(self.curves):
                    self._send(name, run, curve_rows[run], self.hparams | self._point_values(point))
                self.trackers[name].flush()
            except Exception as err:  # a tracker must never end the run
                self.warn(
                    f"xrl-jax: the {name} tracker failed and is dropped ({type(err).__name__}: {err}); the "
                    "run's files hold everything, and a later --resume with --log sends the rest"
                )
                self._close(name)
        write_atomic(self.state_path, json.dumps(self.state, indent=2, sort_keys=True) + "\n")

    def _close(self, name: str) -> None:
        tracker = self.trackers.pop(name)
        try:
            tracker.close()
        except Exception as err:
            self.warn(f"xrl-jax: closing the {name} tracker failed ({type(err).__name__}: {err})")

    def close(self) -> None:
        for name in list(self.trackers):
            self._close(name)
