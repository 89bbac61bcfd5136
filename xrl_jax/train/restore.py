"""Restoring a run's checkpoint groups: one restore for the host loop (a resume) and for the readers
of a folder (explanation figures, re-evaluation), so that every caller verifies a checkpoint the
same way and falls back to the newest good one when the newest is damaged.

A checkpoint holds the run state of one member group (``plan.json`` says which members, and the
device count its rows were padded to) and, in its metadata, the config fingerprint, the members,
the step and the next chunk.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from xrl_jax.checkpoint import Checkpointer, CorruptCheckpointError, NoGoodCheckpointError
from xrl_jax.config import ConfigError, TrainConfig
from xrl_jax.config.user_envs import user_env_record
from xrl_jax.runs.folder import (
    RunFolderError,
    checkpoint_dir,
    is_complete,
    read_checkpoint_plan,
    read_run_config,
    run_paths,
)
from xrl_jax.train import hosts
from xrl_jax.train.chunk import Trainer, get_trainer
from xrl_jax.train.memory import padded_members

# Settings added after runs with checkpoints existed. Each is hashed only when set away from its
# default, so that a run which does not use it keeps the fingerprint it was written with and resumes
# (and is read) after an upgrade. A new setting joins these lists: tests/test_fingerprint.py
# pins the fingerprint of a fixed configuration, and fails when a setting is added without it.
LATE_TRAIN_SETTINGS = ("sweep",)
LATE_AGENT_SETTINGS = (  # the on-policy family's (issue 51)
    "rollout_steps", "ppo_epochs", "ppo_minibatches", "clip_eps", "value_clip_eps", "ent_coef", "gae_lambda",
)  # fmt: skip


def _unset(config, names: tuple[str, ...]) -> list[str]:
    """The settings of ``names`` that ``config`` (a config dataclass) leaves at their defaults."""
    defaults = {f.name: f.default for f in dataclasses.fields(config)}
    return [name for name in names if getattr(config, name) == defaults[name]]


def config_fingerprint(cfg: TrainConfig) -> str:
    """A hash of every setting that shapes the run's results (not the host-only settings; the late
    settings only when set); stored with each checkpoint so that a resume never continues another
    configuration's state."""
    fields = cfg.results_fields()
    for name in _unset(cfg, LATE_TRAIN_SETTINGS):
        fields.pop(name)
    for name in _unset(cfg.agent, LATE_AGENT_SETTINGS):
        fields["agent"].pop(name)
    record = user_env_record(cfg.env)
    if record is not None:  # a user's env: its layout, actions, time limit and module (built-ins: none)
        fields["user_env"] = record
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def stored_members(meta: dict) -> list[int] | None:
    return meta.get("members", meta.get("seeds"))  # runs before sweeps stored their seeds


