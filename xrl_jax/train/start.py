"""Starting a run as ``experiments/run.py`` asks for it: the configuration from the given options
(or from the folder a resume continues), the checks that need nothing written, a new results
folder, and the training itself. Every failure is an exception with a one-line message, raised
before anything is written when it can be.
"""

from __future__ import annotations

import datetime
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax

from xrl_jax import train as train_package
from xrl_jax.config import ConfigError, TrainConfig, parse_overrides, parse_sweep, resolve_config
from xrl_jax.runs.folder import (
    RunFolderError,
    disk_full_message,
    holds_results,
    is_disk_full,
    read_run_config,
    read_summary,
    run_paths,
)
from xrl_jax.runs.plots import plot_sweep
from xrl_jax.runs.trackers import check_trackers
from xrl_jax.tracks import cache_dir
from xrl_jax.train import cpu_devices, hosts
from xrl_jax.train.chunk import mesh_devices
from xrl_jax.train.loop import DiskFullError

# Options a resume compares with the stored run: (the option, the config field it sets).
COMPARED_OPTIONS = (
    ("env", "env"),
    ("algo", "algo"),
    ("preset", "preset"),
    ("seeds", "num_seeds"),
    ("steps", "total_steps"),
    ("sweep", "sweep"),
)


@dataclass(frozen=True)
class RunRequest:
    """What the command line asked for; None wherever an option was not given."""

    env: str | None = None
    algo: str | None = None
    seeds: int | None = None
    steps: int | None = None
    preset: str | None = None
    sets: list[str] | None = None  # --set KEY=VALUE items
    sweep: list[str] | None = None  # --sweep FIELD=V1,V2 items
    devices: int | None = None
    out: str | None = None
    resume: str | None = None
    baseline: str | None = None
    coordinator: str | None = None  # HOST:PORT of process 0 in a job of several processes
    num_processes: int | None = None
    process_id: int | None = None
    coordinator_timeout: float = 120.0  # seconds to wait for the coordinator and the other processes
    trackers: tuple[str, ...] = ()  # --log: mirrors of the records (xrl_jax.runs.trackers)

    def configures(self) -> bool:
        """Whether any option that shapes the configuration was given (a resume must match them)."""
        shaping = (self.env, self.algo, self.seeds, self.steps, self.preset, self.sets, self.sweep)
        return any(value is not None for value in shaping)


@dataclass(frozen=True)
class PreparedRun:
    """A run ready to train: its configuration, its folder (created, and writable), whether it
    continues the folder's run, the --baseline run's summary (None without one), and lines the user
    should read before it starts."""

    cfg: TrainConfig
    out: Path
    resume: bool
    baseline: dict | None
    trackers: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


class LostProcessError(RuntimeError):
    """Another process of the job died while this one trained; the message is one line. The process
    must end at once (:func:`~xrl_jax.train.hosts.leave_at_once`)."""


def join_job(request: RunRequest, on_stall: Callable[[str], None] | None = None) -> None:
    """Join a job of several processes when the request or the environment describes one (nothing
    otherwise); every check that can fail without the other processes comes first. Raises
    :class:`~xrl_jax.config.ConfigError` or :class:`~xrl_jax.train.hosts.CoordinatorError` (one
    line). ``on_stall`` ends the process in one line when the job does not assemble in time (see
    :func:`~xrl_jax.train.hosts.initialize`); the line says what to start again."""
    flags = (request.coordinator, request.num_processes, request.process_id)
    if all(value is None for value in flags) and not hosts.wanted():
        return
    if request.out is None and request.resume is None:
        raise ConfigError(
            "a run of several processes needs --out (or --resume): every process writes into the same folder"
        )
    if request.resume is None:
        again = "nothing was written, so the same command starts the run"
    else:
        resume = request.resume
        again = f"the run in {resume} is untouched: continue it with --resume {resume} on every process"
    stalled = None if on_stall is None else (lambda message: on_stall(f"{message}; {again}"))
    try:
        hosts.initialize(
            request.coordinator,
            request.num_processes,
            request.process_id,
            request.coordinator_timeout,
            stalled,
        )
    except hosts.CoordinatorError:
        raise
    except (RuntimeError, ValueError) as err:  # JAX's own checks of the job description
        raise hosts.CoordinatorError(f"cannot join the job: {_first_line(err)}") from None


