"""Memory planning: how many bytes a seed needs and how many seeds fit at once (the rest run in
groups, one after another)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp

from xrl_jax.config import TrainConfig
from xrl_jax.resources import format_bytes, host_memory_available

if TYPE_CHECKING:
    from xrl_jax.train.chunk import Trainer


class MemoryPlanError(RuntimeError):
    """Even one seed does not fit the memory budget."""





def tree_bytes(tree) -> int:
    leaves = [x for x in jax.tree.leaves(tree) if hasattr(x, "shape") and hasattr(x, "dtype")]
    return int(sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in leaves))


def device_memory_bytes() -> tuple[int, str]:
    """Usable memory of the default device: the allocator's limit on accelerators; on CPU the
    available RAM, or less where a container's memory limit leaves less."""
    device = jax.devices()[0]
    try:
        stats = device.memory_stats() or {}
    except Exception:
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.device_kind} memory"
    return host_memory_available()


def estimate_seed_bytes(trainer: Trainer) -> dict[str, int]:
    """Device bytes one seed needs: exact sizes of its state (``eval_shape``, nothing allocated)
    plus an estimate of the update's and evaluation's temporary arrays."""
    cfg = trainer.config
    abstract = trainer.abstract_state(1)
    obs = trainer.agent.obs_shape
    objects = obs.num_objects * cfg.agent.components_per_object
    a = cfg.agent
    per_sample = objects * (a.actor_width * a.actor_depth + a.critic_width * a.critic_depth * a.n_critics)
    if a.algo == "xsac":
        per_sample += objects * objects * trainer.agent.action_size  # the B x K x K x A density tensor
    # float32 activations kept for the backward pass, gradients and XLA temporaries: ~4 copies.
    workspace = 4 * 4 * cfg.batch_size * (per_sample + obs.state_dim + obs.object_features * obs.num_objects)
    eval_bytes = 4 * 4 * cfg.eval_episodes * objects * a.actor_width * a.actor_depth
    # Fresh tracks: the seed's feed, plus a refill's new half feed before it is written in.
    feed = tree_bytes(abstract.feed) * 3 // 2
    sizes = {
        "buffer": tree_bytes(abstract.buffer),
        "agent": tree_bytes(abstract.agent),
        "env": tree_bytes((abstract.env_state, abstract.obs)) + feed,
        "workspace_estimate": int(workspace + eval_bytes),
    }
    sizes["total"] = sum(sizes.values())
    sizes["bytes_per_transition"] = round(sizes["buffer"] / abstract.buffer.capacity)
    return sizes


def plan_memory(
    trainer: Trainer, cfg: TrainConfig | None = None, budget_bytes: int | None = None
) -> dict[str, Any]:
    """Seed groups of ``cfg`` (default: the trainer's) that fit the budget.

    Raises :class:`MemoryPlanError` if one seed does not fit."""
    cfg = trainer.config if cfg is None else cfg
    sizes = estimate_seed_bytes(trainer)
    if budget_bytes is None:
        if cfg.memory_budget_gb > 0:
            budget_bytes, source = int(cfg.memory_budget_gb * 1e9), "memory_budget_gb"
        else:
            available, source = device_memory_bytes()
            budget_bytes = int(0.9 * available)
    else:
        source = "given"
    shared = tree_bytes((trainer.env_params, trainer.eval_params))
    fit = (budget_bytes - shared) // max(sizes["total"], 1)
    if fit < 1:
        raise MemoryPlanError(
            f"one seed needs about {format_bytes(sizes['total'])} (buffer {format_bytes(sizes['buffer'])}) "
            f"but the budget ({source}) is {format_bytes(budget_bytes)}; "
            "reduce buffer_size or the network widths with --set"
        )
    group = min(cfg.num_seeds, int(fit))
    if cfg.max_group_size:
        group = min(group, cfg.max_group_size)
    num_groups = -(-cfg.num_seeds // group)
    group = -(-cfg.num_seeds // num_groups)  # balance the groups
    groups = [list(range(g * group, min((g + 1) * group, cfg.num_seeds))) for g in range(num_groups)]
    return {"per_seed_bytes": sizes, "budget_bytes": budget_bytes, "budget_source": source, "groups": groups}
