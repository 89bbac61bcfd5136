"""Measurements of what the project costs: throughput of envs, updates and whole training chunks
(``experiments/bench.py``), and parameters and FLOPs per action beside the paper's Table I
(``experiments/costs.py``). They sit above the trainer, which they time; tests never assert
timings, these do. docs/benchmarks.md holds the measured numbers.

* :mod:`.timing`: wall-clock timing (best of several, or alternating between variants on a noisy
  machine), the matmul ceiling, XLA's FLOP count, peak memory;
* :mod:`.rollouts`: env steps per second, the fresh-track feed's cost;
* :mod:`.updates`: gradient updates per second, end-to-end training steps per second;
* :mod:`.table_one`: parameter counts and inference FLOPs on Country Road shapes;
* :mod:`.profile`: one chunk's op time by model part (``jax.profiler`` and the optimised HLO);
* :mod:`.compare`: two versions' ``bench.py train`` side by side, in turn, in processes of their own;
* :mod:`.third_party`: our PPO beside rejax's at an equal budget (``bench.py rejax``).
"""

import importlib

# What ``bench.py rejax --rejax-with`` can give rejax's PPO of ours (:mod:`.third_party`); here, where
# bench.py's parser reads it without importing jax.
REJAX_PIECES = ("squash", "state_std", "observation", "global_clip")

# Loaded on first use, so that ``xrl_jax.benchmarks.compare`` (bench.py compare, which only starts
# other processes) imports no jax: on a GPU host a parent holding the device takes its children's memory.
_EXPORTS = {
    "bench_env": "rollouts",
    "bench_intersection": "rollouts",
    "bench_tracks": "rollouts",
    "format_table_one": "table_one",
    "measure_table_one": "table_one",
    "bench_matmul": "timing",
    "machine_info": "timing",
    "bench_train": "updates",
    "bench_update": "updates",
    "bench_profile": "profile",
    "ppo_against_rejax": "third_party",
}


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"xrl_jax.benchmarks.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'xrl_jax.benchmarks' has no attribute {name!r}")


__all__ = sorted([*_EXPORTS, "REJAX_PIECES"])
