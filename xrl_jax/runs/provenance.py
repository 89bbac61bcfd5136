"""What makes a run reproducible: the resolved config, versions, git commit, device and command
line, as written into the folder's ``config.json``."""

from __future__ import annotations

import datetime
import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import jax

import envs
from xrl_jax.agents import make_hparams
from xrl_jax.config.user_envs import user_env_record
from xrl_jax.runs.folder import member_fields, member_stem


def _git_commit(repo: Path) -> dict[str, Any]:
    def git(*args):
        result = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10)
        return result.stdout.strip() if result.returncode == 0 else None

    try:
        commit = git("rev-parse", "HEAD")
        status = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def versions() -> dict[str, str | None]:
    import importlib.metadata as md

    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "distrax", "numpy", "xrl-jax"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    out["envs"] = envs.__version__
    return out


def run_metadata(argv: list[str] | None = None) -> dict[str, Any]:
    """Versions, git commit, device and command line: everything needed to reproduce the run."""
    device = jax.devices()[0]
    return {
        "versions": versions(),
        "git": _git_commit(Path(__file__).resolve().parents[1]),
        "device": {"backend": jax.default_backend(), "kind": getattr(device, "device_kind", str(device))},
        "command": [sys.executable, *(sys.argv if argv is None else argv)],
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def config_document(cfg, argv: list[str] | None = None) -> dict[str, Any]:
    """The content of ``config.json``: the fully resolved config (incl. resolved agent defaults), and
    for a user's env its record (:mod:`xrl_jax.config.user_envs`): module, layout, time limit."""
    agent = cfg.agent
    hp = make_hparams(agent, envs.action_size(envs.action_space(cfg.env_name)))
    resolved = {
        "alpha_lr": agent.resolved_alpha_lr(),
        "epsilon_random": agent.resolved_epsilon_random(),
        "target_entropy": float(hp.target_entropy),
        "log_std_min": agent.resolved_log_std_min(),
        "env_name": cfg.env_name,
        "buffer_layout": cfg.buffer_layout,
        "updates_per_seed": max(0, cfg.total_steps - cfg.warmup_steps),
    }
    doc = {"config": cfg.to_dict(), "resolved": resolved, **run_metadata(argv)}
    record = user_env_record(cfg.env)
    if record is not None:  # a user's env: what a resume or a reader must find registered again
        doc["user_env"] = record
    if cfg.num_points > 1:  # every member's seed, point and values, in the order of the member axis
        doc["members"] = [
            {"member": m, "file": member_stem(cfg, m), **member_fields(cfg, m)}
            for m in range(cfg.num_members)
        ]
    json.dumps(doc)  # fail early on anything not serialisable
    return doc
