"""Measurements of what the project costs: throughput of envs, updates and whole training chunks
(``experiments/bench.py``), and parameters and FLOPs per action beside the paper's Table I
(``experiments/costs.py``). They sit above the trainer, which they time; tests never assert
timings, these do. docs/benchmarks.md holds the measured numbers.

* :mod:`.timing`: wall-clock timing (best of several, or alternating between variants on a noisy
  machine), the matmul ceiling, XLA's FLOP count, peak memory;
* :mod:`.rollouts`: env steps per second, the fresh-track feed's cost;
* :mod:`.updates`: gradient updates per second, end-to-end training steps per second;
* :mod:`.table_one`: parameter counts and inference FLOPs on Country Road shapes.
"""

from xrl_jax.benchmarks.rollouts import bench_env, bench_intersection, bench_tracks
from xrl_jax.benchmarks.table_one import format_table_one, measure_table_one
from xrl_jax.benchmarks.timing import bench_matmul, machine_info
from xrl_jax.benchmarks.updates import bench_train, bench_update

__all__ = [
    "bench_env",
    "bench_intersection",
    "bench_matmul",
    "bench_tracks",
    "bench_train",
    "bench_update",
    "format_table_one",
    "machine_info",
    "measure_table_one",
]
