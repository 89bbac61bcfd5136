"""Several processes (hosts) on JAX's own runtime: joining the job, the barrier, and reading a
process's own members from global arrays.

A run on P processes is one SPMD program over a mesh of every process's devices: each process
holds the members of its devices, writes their records and its part of each checkpoint (orbax
writes multi-host checkpoints natively), and process 0 writes what belongs to the whole run
(``plan.json``, ``timing.jsonl``, ``summary.json``, the figures). The processes advance chunk by
chunk together; the only cross-process values are the trainer's two ``psum``\\ s and the barriers
here.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
from collections.abc import Callable

import jax
import numpy as np

# Environment variables a job may set instead of flags (JAX's own names; SLURM's are read by JAX).
COORDINATOR_ENV, NUM_PROCESSES_ENV, PROCESS_ID_ENV = (
    "JAX_COORDINATOR_ADDRESS",
    "JAX_NUM_PROCESSES",
    "JAX_PROCESS_ID",
)

# How much longer than the --coordinator-timeout JAX itself waits for the job to assemble, so that
# initialize's own watchdog (a one-line message) ends the wait before JAX's abort does.
JOIN_GRACE_S = 30
# What a failed collective says when another process of the job died: Gloo's closed connections on
# CPU, the coordination service's missed heartbeats.
LOST_PROCESS_MARKS = ("Connection reset by peer", "Connection closed by peer", "Gloo", "heartbeat timeout")


class CoordinatorError(RuntimeError):
    """The job's coordinator could not be reached, or the flags do not describe a job."""


def is_primary() -> bool:
    return jax.process_index() == 0


def sync(name: str) -> None:
    """Wait until every process has reached the barrier ``name`` (nothing with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def gathered(value) -> np.ndarray:
    """Every process's ``value`` (a number or flag), in process order; with one process, ``[value]``.
    For decisions all processes must take alike: stop now, checkpoint now, the group size."""
    if jax.process_count() == 1:
        return np.array([value])
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(np.array([value]))).reshape(-1)


def fetch(tree):
    """A pytree of (global) arrays as numpy: the whole array where this process holds all of it,
    else its own rows with the others left zero (read only the rows of :func:`local_rows`)."""

    def one(x):
        if not isinstance(x, jax.Array) or x.is_fully_addressable:
            return np.asarray(jax.device_get(x))
        out = np.zeros(x.shape, x.dtype)
        for shard in x.addressable_shards:
            out[shard.index] = np.asarray(shard.data)
        return out

    return jax.tree.map(one, tree)


def fetch_all(tree):
    """A pytree of (global) arrays as numpy, whole on every process: the rows other processes hold
    are gathered from them (a collective: every process calls it alike). For the small per-member
    records a progress callback receives of every member."""
    if jax.process_count() == 1:
        return fetch(tree)
    from jax.experimental import multihost_utils

    def one(x):
        if not isinstance(x, jax.Array) or x.is_fully_addressable:
            return np.asarray(jax.device_get(x))
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))

    return jax.tree.map(one, tree)


def local_rows(sharding, num_rows: int) -> list[int]:
    """The rows of a ``num_rows``-long member axis that this process's devices hold."""
    index_map = sharding.addressable_devices_indices_map((num_rows,))
    return sorted({row for index in index_map.values() for row in range(*index[0].indices(num_rows))})


def wanted() -> bool:
    """Whether the environment describes a job of several processes: JAX's coordinator variable,
    or a SLURM step with several tasks (JAX reads SLURM's variables itself)."""
    if os.environ.get(COORDINATOR_ENV):
        return True
    return int(os.environ.get("SLURM_STEP_NUM_TASKS", os.environ.get("SLURM_NTASKS", "1")) or 1) > 1


def _split_address(address: str) -> tuple[str, int]:
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise CoordinatorError(f"--coordinator {address!r}: expected HOST:PORT")
    return host.strip("[]"), int(port)


