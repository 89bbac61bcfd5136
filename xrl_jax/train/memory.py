"""Memory planning: how many bytes a member (one seed at one sweep point) needs and how many fit on
each device at once; the members of a run are spread over the devices, and what does not fit runs
in groups, one after another."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from xrl_jax.config import ACTOR_TWIN, ConfigError, TrainConfig
from xrl_jax.resources import disk_free_bytes, format_bytes, host_memory_available
from xrl_jax.runs.folder import read_checkpoint_plan, run_paths, write_atomic
from xrl_jax.train import hosts
from xrl_jax.train.families import algorithm_family

if TYPE_CHECKING:
    from xrl_jax.train.chunk import Trainer


class MemoryPlanError(RuntimeError):
    """Even one member does not fit a device's memory budget."""


def tree_bytes(tree) -> int:
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape") and hasattr(x, "dtype")]
    return int(sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in leaves))


def device_memory_bytes(devices_on_host: int = 1) -> tuple[int, str]:
    """Usable memory of one device: the allocator's limit on accelerators; on CPU the available RAM
    (or less where a container's memory limit leaves less), shared by the ``devices_on_host`` CPU
    devices of this process."""
    device = jax.local_devices()[0]
    try:
        stats = device.memory_stats() or {}
    except Exception:
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.device_kind} memory"
    available, source = host_memory_available()
    if devices_on_host > 1:
        return available // devices_on_host, f"{source} / {devices_on_host} CPU devices"
    return available, source


def estimate_seed_bytes(trainer: Trainer) -> dict[str, int]:
    """Device bytes one member needs: exact sizes of its state (``eval_shape``, nothing allocated)
    plus an estimate of the update's and evaluation's temporary arrays."""
    cfg = trainer.config
    abstract = trainer.abstract_state(1, sharded=False)
    obs = trainer.agent.obs_shape
    objects = obs.num_objects * cfg.agent.components_per_object
    a = cfg.agent
    per_sample = objects * (a.actor_width * a.actor_depth + a.critic_width * a.critic_depth * a.n_critics)
    if ACTOR_TWIN.get(a.algo, a.algo) == "xsac":  # XSAC and XPPO score every component's sample
        per_sample += objects * objects * trainer.agent.action_size  # the B x K x K x A density tensor
    observation = obs.state_dim + obs.object_features * obs.num_objects
    # The rows of one update's batch, and (on-policy) the rollout's transitions in the chunk's
    # temporaries: two observations and a few floats each.
    batch, rollout = algorithm_family(cfg).update_rows(cfg, cfg.scenario.agent_slots)
    # float32 activations kept for the backward pass, gradients and XLA temporaries: ~4 copies.
    workspace = 4 * 4 * batch * (per_sample + observation) + 4 * rollout * (2 * observation + 8)
    eval_bytes = 4 * 4 * cfg.eval_episodes * objects * a.actor_width * a.actor_depth
    # The vector env's state (on fresh tracks with the seed's feed), plus what its refill holds.
    refill = trainer.venv.refill_bytes(abstract.venv_state)
    sizes = {
        "buffer": tree_bytes(abstract.buffer),
        "agent": tree_bytes(abstract.agent),
        "env": tree_bytes((abstract.venv_state, abstract.obs)) + refill,
        "workspace_estimate": int(workspace + eval_bytes),
    }
    sizes["total"] = sum(sizes.values())
    if abstract.buffer is not None:
        sizes["bytes_per_transition"] = round(sizes["buffer"] / abstract.buffer.capacity)
    return sizes


