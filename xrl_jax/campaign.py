"""The paper's whole protocol as one resumable campaign (``experiments/paper.py``): its runs, what
they cost, running them one after another, and the report over them.

Runs, one results folder each: every env x agent (Fig. 5-7), the kappa sweep of Fig. 8 (discrete
Country Road) and the Table I variants (XSAC on Country Road with its mixture weights from hidden
layer 1 and 2; layer 3 is the main XSAC run). A finished run is skipped and a started one resumed,
so the same campaign continues where it stopped. It sits above the trainer (memory plans) and the
report.
"""

from __future__ import annotations

import fnmatch
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from xrl_jax.config import ALGOS, ENVS, ConfigError, parse_overrides, parse_sweep, resolve_config

KAPPAS = "-0.01,-0.001,0,0.001,0.01,0.1"
# Device throughput for the estimate, in FLOP/s the update achieves. The CPU's is measured, so it lives
# with its measurement in a data file (cpu_flops). An H100 SXM: 67 TFLOP/s float32 on its datasheet, of
# which these small networks reach a fraction: --utilisation.
MEASURED_RATES = Path(__file__).resolve().parent / "benchmarks" / "measured_rates.json"  # package data
H100_FLOPS = 67e12
STOPPED_BY_SIGNAL = (130, 143)  # run.py's statuses after SIGINT / SIGTERM
BAD_INPUT = 2  # run.py's status for a request it refuses: the campaign's others would be refused too


def cpu_flops() -> float:
    """The update FLOP/s of the CPU that the plan's CPU hours assume (``measured_rates.json``, which
    says how it was measured: docs/benchmarks.md)."""
    return float(json.loads(MEASURED_RATES.read_text())["cpu_update_flop_per_s"]["value"])


@dataclass(frozen=True)
class PlannedRun:
    name: str
    env: str
    algo: str
    sets: tuple[str, ...] = ()
    sweep: tuple[str, ...] = ()
    figure: str = ""

    def args(self, preset: str, seeds: int) -> list[str]:
        """The run's options for ``experiments/run.py``."""
        out = ["--env", self.env, "--algo", self.algo, "--preset", preset, "--seeds", str(seeds)]
        for item in self.sets:
            out += ["--set", item]
        for item in self.sweep:
            out += ["--sweep", item]
        return out


def campaign() -> list[PlannedRun]:
    """Every run of the paper's protocol, in the order they run."""
    runs = [
        PlannedRun(
            f"{env}-{algo}",
            env,
            algo,
            figure={"country_road": "Fig. 5", "tracking": "Fig. 6", "intersection": "Fig. 7"}[env],
        )
        for env in ENVS
        for algo in ALGOS
    ]
    runs.append(
        PlannedRun(
            "country_road-xdsac-kappa", "country_road", "xdsac", sweep=(f"kappa={KAPPAS}",), figure="Fig. 8"
        )
    )
    for depth in (1, 2):
        runs.append(
            PlannedRun(
                f"country_road-xsac-weights{depth}",
                "country_road",
                "xsac",
                sets=(f"weight_depth={depth}",),
                figure="Table I",
            )
        )
    return runs


def select_runs(patterns: list[str] | None) -> list[PlannedRun]:
    """The campaign's runs whose names match one of the shell-style ``patterns`` (all without any);
    :class:`~xrl_jax.config.ConfigError` when none does."""
    runs = campaign()
    if not patterns:
        return runs
    chosen = [r for r in runs if any(fnmatch.fnmatchcase(r.name, pattern) for pattern in patterns)]
    if not chosen:
        names = ", ".join(r.name for r in runs)
        raise ConfigError(f"--only {' '.join(patterns)} matches no run; runs: {names}")
    return chosen


def run_status(folder: Path) -> str:
    """ "done" (a complete summary), "started" (a config, so --resume continues it) or "new"."""
    from xrl_jax.runs.folder import has_config, is_complete  # xrl_jax.runs imports jax: not for --help

    if is_complete(folder):
        return "done"
    return "started" if has_config(folder) else "new"