def first_nonfinite_leaf(tree) -> str:
    """The path of the first float leaf of ``tree`` with a non-finite entry (for one-line messages)."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        leaf = np.asarray(leaf)
        if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
            return jax.tree_util.keystr(path)
    return "(none found)"


def all_finite(tree) -> bool:
    """Whether every float leaf of a (global) pytree is finite, the same answer on every process.
    Checked on the host: an eager reduction over arrays spread on a split CPU host runs a collective
    outside the compiled chunk, which deadlocked (1 restore in ~10, XLA:CPU, JAX 0.10)."""
    leaves = [x for x in jax.tree.leaves(hosts.fetch(tree)) if np.issubdtype(x.dtype, np.floating)]
    local = all(np.all(np.isfinite(x)) for x in leaves)
    return local if jax.process_count() == 1 else bool(hosts.gathered(local).all())


def restore_group(
    ckpt: Checkpointer,
    trainer: Trainer,
    members: list[int],
    num_rows: int,
    fingerprint: str,
    group_index: int,
    warn,
    set_aside: bool = True,
) -> tuple[Any, dict]:
    """``(state, metadata)`` of the newest good checkpoint of member group ``group_index``
    (``num_rows`` rows: the members and their padding to the device count).

    A checkpoint is good when its files match their digests, it belongs to this configuration and
    member group, and its agent is finite; damaged ones are reported through ``warn`` (and, with
    ``set_aside``, moved aside so that they are never restored again: only the run's writer does
    that). Raises :class:`ConfigError` when the newest checkpoint is another configuration's, and
    :class:`~xrl_jax.checkpoint.NoGoodCheckpointError` when none is good."""
    try:
        meta = ckpt.metadata()
    except CorruptCheckpointError:
        meta = None  # a damaged newest checkpoint: restore_newest_good reports it and falls back
    if meta is not None and meta.get("config", fingerprint) != fingerprint:
        raise ConfigError(
            f"checkpoint group {group_index} in {ckpt.directory.parent} was written by another "
            "configuration than config.json describes; start a new run with --out"
        )
    if meta is not None and stored_members(meta) != members:
        raise ConfigError(
            f"checkpoint group {group_index} holds members {stored_members(meta)}, expected {members}"
        )

    def check(state, meta) -> str | None:
        if meta.get("config") != fingerprint or stored_members(meta) != members:
            return "it belongs to another configuration or member group"
        if not all_finite(state.agent):
            return f"the agent's {first_nonfinite_leaf(hosts.fetch(state.agent))} is not finite"
        return None

    return ckpt.restore_newest_good(trainer.abstract_state(num_rows), check, warn, set_aside=set_aside)


# ---- Readers of a results folder: trained agents ----------------------------------------------


@functools.lru_cache(maxsize=2)
def shared_trainer(cfg: TrainConfig) -> Trainer:
    """The run's trainer on this machine's first device, shared by repeated loads of one config in a
    process (its agent, and so the compiled episode rollouts, are then reused). A run trained on
    several devices or hosts restores here onto one."""
    return get_trainer(cfg, devices=jax.devices()[:1])


def _warn(line: str) -> None:
    print(line, file=sys.stderr)


def _group_agents(folder: Path, cfg: TrainConfig, group: list[int], devices: int, group_index: int, warn):
    """``(trainer, members, agents, step)``: the newest good checkpoint of one group, its members in
    row order (rows past them are the padding to the device count)."""
    directory = checkpoint_dir(folder, group_index)
    if not directory.is_dir():
        raise RunFolderError(f"no checkpoint in {folder} (missing {directory})")
    checkpointer = Checkpointer(directory)
    try:
        if checkpointer.latest_step() is None:
            raise RunFolderError(f"no checkpoint in {directory}")
        trainer = shared_trainer(cfg)
        num_rows = len(padded_members(group, devices))
        try:
            state, meta = restore_group(
                checkpointer,
                trainer,
                group,
                num_rows,
                config_fingerprint(cfg),
                group_index,
                warn,
                set_aside=False,
            )
        except (ConfigError, NoGoodCheckpointError) as err:
            raise RunFolderError(str(err)) from None
    finally:
        checkpointer.close()
    step = int(meta.get("step", 0))
    if step < cfg.total_steps:
        why = (
            "the run finished, but its last checkpoint could not be used"
            if is_complete(folder)
            else "the run has not finished: it is still going, was stopped, or diverged after that step"
        )
        warn(f"{folder}: using the checkpoint at step {step:,} of {cfg.total_steps:,} ({why})")
    return trainer, list(stored_members(meta) or group), state.agent, step


def load_trained_agent(run_dir, seed: int = 0, point: int = 0, warn=_warn):
    """``(config, trainer, agent_state)`` of seed ``seed`` (at sweep point ``point`` of a sweep)
    from the newest good checkpoint of a results folder; ``warn`` hears of damaged checkpoints
    passed over and of a run that has not finished."""
    folder = Path(run_dir)
    cfg = read_run_config(folder)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < cfg.num_seeds:
        raise RunFolderError(f"seed {seed} out of range: the run has seeds 0..{cfg.num_seeds - 1}")
    if isinstance(point, bool) or not isinstance(point, int) or not 0 <= point < cfg.num_points:
        raise RunFolderError(f"sweep point {point} out of range: the run has points 0..{cfg.num_points - 1}")
    member = point * cfg.num_seeds + seed
    groups, devices = read_checkpoint_plan(folder, cfg.num_members)
    group_index = next((g for g, members in enumerate(groups) if member in members), None)
    if group_index is None:
        raise RunFolderError(
            f"seed {seed} (point {point}) is in no checkpoint group of {run_paths(folder)['plan']}"
        )
    trainer, members, agents, _ = _group_agents(folder, cfg, groups[group_index], devices, group_index, warn)
    row = members.index(member)
    return cfg, trainer, jax.tree.map(lambda leaf: leaf[row], agents)


def load_trained_agents(run_dir, warn=_warn):
    """``(config, trainer, agent_states)``: every member's agent (a plain run's: every seed's),
    stacked on a leading axis in member order, restoring each checkpoint group once."""
    return load_trained_agents_and_steps(run_dir, warn)[:3]


def load_trained_agents_and_steps(run_dir, warn=_warn):
    """:func:`load_trained_agents` and, in member order, the step of the checkpoint each came from."""
    folder = Path(run_dir)
    cfg = read_run_config(folder)
    groups, devices = read_checkpoint_plan(folder, cfg.num_members)
    by_member, steps, trainer = {}, {}, None
    for group_index, group in enumerate(groups):
        trainer, members, agents, step = _group_agents(folder, cfg, group, devices, group_index, warn)
        for row, member in enumerate(members):
            by_member[member] = jax.tree.map(lambda leaf, r=row: leaf[r], agents)
            steps[member] = step
    missing = sorted(set(range(cfg.num_members)) - set(by_member))
    if missing:
        raise RunFolderError(f"members {missing} are in no checkpoint group of {run_paths(folder)['plan']}")
    ordered = [by_member[member] for member in range(cfg.num_members)]
    stacked = jax.tree.map(lambda *leaves: jax.numpy.stack(leaves), *ordered)
    return cfg, trainer, stacked, [steps[member] for member in range(cfg.num_members)]
