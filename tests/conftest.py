"""What every test process shares: one run-wide JAX compilation cache and one track cache.

Most of the suite's time is compilation, and much of it is the same program compiled again: by the
other xdist worker, by a child process (CLI tests, forced host devices, two-process jobs), or by a
trainer rebuilt for the same configuration. So the controller sets, before any worker or child starts
(they inherit the environment):

* ``JAX_COMPILATION_CACHE_DIR``: a fresh folder for this run, so a program compiled once is loaded
  by every other process, and a run from a fresh clone costs what it costs here (no stale or warm
  cache decides the time). Set it yourself to keep a cache across runs; ``run.py`` uses it too
  (``enable_compilation_cache`` leaves a set cache alone).
* ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0``: JAX keeps only programs that took a second to
  compile by default; the tests compile hundreds of smaller ones twice (once per worker).
* ``XRL_JAX_CACHE_DIR``: a fresh folder holding the two shipped smoke banks, so the tests neither read
  nor fill the user's cache (``train_support.prepare_cache`` still gives a module its own).
* ``JAX_DISABLE_MOST_OPTIMIZATIONS=1``: XLA's CPU backend compiles without LLVM's optimisations
  (JAX's switch for when "the cost of optimization is greater than that of running a less-optimized
  program"), about 40 % less compile time; the tests run short programs, so the slower code costs
  little. Results can differ from an optimised build's in the last bits (LLVM then fuses
  multiply-adds), which no test may depend on: tolerances follow from the computation, and exact
  comparisons are between programs of the same run. ``JAX_DISABLE_MOST_OPTIMIZATIONS=0 python -m pytest``
  tests the optimised build.
* ``XLA_FLAGS`` gains ``--xla_cpu_use_fusion_emitters=false`` (unless it names that flag): XLA's CPU
  backend then emits its fused kernels with its older LLVM IR emitter instead of the MLIR fusion
  emitters, which compiles the tests' programs about 2.5x faster (a Tracking smoke run's: 14 s of
  backend compilation against 6 s). The same caveat on the last bits holds; run.py never sets it.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile

import pytest
from train_support import FAST_COMPILING_EMITTERS, seed_track_cache

_OWNED: list[str] = []


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # an xdist worker: the controller has set the environment
        return
    if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        _OWNED.append(tempfile.mkdtemp(prefix="xrl-jax-tests-compiled-"))
        os.environ["JAX_COMPILATION_CACHE_DIR"] = _OWNED[-1]
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
    if "--xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILING_EMITTERS}".strip()
    _OWNED.append(tempfile.mkdtemp(prefix="xrl-jax-tests-cache-"))
    os.environ["XRL_JAX_CACHE_DIR"] = _OWNED[-1]
    if "jax" in sys.modules:  # imported before this file (a plugin): it read the variables already
        import jax

        jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
        min_time = float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_time)
        disable = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"].lower() in ("1", "true", "yes", "on")
        jax.config.update("jax_disable_most_optimizations", disable)


@pytest.fixture(autouse=True)
def _optimised_build(request):
    """Tests marked ``optimised`` (learning runs: their time is in running the programs, which the
    unoptimised build runs ~2.3x slower) compile with XLA's optimisations, whatever the run's setting."""
    if request.node.get_closest_marker("optimised") is None:
        yield
        return
    import jax

    before = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", before)


def pytest_sessionstart(session):
    """In each process that runs tests (the controller has not imported JAX: workers start sooner)."""
    if not hasattr(session.config, "workerinput") and session.config.pluginmanager.has_plugin("dsession"):
        return  # the xdist controller runs no test
    seed_track_cache(os.environ["XRL_JAX_CACHE_DIR"])


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """``-n`` sends whole test files to a worker (``--dist loadfile``) unless ``--dist`` is given: a
    file's module fixtures (a smoke run, a compiled agent) are then built once, not once per worker.
    The files go out in the order of :func:`pytest_collection_modifyitems`."""
    if config.getoption("dist") == "load" and not any(
        arg.startswith(("--dist", "-d")) for arg in config.invocation_params.args
    ):
        from xdist.scheduler import LoadFileScheduling

        config.option.loadscopereorder = False  # the order below, not xdist's by number of tests
        return LoadFileScheduling(config, log)
    return None


@pytest.hookimpl(trylast=True)  # after -m and -k have deselected
def pytest_collection_modifyitems(config, items):
    """Files with a learning run (marked ``optimised``: minutes each) first, then the rest by their
    number of tests, as xdist orders them: the longest work starts first, so that no worker is left
    with a learning run while the others are done (the marked tiers' time)."""
    per_file: dict[str, list] = {}
    for item in items:
        per_file.setdefault(item.nodeid.split("::")[0], []).append(item)
    learns = {f for f, tests in per_file.items() if any(t.get_closest_marker("optimised") for t in tests)}
    order = sorted(per_file, key=lambda f: (f not in learns, -len(per_file[f])))
    items[:] = [item for f in order for item in per_file[f]]


def pytest_unconfigure(config):
    while _OWNED:
        shutil.rmtree(_OWNED.pop(), ignore_errors=True)
