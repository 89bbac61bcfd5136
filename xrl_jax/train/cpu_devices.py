"""How many XLA devices a CPU host is split into, so that a run uses every core by default.

XLA's CPU backend runs most element-wise kernels of one device on one thread, so a run on one CPU
device leaves the other cores mostly idle. Split into several host devices, the members of a run
(seeds x sweep points) spread over them as over GPUs (:func:`~xrl_jax.train.chunk.mesh_devices`),
each device running its block of members on its own core. The rule and the measurements it rests
on: docs/performance.md, "Every core by default".

The split must be chosen before JAX starts its backend (``jax_num_cpu_devices``); the count a run
used is written into its config (``num_devices``), so that a resume splits the host the same way and
its members keep their numbers bit for bit.
"""

from __future__ import annotations

import os
import re

import jax

from xrl_jax.config import TrainConfig

HOST_DEVICE_FLAG = "xla_force_host_platform_device_count"


def cpu_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a container's or a job's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def members_at_once(cfg: TrainConfig) -> int:
    """The members one program trains together: all of them, or ``max_group_size`` at most (the
    memory planner may still make the groups smaller on a small machine)."""
    if cfg.max_group_size:
        return min(cfg.num_members, cfg.max_group_size)
    return cfg.num_members


def auto_cpu_devices(cfg: TrainConfig, cores: int) -> int:
    """The CPU devices for ``cfg`` on ``cores`` cores (:func:`devices_for_members`, with the scenario
    kind's devices per core)."""
    from xrl_jax.train.kinds import scenario_kind

    return devices_for_members(members_at_once(cfg), cores, scenario_kind(cfg).cpu_devices_per_core)


def most_cpu_devices(cores: int) -> int:
    """The most CPU devices any run takes on ``cores`` cores (the scenario kind with the most per
    core): a process that trains several configurations (``paper.py``) splits its host so once."""
    from xrl_jax.train.kinds import KINDS

    return max(cores, 1) * max(kind.cpu_devices_per_core for kind in KINDS.values())


def devices_for_members(members: int, cores: int, per_core: int = 1) -> int:
    """``per_core`` devices per core, as many as ``members`` trained together fill evenly (a device of
    padding repeats a member's work: it would cost a core's time for nothing), never more than the
    members. Racing members gain from sharing a device (2 per device beat 1: 350 against 324
    env-steps/s for 4 Tracking XDSAC seeds on 2 cores); the Intersection's members wait for each
    other's vehicles in a device, and one device each beat two per device (248 against 172)."""
    slots = max(cores, 1) * max(per_core, 1)
    return max(d for d in range(1, min(slots, max(members, 1)) + 1) if members % d == 0)


def flagged_host_devices() -> int | None:
    """The host device count ``XLA_FLAGS`` sets (``--xla_force_host_platform_device_count``), if any."""
    found = re.search(rf"--{HOST_DEVICE_FLAG}=(\d+)", os.environ.get("XLA_FLAGS", ""))
    return int(found.group(1)) if found else None


# The devices of a split host meet in a chunk's two collectives (xrl_jax.train.chunk), where one device
# may arrive later than another by its members' extra work (on the Intersection, their cars). XLA
# aborts the process when that takes 40 s (and warns after 20 s); a chunk of long runs can differ by
# more, so the wait is half an hour, which still ends a process that would otherwise wait forever.
PATIENT_COLLECTIVES = {
    "xla_cpu_collective_call_terminate_timeout_seconds": 1_800,
    "xla_cpu_collective_call_warn_stuck_timeout_seconds": 600,
}


def split_cpu_host(count: int) -> bool:
    """Ask JAX for ``count`` CPU devices (it makes them when its backend starts; on a machine with an
    accelerator the CPU devices go unused), with patient collectives. Returns False when that is no
    longer possible (the backend has started) or the user's ``XLA_FLAGS`` chose a count already,
    which then stands."""
    flagged = flagged_host_devices()
    if max(count, flagged or 0) > 1:
        patient_collectives()
    if flagged is not None:
        return False
    try:
        jax.config.update("jax_num_cpu_devices", int(count))
    except RuntimeError:  # the backend runs already: its devices are what they are
        return False
    global _SPLIT
    _SPLIT = int(count) > 1
    return True


_SPLIT = False  # whether this process asked for several CPU devices (end_process)


def patient_collectives() -> None:
    """Add :data:`PATIENT_COLLECTIVES` to ``XLA_FLAGS`` where the user set none of them (XLA reads
    the variable when its backend starts)."""
    flags = os.environ.get("XLA_FLAGS", "")
    extra = [f"--{name}={value}" for name, value in PATIENT_COLLECTIVES.items() if name not in flags]
    os.environ["XLA_FLAGS"] = " ".join([flags, *extra]).strip()


def end_process(status: int) -> None:
    """End a script's process with ``status`` at once (standard streams flushed) where it split its
    CPU host (:func:`split_cpu_host`) and is the job's only process: tearing down a split host's XLA
    client at interpreter exit sometimes waited forever (1 exit in ~10 on XLA:CPU, JAX 0.10); with
    nothing left to write, skipping the teardown loses nothing. Elsewhere an ordinary exit."""
    import sys

    if _SPLIT and jax.process_count() == 1 and jax.default_backend() == "cpu":
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)
