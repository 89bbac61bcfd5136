"""End-to-end vectorised training: the whole SAC loop in one compiled ``lax.scan`` chunk, vmapped
over seeds, driven by a host loop between chunks. Its configuration (:class:`TrainConfig`,
:func:`resolve_config`) lives in :mod:`xrl_jax.config` and is re-exported here.

Modules, by what they hold:

* :mod:`~xrl_jax.train.episodes`: the rolling window of finished episodes (rollout metrics);
* :mod:`~xrl_jax.train.step`: one member's run state, its start and one vector step of its envs;
* :mod:`~xrl_jax.train.kinds`: the scenario kinds (racing, multi-agent, a user's env), one object each;
* :mod:`~xrl_jax.train.chunk`: the compiled chunk over members and devices, its report (:func:`make_trainer`);
* :mod:`~xrl_jax.train.families`: the algorithm families (SAC's replay, PPO's rollouts), one object each;
* :mod:`~xrl_jax.train.on_policy`: the on-policy family's iteration: a rollout, its GAE and the epochs
  of updates (``--algo ppo|dppo|xppo|xdppo``);
* :mod:`~xrl_jax.train.memory`: bytes per seed and the seed groups that fit;
* :mod:`~xrl_jax.train.loop`: the host loop (:func:`train`), its records (:mod:`~xrl_jax.train.records`,
  :class:`Progress` for its progress callbacks) and what it shows (:mod:`~xrl_jax.train.console`);
* :mod:`~xrl_jax.train.restore`: a run's checkpoint groups, for a resume and for readers of a folder;
* :mod:`~xrl_jax.train.evaluate_run`: a trained run's agents evaluated again (:func:`evaluate_run`);
* :mod:`~xrl_jax.train.start`: a run started as ``experiments/run.py`` asks (joining a job of
  several processes, a new folder or a resumed one).

The track banks are :mod:`xrl_jax.tracks`'s, the results folder :mod:`xrl_jax.runs`'s.
"""

from xrl_jax.config import (
    ENVS,
    PRESETS,
    ConfigError,
    TrainConfig,
    parse_overrides,
    resolve_config,
)
from xrl_jax.runs.folder import write_atomic
from xrl_jax.tracks import cache_dir, cached_track_bank, track_cache_path
from xrl_jax.train.chunk import ChunkReport, Trainer, get_trainer, make_trainer
from xrl_jax.train.evaluate_run import evaluate_run
from xrl_jax.train.kinds import make_envs, scenario_kind
from xrl_jax.train.loop import DiskFullError, DivergenceError, FolderWriteError, train
from xrl_jax.train.memory import MemoryPlanError, estimate_seed_bytes, plan_memory
from xrl_jax.train.records import Progress
from xrl_jax.train.restore import load_trained_agent, load_trained_agents
from xrl_jax.train.step import RunState

__all__ = [
    "ENVS",
    "PRESETS",
    "ChunkReport",
    "ConfigError",
    "DiskFullError",
    "DivergenceError",
    "FolderWriteError",
    "MemoryPlanError",
    "Progress",
    "RunState",
    "TrainConfig",
    "Trainer",
    "cache_dir",
    "cached_track_bank",
    "estimate_seed_bytes",
    "evaluate_run",
    "get_trainer",
    "load_trained_agent",
    "load_trained_agents",
    "make_envs",
    "make_trainer",
    "parse_overrides",
    "plan_memory",
    "resolve_config",
    "scenario_kind",
    "track_cache_path",
    "train",
    "write_atomic",
]
