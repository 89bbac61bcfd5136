"""What a run may use and what it will cost: memory (a container's limit included), disk, the
backend it runs on, and the estimate of its duration that the user sees before committing days.

Jax-free except :func:`backend_summary`, so the checks run before anything is compiled.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

UNLIMITED = 1 << 62  # cgroup v1 writes "no limit" as a huge number (9223372036854771712 here)
DAY_S = 86_400.0


def _read_number(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    if text == "max":
        return None
    try:
        value = int(text)
    except ValueError:
        return None
    return None if value >= UNLIMITED else value


def cgroup_memory_headroom(
    root: str | Path = "/sys/fs/cgroup", self_cgroup: str | Path = "/proc/self/cgroup"
) -> tuple[int, str] | None:
    """``(bytes, description)`` still free under the tightest memory limit of this process's
    control groups (v2 ``memory.max``/``memory.current``, v1 ``memory.limit_in_bytes``/
    ``memory.usage_in_bytes``), each ancestor included since limits nest; None without a limit.

    A container's limit is what the kernel enforces with the OOM killer, whatever the host has
    free, so the memory planner must budget against it."""
    root = Path(root)
    try:
        lines = Path(self_cgroup).read_text().splitlines()
    except OSError:
        return None
    candidates: list[tuple[Path, str, str]] = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, group = parts
        if controllers == "":  # cgroup v2, unified hierarchy
            base, limit_file, usage_file = root, "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            base, limit_file, usage_file = root / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes"
        else:
            continue
        relative = Path(group.lstrip("/"))
        levels = [relative, *relative.parents]  # the own group first, then every ancestor up to the root
        candidates += [(base / level, limit_file, usage_file) for level in levels]
    best = None
    for folder, limit_file, usage_file in candidates:
        limit = _read_number(folder / limit_file)
        if limit is None:
            continue
        usage = _read_number(folder / usage_file) or 0
        headroom = max(limit - usage, 0)
        if best is None or headroom < best[0]:
            best = (headroom, f"container memory limit {limit / 1e9:.1f} GB ({folder / limit_file})")
    return best


def host_memory_available() -> tuple[int, str]:
    """Bytes the host can give this process now: the smaller of free RAM and the cgroup headroom."""
    import psutil

    available = (int(psutil.virtual_memory().available), "available host RAM")
    limited = cgroup_memory_headroom()
    return min(available, limited) if limited is not None else available


def disk_free_bytes(folder: str | Path) -> int:
    return shutil.disk_usage(folder).free


def backend_summary() -> str:
    """One line naming the backend and its devices, e.g. ``cpu (2 cores: AMD EPYC)``."""
    import jax

    devices = jax.devices()
    backend = jax.default_backend()
    if backend == "cpu":
        return f"cpu ({os.cpu_count()} cores: {cpu_model()})"
    kinds = sorted({d.device_kind for d in devices})
    return f"{backend} ({len(devices)} device(s): {', '.join(kinds)})"


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), as backends and calibrations name the machine."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "unknown model"


def format_bytes(count: float) -> str:
    """``512 B``, ``40.0 kB``, ``12.3 MB``, ``4.56 GB``: three significant digits at any size."""
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(count) >= size:
            value = count / size
            return f"{value:.3g} {unit}" if value < 1000 else f"{value:.0f} {unit}"
    return f"{count:.0f} B"


def format_duration(seconds: float) -> str:
    """``42 s``, ``13 min``, ``5.2 h``, ``23 days``: the precision a plan needs."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * DAY_S:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / DAY_S:.0f} days"