def _wait_for_coordinator(address: str, timeout_s: float) -> None:
    """Connect to the coordinator's port until it answers or ``timeout_s`` passes. JAX's own
    client aborts the process with a page of C++ stack when the coordinator is unreachable; this
    check fails first, in one line."""
    host, port = _split_address(address)
    deadline = time.monotonic() + timeout_s
    last = "no answer"
    while True:
        try:
            with socket.create_connection((host, port), timeout=min(5.0, timeout_s)):
                return
        except OSError as err:
            last = err.strerror or type(err).__name__
        if time.monotonic() >= deadline:
            raise CoordinatorError(
                f"cannot reach the coordinator {address} within {timeout_s:g} s ({last}); start process 0 "
                "first, or check --coordinator and the network"
            )
        time.sleep(0.5)


def initialize(
    coordinator: str | None,
    num_processes: int | None,
    process_id: int | None,
    timeout_s: float,
    on_stall: Callable[[str], None] | None = None,
) -> None:
    """Join the job (``jax.distributed.initialize``). Missing values come from JAX's environment
    variables or its cluster detection (SLURM, Open MPI, Kubernetes). A process other than 0 first
    checks within ``timeout_s`` that the coordinator answers.

    When the other processes have not all joined within ``timeout_s``, JAX aborts the process with a
    page of C++ stack that Python cannot catch. With ``on_stall``, that wait is JAX's for
    :data:`JOIN_GRACE_S` longer and ``on_stall`` is called, on another thread, with a one-line
    message once ``timeout_s`` has passed; it must end the process (``os._exit``: the waiting thread
    is inside JAX and cannot be interrupted)."""
    coordinator = coordinator or os.environ.get(COORDINATOR_ENV)
    if num_processes is None and os.environ.get(NUM_PROCESSES_ENV):
        num_processes = int(os.environ[NUM_PROCESSES_ENV])
    if process_id is None and os.environ.get(PROCESS_ID_ENV):
        process_id = int(os.environ[PROCESS_ID_ENV])
    if num_processes is not None and process_id is not None and not 0 <= process_id < num_processes:
        raise CoordinatorError(f"--process-id {process_id} is not in 0..{num_processes - 1}")
    if coordinator is not None:
        _split_address(coordinator)
        if process_id not in (None, 0):
            _wait_for_coordinator(coordinator, timeout_s)
    watchdog = None
    if on_stall is not None:
        message = _stall_message(coordinator, num_processes, process_id, timeout_s)
        watchdog = threading.Timer(timeout_s, on_stall, args=(message,))
        watchdog.daemon = True
        watchdog.start()
    try:
        jax.distributed.initialize(
            coordinator_address=coordinator,
            num_processes=num_processes,
            process_id=process_id,
            initialization_timeout=max(int(timeout_s), 1) + (JOIN_GRACE_S if watchdog else 0),
        )
    finally:
        if watchdog is not None:
            watchdog.cancel()


def _stall_message(
    coordinator: str | None, num_processes: int | None, process_id: int | None, timeout_s: float
) -> str:
    who = "this process" if process_id is None else f"process {process_id}"
    others = "the other processes" if num_processes is None else f"all {num_processes} processes"
    ids = "" if num_processes is None else f", --process-id 0..{num_processes - 1}"
    where = f"the coordinator {coordinator}" if coordinator else "the job's coordinator"
    return (
        f"the job did not assemble within {timeout_s:g} s: {who} waited at {where} for {others} to join; "
        f"start them all with the same options{ids} within --coordinator-timeout of each other"
    )


def lost_a_process(error: BaseException) -> bool:
    """Whether ``error`` is a collective of a job of several processes that failed because another
    process is gone (a closed connection: Gloo on CPU reports it at once) or stopped answering."""
    if jax.process_count() == 1:
        return False
    text = str(error)
    return any(mark in text for mark in LOST_PROCESS_MARKS)


def leave_at_once(status: int) -> None:
    """End this process now with ``status``, skipping the exit handlers: after a process of the job is
    lost, JAX's own shutdown waits at a barrier for it and then aborts with a page of C++ stack."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