def member_steps_done(folder: Path, cfg) -> list[int]:
    """Per member, the step its group's newest checkpoint holds: where a resume continues (0 without
    one)."""
    from xrl_jax.checkpoint import latest_step
    from xrl_jax.runs.folder import checkpoint_dir, read_checkpoint_plan

    groups, _ = read_checkpoint_plan(folder, cfg.num_members)
    done = [0] * cfg.num_members
    for index, group in enumerate(groups):
        step = latest_step(checkpoint_dir(folder, index)) or 0
        for member in group:
            done[member] = step
    return done


def new_run_config(run: PlannedRun, preset: str, seeds: int, sets: tuple[str, ...] | list[str] = ()):
    """The :class:`~xrl_jax.config.TrainConfig` that starting ``run`` gives: the preset, ``seeds``,
    the run's own settings and the campaign's ``sets``."""
    return resolve_config(
        run.env,
        run.algo,
        preset,
        num_seeds=seeds,
        overrides=parse_overrides([*run.sets, *sets]),
        sweep=parse_sweep(list(run.sweep)),
    )


def check_sets(runs: list[PlannedRun], sets: list[str], preset: str, seeds: int) -> None:
    """Raise :class:`~xrl_jax.config.ConfigError` when the ``--set`` items cannot reach the runs (one
    malformed, a setting given twice, one that a run sets itself, or a value a run's config refuses):
    checked before the first run starts rather than when a later run refuses them and ends the
    campaign halfway."""
    parse_overrides(sets)
    for planned in runs:
        try:
            parse_overrides([*planned.sets, *sets])
        except ConfigError as err:
            raise ConfigError(f"{planned.name} sets this itself: {err}") from None
        try:
            new_run_config(planned, preset, seeds, sets)
        except ConfigError as err:
            raise ConfigError(f"{planned.name}: {err}") from None


@dataclass(frozen=True)
class _Planned:
    """A run of the plan as it would run: its configuration, what its checkpoints hold, its devices
    and member groups."""

    run: PlannedRun
    status: str
    cfg: object  # TrainConfig
    done: list[int]  # per member, the steps its group's newest checkpoint holds
    devices: int
    memory: dict
    agent: object  # the run's Agent, for its FLOPs

    @property
    def members_per_device(self) -> int:
        from xrl_jax.train.calibrations import members_per_device

        return members_per_device(self.memory["groups"], self.devices)

    def groups_done(self, left: bool) -> list[int]:
        """Per member group, the steps done: what its checkpoints hold (``left``), or none."""
        return [min(self.done[m] for m in group) if left else 0 for group in self.memory["groups"]]


def _prepare(run: PlannedRun, out: Path, preset: str, seeds: int, sets: tuple[str, ...]) -> _Planned:
    from xrl_jax.runs.folder import read_run_config
    from xrl_jax.train import get_trainer, plan_memory
    from xrl_jax.train.calibrations import run_devices
    from xrl_jax.train.chunk import mesh_devices

    status = run_status(out / run.name)
    # A started run resumes as it was started: neither --preset, --seeds nor --set reach it.
    cfg = new_run_config(run, preset, seeds, sets) if status == "new" else read_run_config(out / run.name)
    devices = run_devices(cfg, new_run=status == "new")
    trainer = get_trainer(cfg, devices=mesh_devices(devices))
    memory = plan_memory(trainer, cfg)
    if status == "started":
        done = member_steps_done(out / run.name, cfg)
    else:  # a finished run counts as done whatever its checkpoints hold
        done = [cfg.total_steps if status == "done" else 0] * cfg.num_members
    return _Planned(run, status, cfg, done, devices, memory, trainer.agent)