def plan_memory(
    trainer: Trainer, cfg: TrainConfig | None = None, budget_bytes: int | None = None
) -> dict[str, Any]:
    """Member groups of ``cfg`` (default: the trainer's) that fit, ``budget_bytes`` (or
    ``memory_budget_gb``, or 90 % of the device's memory) being each device's share.

    A group holds at most as many members as fit on one device times the mesh's devices; the
    groups are balanced, and each runs padded to a multiple of the device count (see
    :func:`padded_members`). Raises :class:`MemoryPlanError` if one member does not fit a device.
    """
    cfg = trainer.config if cfg is None else cfg
    sizes = estimate_seed_bytes(trainer)
    devices = trainer.num_devices
    if budget_bytes is None:
        if cfg.memory_budget_gb > 0:
            budget_bytes, source = int(cfg.memory_budget_gb * 1e9), "memory_budget_gb per device"
        else:
            local = sum(d.process_index == jax.process_index() for d in trainer.mesh.devices.flat)
            available, source = device_memory_bytes(local)
            budget_bytes = int(0.9 * available)
    else:
        source = "given"
    shared = tree_bytes((trainer.env_params, trainer.eval_params))
    fit = (budget_bytes - shared) // max(sizes["total"], 1)
    if fit < 1:
        raise MemoryPlanError(
            f"one member needs about {format_bytes(sizes['total'])} (buffer {format_bytes(sizes['buffer'])}) "
            f"but a device's budget ({source}) is {format_bytes(budget_bytes)}; "
            "reduce buffer_size or the network widths with --set"
        )
    members = cfg.num_members
    group = min(members, int(fit) * devices)
    limit = "memory" if group < members else None
    if cfg.max_group_size and cfg.max_group_size < group:
        group, limit = cfg.max_group_size, "max_group_size"
    num_groups = -(-members // group)
    group = -(-members // num_groups)  # balance the groups
    groups = [list(range(g * group, min((g + 1) * group, members))) for g in range(num_groups)]
    return {
        "per_seed_bytes": sizes,
        "budget_bytes": budget_bytes,
        "budget_source": source,
        "devices": devices,
        "groups": groups,
        "groups_limited_by": limit,  # what kept the members from running all at once, if anything did
    }


def padded_members(members: list[int], devices: int) -> list[int]:
    """``members`` repeated at the end up to a multiple of ``devices``: every device holds the same
    number of rows. The repeats train as their originals do and are never written."""
    return members + [members[-1]] * (-len(members) % devices)


def plan_run(trainer: Trainer, cfg: TrainConfig, out: Path, resume: bool, log, warn) -> dict[str, Any]:
    """The run's member groups (:func:`plan_memory`, the same on every process; a resume keeps the
    grouping its checkpoints were made with), written to the folder's plan and told through ``log``;
    ``warn`` hears when the disk looks too small for the checkpoints."""
    plan = plan_memory(trainer, cfg)
    smallest = int(hosts.gathered(len(plan["groups"][0])).min())  # all processes run the same groups
    if smallest < len(plan["groups"][0]):
        plan = plan_memory(trainer, cfg.replace(max_group_size=smallest))
        plan["groups_limited_by"] = "memory"  # another process's
    devices = trainer.num_devices
    if resume and run_paths(out)["plan"].exists():
        stored_groups, was = read_checkpoint_plan(out, cfg.num_members)
        plan["groups"], plan["groups_limited_by"] = stored_groups, "the checkpoints"
        padded = [len(padded_members(g, devices)) for g in stored_groups]
        if padded != [len(padded_members(g, was)) for g in stored_groups]:
            raise ConfigError(
                f"{out} was trained on {was} device(s) in all; its checkpoints hold rows for that "
                f"count, so resume it on {was} device(s) (--devices, or as many processes as before)"
            )
    elif hosts.is_primary():
        write_atomic(run_paths(out)["plan"], json.dumps(plan, indent=2, sort_keys=True) + "\n")
    _tell_plan(cfg, plan, devices, log)
    per_seed = plan["per_seed_bytes"]
    # Two checkpoints kept per group, plus the one being written; each process writes its members' share.
    needed = 3 * len(plan["groups"][0]) * (per_seed["buffer"] + per_seed["agent"] + per_seed["env"])
    needed //= jax.process_count()
    free = disk_free_bytes(out)
    if free < needed:
        warn(f"warning: {format_bytes(free)} free on the disk of {out}, but the checkpoints "
             f"of a member group need up to {format_bytes(needed)}")  # fmt: skip
    return plan


def _tell_plan(cfg: TrainConfig, plan: dict[str, Any], devices: int, log) -> None:
    groups, per_seed = plan["groups"], plan["per_seed_bytes"]
    total, buffer = format_bytes(per_seed["total"]), format_bytes(per_seed["buffer"])
    what = "seed" if cfg.num_points == 1 else "member (a seed at a sweep point)"
    log(f"memory: ~{total} per {what} (buffer {buffer}), budget {format_bytes(plan['budget_bytes'])} "
        f"per device ({plan['budget_source']})")  # fmt: skip
    if devices > 1 or jax.process_count() > 1:
        per_device = -(-len(groups[0]) // devices)
        log(f"devices: {cfg.num_members} members over {devices} devices in {jax.process_count()} "
            f"process(es), up to {per_device} per device")  # fmt: skip
    if len(groups) > 1:
        why = {
            "max_group_size": f"max_group_size={cfg.max_group_size}",
            "the checkpoints": "as the run began",
        }.get(plan["groups_limited_by"], f"memory: {cfg.num_members} members do not fit at once")
        log(f"{why}: running {len(groups)} groups of up to {len(groups[0])} one after another")