def _first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__


def requested_config(request: RunRequest, base: dict | None = None) -> TrainConfig:
    """The resolved config; options not given come from ``base`` (a stored run's) or the defaults."""
    base = base or {}
    stored_sweep = tuple((name, tuple(values)) for name, values in base.get("sweep", ()))
    cfg = resolve_config(
        env=request.env or base.get("env", "tracking"),
        algo=request.algo or base.get("algo", "xsac"),
        preset=request.preset or base.get("preset", "paper"),
        num_seeds=request.seeds or base.get("num_seeds", 1),
        total_steps=request.steps,
        overrides=parse_overrides(request.sets or []),
        sweep=parse_sweep(request.sweep) if request.sweep else stored_sweep,
    )
    return cfg.replace(num_devices=request.devices) if request.devices else cfg


def resume_mismatches(request: RunRequest, stored: TrainConfig) -> list[str]:
    """The given options (and --set keys) whose values differ from the stored run's."""
    have = stored.to_dict()
    wanted = requested_config(request, have).to_dict()
    out = []
    for option, field in COMPARED_OPTIONS:
        if getattr(request, option) is not None and wanted[field] != have[field]:
            out.append(f"{field}: stored {have[field]!r}, given {wanted[field]!r}")
    for key in parse_overrides(request.sets or []):
        name = key.removeprefix("agent.")
        a, b = (have[name], wanted[name]) if name in have else (have["agent"][name], wanted["agent"][name])
        if a != b:
            out.append(f"{name}: stored {a!r}, given {b!r}")
    return out


def _baseline(request: RunRequest, cfg: TrainConfig) -> tuple[dict | None, str | None]:
    """The --baseline run's summary (None without --baseline), or why it cannot be drawn."""
    if request.baseline is None:
        return None, None
    if cfg.num_points == 1:
        return None, "--baseline draws a line in a sweep's figure; give it with --sweep"
    try:
        baseline = read_summary(request.baseline)
    except RunFolderError as err:
        return None, f"--baseline {request.baseline}: {err}"
    if baseline.get("env") != cfg.env or not baseline.get("aggregate"):
        return None, f"--baseline {request.baseline}: not a finished {cfg.env} run without a sweep"
    return baseline, None


def _split_cpu_host(cfg: TrainConfig, new_run: bool, notes: list[str]) -> TrainConfig:
    """Split a CPU host into XLA devices before JAX's backend starts (:mod:`~xrl_jax.train.cpu_devices`):
    as many as the run's ``num_devices`` (given, or stored by the run a resume continues), or, for a
    new run of one process that leaves it at 0, as many as the measured rule gives. A new run on a
    CPU writes the count it got into its config, so that its resumes split the host alike; an older
    run's 0 keeps the devices it had; on an accelerator the run spreads over all of them as before."""
    if cfg.num_devices:
        if cpu_devices.split_cpu_host(cfg.num_devices) or new_run or jax.default_backend() != "cpu":
            return cfg
        have = len(jax.local_devices())
        if have < cfg.num_devices:  # a resume in a process whose backend runs already (a notebook)
            notes.append(
                f"the run was split over {cfg.num_devices} CPU devices and this process has {have} "
                f"(its JAX backend had started): it continues on {have}, whose numbers may differ from "
                "an uninterrupted run's in the last bits"
            )
            return cfg.replace(num_devices=have)
        return cfg
    if not new_run or jax.distributed.is_initialized():
        return cfg
    rule = cpu_devices.auto_cpu_devices(cfg, cpu_devices.cpu_cores())
    cpu_devices.split_cpu_host(rule)
    if jax.default_backend() == "cpu":
        # Split now, by run.py before, or by the user's XLA_FLAGS (whose count stands); a process that
        # runs several configurations (paper.py) splits for the one that wants most: this one takes
        # the rule's count of those.
        have = len(jax.local_devices())
        return cfg.replace(num_devices=have if cpu_devices.flagged_host_devices() else min(rule, have))
    return cfg