def plan(
    runs: list[PlannedRun],
    out: Path,
    preset: str,
    seeds: int,
    utilisation: float,
    sets: tuple[str, ...] = (),
    calibrate: Callable | None = None,
    say: Callable[[str], None] = lambda message: None,
) -> list[dict]:
    """One row per run: its status, members, memory and groups on this machine, FLOPs and device-hours,
    each for the configuration that will run: a started or finished run's own (``config.json``), a new
    one's from the preset, its own settings and the campaign's ``sets``.

    The CPU hours are this machine's calibrations (:mod:`xrl_jax.train.calibrations`): cached ones,
    and those ``calibrate(cfg, members_per_device, devices) -> record`` measures now (told through
    ``say`` first: how many, and about how long); without ``calibrate``, or where it fails, the FLOP
    model (the update's FLOPs at ``measured_rates.json``'s rate). The H100 hours are the FLOP model's."""
    prepared = [_prepare(run, out, preset, seeds, sets) for run in runs]
    rates = {} if calibrate is None else calibrated_rates(prepared, calibrate, say)
    return [_row(p, utilisation, rates.get(p.run.name)) for p in prepared]


def _row(p: _Planned, utilisation: float, rate: tuple[dict, str] | None) -> dict:
    from xrl_jax.benchmarks.occupancy import load_occupancy, update_cost
    from xrl_jax.resources import format_bytes
    from xrl_jax.train import scenario_kind
    from xrl_jax.train.calibrations import predicted_seconds

    cfg, occupancy, cpu = p.cfg, load_occupancy(), cpu_flops()
    # FLOPs as they run: the packed update, or every slot when a batch overflows (by the measured
    # occupancy of xrl_jax/benchmarks/set_occupancy.json, members sharing their branches as on one
    # device).
    cost = update_cost(p.agent, cfg.batch_size, cfg.num_members, occupancy)
    flops = cost["expected"]
    # A member updates after each step past the warm-up.
    updates = max(cfg.total_steps - cfg.warmup_steps, 0) * cfg.num_members
    updates_left = sum(max(cfg.total_steps - max(step, cfg.warmup_steps), 0) for step in p.done)
    # On the Intersection one update per acting vehicle: as many as measured per env step under
    # the scripted driver, which stands for training (after the warm-up a learning policy keeps
    # its cars on the road as it does; random drivers lose theirs sooner and act less):
    # set_occupancy.json keeps both, docs/performance.md "How full the sets are" says why.
    per_step = scenario_kind(cfg).updates_per_env_step(cfg, occupancy)
    total, left = flops * per_step * updates, flops * per_step * updates_left
    row = {
        "run": p.run.name,
        "figure": p.run.figure,
        "status": p.status,
        "members": cfg.num_members,
        "steps": cfg.total_steps,
        "memory_per_member": format_bytes(p.memory["per_seed_bytes"]["total"]),
        "groups": len(p.memory["groups"]),
        "devices": p.devices,
        "members_per_device": p.members_per_device,
        "gflop_per_update": flops / 1e9,
        "dense_gflop_per_update": cost["dense"] / 1e9,
        "fallback_probability": cost["fallback_probability"],
        "progress": sum(p.done) / (cfg.total_steps * cfg.num_members),
        "pflop_total": total / 1e15,
        "flop_cpu_hours": total / cpu / 3600,
        "flop_cpu_hours_left": left / cpu / 3600,
        "h100_hours": total / (H100_FLOPS * utilisation) / 3600,
        "h100_hours_left": left / (H100_FLOPS * utilisation) / 3600,
        "cpu_source": "FLOP",
    }
    row["cpu_hours"], row["cpu_hours_left"] = row["flop_cpu_hours"], row["flop_cpu_hours_left"]
    if rate is not None:
        record, source = rate
        whole = predicted_seconds(cfg, record, p.groups_done(left=False))
        rest = predicted_seconds(cfg, record, p.groups_done(left=True))
        row.update(cpu_source=source, cpu_hours=whole["total_s"] / 3600)
        row["cpu_hours_left"] = rest["total_s"] / 3600
        row["calibrated_s"] = whole
    return row


def calibrated_rates(prepared: list[_Planned], calibrate: Callable, say: Callable[[str], None]) -> dict:
    """Per run name, ``(record, "cached" | "measured")``: the cached calibration of its configuration
    on this machine, or one measured now with ``calibrate`` (and cached); runs of one configuration
    share one. A calibration that fails is told, and leaves its runs to the FLOP model."""
    from xrl_jax.benchmarks.calibration import CalibrationError
    from xrl_jax.resources import format_duration
    from xrl_jax.train import calibrations

    found, missing = {}, {}
    for p in prepared:
        key = calibrations.calibration_key(p.cfg, p.members_per_device, p.devices)
        record = calibrations.load_calibration(key, warn=say)
        if record is not None:
            found[p.run.name] = (record, "cached")
        else:
            missing.setdefault(json.dumps(key, sort_keys=True), (key, []))[1].append(p)
    if not missing:
        return found
    each, basis = typical_calibration_s()
    say(
        f"{len(missing)} configuration(s) have no calibration on this machine; measuring them takes "
        f"~{format_duration(each * len(missing))} (~{each:.0f} s each, {basis}; more members and wider "
        "networks take longer); --no-calibrate estimates from FLOPs instead"
    )
    for index, (key, group) in enumerate(missing.values()):
        names, first = ", ".join(p.run.name for p in group), group[0]
        tic = time.perf_counter()
        try:
            record = calibrate(first.cfg, first.members_per_device, first.devices)
        except (CalibrationError, OSError) as err:
            say(f"calibrating {names} failed ({err}); its CPU hours come from the FLOP model")
            continue
        record = dict(record, calibration_s=time.perf_counter() - tic)  # as long as the plan waited
        calibrations.store_calibration(key, record)
        others = record.get("others_cpu_share") or 0.0
        busy = (
            f"; other processes took {others:.0%} of the CPUs meanwhile: slow rates" if others > 0.2 else ""
        )
        say(
            f"calibrated {names} ({first.members_per_device} member(s) per device on {first.devices} "
            f"device(s)) in {record['calibration_s']:.0f} s ({index + 1}/{len(missing)}){busy}"
        )
        found.update({p.run.name: (record, "measured") for p in group})
    return found