def _devices_problem(cfg: TrainConfig) -> str | None:
    try:
        mesh_devices(cfg.num_devices)
    except ValueError as err:
        return str(err)
    return None


def _new_folder(request: RunRequest, cfg: TrainConfig, results_root: Path) -> Path:
    """The folder of a new run (``--out``, or a time-stamped one under ``results_root``), created and
    checked writable; one that holds results already is refused."""
    out = (
        Path(request.out)
        if request.out
        else results_root
        / f"{cfg.env}-{cfg.algo}-{datetime.datetime.now(datetime.timezone.utc):%Y%m%d-%H%M%S}"
    )
    if out.exists() and (not out.is_dir() or holds_results(out)):
        raise RunFolderError(
            f"results folder {out} already exists; choose another --out or continue it with --resume {out}"
        )
    # Every process of a job looks before any of them writes: one that looked late could otherwise find
    # a faster one's first files (e.g. its write probe, below) and refuse the job's own folder.
    hosts.sync("new results folder checked")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write_test.{jax.process_index()}"
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        if is_disk_full(err):
            raise DiskFullError(disk_full_message(out, False, err)) from None
        raise RunFolderError(f"cannot write the results folder --out {out}: {err.strerror or err}") from None
    return out


def prepare_run(request: RunRequest, results_root: Path) -> PreparedRun:
    """Check the request and make its folder: the stored run's config on a resume (the given options
    must match it), else the one the options describe; the --baseline run and the devices are
    checked before anything is written. Raises :class:`~xrl_jax.config.ConfigError` or
    :class:`~xrl_jax.runs.folder.RunFolderError` (bad input), :class:`DiskFullError` (no room for
    the new folder), each with a one-line message."""
    if request.resume is not None:
        if request.out is not None:
            raise ConfigError("--out and --resume exclude each other (a resumed run writes into DIR)")
        out = Path(request.resume)
        try:
            stored = read_run_config(out)
        except RunFolderError as err:
            raise RunFolderError(f"--resume {out}: {err}") from None
        if request.configures():
            diffs = resume_mismatches(request, stored)
            if diffs:
                raise ConfigError(
                    f"--resume {out} holds a run with another configuration ({'; '.join(diffs)})"
                )
        cfg = stored.replace(num_devices=request.devices) if request.devices else stored
    else:
        cfg = requested_config(request)
    check_trackers(request.trackers)
    notes: list[str] = []
    cfg = _split_cpu_host(cfg, request.resume is None, notes)
    baseline, problem = _baseline(request, cfg)
    problem = _devices_problem(cfg) or problem
    if problem:  # before anything is written
        raise ConfigError(problem)
    if request.resume is None:
        out = _new_folder(request, cfg, results_root)
    return PreparedRun(cfg, out, request.resume is not None, baseline, tuple(request.trackers), tuple(notes))


def train_prepared(run: PreparedRun, **train_options: Any) -> dict[str, Any] | None:
    """Train the prepared run (:func:`~xrl_jax.train.loop.train` with ``train_options``) and draw the
    --baseline run into a sweep's figure; returns the summary (None when stopped early)."""
    try:
        # looked up at the call, so tests may wrap train()
        summary = train_package.train(run.cfg, run.out, resume=run.resume, **train_options)
    except Exception as err:  # a collective that failed because another process of the job died
        if not hosts.lost_a_process(err):
            raise
        raise LostProcessError(
            f"process {jax.process_index()} of {jax.process_count()} lost another process of the job "
            f"({_first_line(err)}); the committed checkpoints in {run.out} are kept: start every process "
            f"again with --resume {run.out}"
        ) from None
    if summary is not None and hosts.is_primary() and run.baseline is not None and summary.get("sweep"):
        plot_sweep(summary, run_paths(run.out)["sweep"], run.baseline)
    return summary


def enable_compilation_cache() -> None:
    """Reuse compiled chunks across runs of the same configuration (a minute of compile on CPU), in
    ``XRL_JAX_CACHE_DIR/jax``; where JAX's own cache is already set (``JAX_COMPILATION_CACHE_DIR``),
    that one as it is (the tests share one cache among all their processes so)."""
    if jax.config.jax_compilation_cache_dir:
        return
    path = cache_dir() / "jax"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