def typical_calibration_s() -> tuple[float, str]:
    """How long a calibration takes here, and on what that rests: the median of this machine's cached
    calibrations, or without any the one measured in ``measured_rates.json``."""
    from xrl_jax.train.calibrations import cached_calibrations

    seconds = sorted(r.get("calibration_s", 0.0) for r in cached_calibrations())
    if seconds:
        return seconds[len(seconds) // 2], f"the median of this machine's {len(seconds)} calibration(s)"
    measured = json.loads(MEASURED_RATES.read_text())["calibration_s"]
    return float(measured["value"]), measured["basis"]


SOURCES = {"cached": "cached calibration", "measured": "calibrated now", "FLOP": "FLOP model"}


def hours(value: float) -> str:
    """Hours with two significant digits below 10 (a quick run's 0.15 h is not 0.1), whole above."""
    return f"{value:,.0f}" if value >= 10 else f"{value:.2g}" if value >= 0.01 else f"{value:.1g}"


def format_plan(rows: list[dict], utilisation: float) -> list[str]:
    """The plan as a table (each run's whole cost, and how much of it its checkpoints already hold,
    with where its CPU hours come from), and the device-hours of what is still to run."""
    lines = [
        f"{'run':<30} {'for':<8} {'status':<8} {'done':>5} {'members':>7} {'memory/member':>13} "
        f"{'groups':>6} {'devices':>7} {'GFLOP/upd':>9} {'dense':>7} {'CPU h':>10} {'CPU from':<9} "
        f"{'H100 h':>8}"
    ]
    for r in rows:
        lines.append(
            f"{r['run']:<30} {r['figure']:<8} {r['status']:<8} {r['progress']:>5.0%} {r['members']:>7} "
            f"{r['memory_per_member']:>13} {r['groups']:>6} {r['devices']:>7} {r['gflop_per_update']:>9.3g} "
            f"{r['dense_gflop_per_update']:>7.3g} {hours(r['cpu_hours']):>10} {r['cpu_source']:<9} "
            f"{r['h100_hours']:>8,.2f}"
        )
    cpu, h100 = sum(r["cpu_hours_left"] for r in rows), sum(r["h100_hours_left"] for r in rows)
    counts = {source: sum(r["cpu_source"] == source for r in rows) for source in SOURCES}
    sources = ", ".join(f"{n} by {SOURCES[source]}" for source, n in counts.items() if n)
    lines.append(
        f"total still to run: {hours(cpu)} CPU hours on this machine ({sources}), {h100:,.1f} H100 hours "
        f"at {utilisation:.0%} of {H100_FLOPS / 1e12:.0f} TFLOP/s (FLOP model)"
    )
    if counts["FLOP"]:
        lines.append(
            f"FLOP model: the updates' FLOPs at {cpu_flops() / 1e9:.0f} GFLOP/s on a CPU "
            "(measured_rates.json), updates only; at the quick preset's widths a CPU reaches a fraction "
            "of that (docs/performance.md, Estimates that hold)"
        )
    if counts["cached"] + counts["measured"]:
        lines.append(
            "calibrated: this machine's measured seconds per vector step (updates included) and per "
            "evaluation, for each run's members per device; compilation once, checkpoints not counted"
        )
    return lines


@dataclass(frozen=True)
class CampaignSettings:
    """How the campaign's runs start: the preset, seeds per configuration, and ``--set`` items for
    every run it starts (resumed runs keep their own)."""

    preset: str = "paper"
    seeds: int = 20
    sets: tuple[str, ...] = ()
    controller: bool = True  # each scenario's yardstick in the report


def run_campaign(
    runs: list[PlannedRun],
    out: Path,
    settings: CampaignSettings,
    run_one: Callable[[list[str]], int],
    say: Callable[[str], None],
    show: Callable[[str], None],
    again: str,
) -> int:
    """Run ``runs`` into ``out`` one after another with ``run_one`` (run.py's ``main``: options in,
    exit status out), skipping finished ones and resuming started ones, then write the report over
    every started run into ``out/report``. ``say`` takes progress notes, ``show`` the report's path;
    ``again`` is the command that continues the campaign. Returns the exit status: a run's own when
    it was stopped by a signal or refused its options, 1 when a run did not finish, else 0."""
    from xrl_jax.benchmarks import table_one
    from xrl_jax.report import ReportError, write_report
    from xrl_jax.runs.folder import has_config

    out.mkdir(parents=True, exist_ok=True)
    failed = []
    for planned in runs:
        folder = out / planned.name
        status = run_status(folder)
        if status == "done":
            say(f"{planned.name}: done, skipped")
            continue
        if status == "started":
            argv = ["--resume", str(folder), "--quiet"]
        else:
            extra = [word for item in settings.sets for word in ("--set", item)]
            argv = [*planned.args(settings.preset, settings.seeds), *extra, "--out", str(folder), "--quiet"]
        say(f"{planned.name}: {'resuming' if status == 'started' else 'starting'}")
        code = run_one(argv)
        if code in STOPPED_BY_SIGNAL:  # the run kept its checkpoint; end the campaign
            say(f"stopped; continue with: {again}")
            return code
        if code == BAD_INPUT:
            return code
        if code != 0:
            failed.append(planned.name)
    folders = [out / r.name for r in runs if has_config(out / r.name)]
    try:
        report = write_report(
            folders, out / "report", controller=settings.controller, policy_costs=table_one.policy_costs
        )
    except ReportError as err:  # the runs are kept; only the report is missing
        say(f"the runs are kept, but the report failed: {err}")
        return 1
    show(f"report: {report}")
    if failed:
        say(f"these runs did not finish: {', '.join(failed)} (see their messages above)")
        return 1
    return 0
