"""Shared set-up for the trainer tests: a private cache folder pre-filled with the smoke tracks.

Generating even three tracks compiles the generator for ~30 s on CPU, so the tests ship the two
tiny banks the smoke preset uses (training seed 0 and evaluation seed 1, three tracks each).
"""

import contextlib
import os
import shutil
from pathlib import Path

DATA = Path(__file__).parent / "data"


def prepare_cache(folder: Path) -> None:
    """Point ``XRL_JAX_CACHE_DIR`` at ``folder`` and seed it with the shipped smoke track banks."""
    os.environ["XRL_JAX_CACHE_DIR"] = str(folder)
    seed_track_cache(folder)


def seed_track_cache(folder: Path | str) -> None:
    """Copy the shipped smoke banks into the track cache ``folder`` (atomically: two xdist workers
    may seed one folder at once)."""
    from xrl_jax.tracks import cache_dir, track_cache_path

    for seed in (0, 1):
        target = Path(folder) / track_cache_path(seed, 3).relative_to(cache_dir())
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            partial = target.with_suffix(f".tmp{os.getpid()}")
            shutil.copy(DATA / f"tracks_seed{seed}_size3.npz", partial)
            os.replace(partial, target)


# XLA_FLAGS of the tests' compile (tests/conftest.py says why): faster to compile, rounded differently.
FAST_COMPILING_EMITTERS = "--xla_cpu_use_fusion_emitters=false"


def production_compile_environ() -> dict[str, str]:
    """``os.environ`` for a child process that compiles as a user's run does: XLA's optimisations on
    and its default emitters (not the tests' faster-compiling settings)."""
    env = dict(os.environ, JAX_DISABLE_MOST_OPTIMIZATIONS="0")
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace(FAST_COMPILING_EMITTERS, "").strip()
    return env


def xla_flags(*flags: str) -> str:
    """``XLA_FLAGS`` for a child process: this run's (tests/conftest.py sets some) and ``flags``."""
    return " ".join([os.environ.get("XLA_FLAGS", ""), *flags]).strip()


# The trivial env's module, and run.py's arguments that register it by --import and train on it.
FAST_ENV_MODULE = str(DATA.parent / "fast_env.py")
FAST_ENV_ARGS = ["--import", FAST_ENV_MODULE, "--env", "fast"]


@contextlib.contextmanager
def fast_env_registered():
    """tests/fast_env.py's trivial env registered for the duration (``fast``): a host-side test that
    only needs a run trains on it, in half the compile time of a scenario's."""
    import fast_env

    import xrl_jax

    fast_env.register()
    try:
        yield fast_env.NAME
    finally:
        xrl_jax.unregister_env(fast_env.NAME)


def load_script(name: str, module_name: str):
    """``experiments/<name>.py`` loaded in-process, so that runs of one configuration share their
    compilation (a subprocess would compile again)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(module_name, DATA.parents[1] / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses look their module up while it executes
    spec.loader.exec_module(module)
    return module


def call(script, capsys, *args):
    """(exit status, stdout, stderr) of one invocation of a script's ``main``."""
    try:
        status = script.main(list(args))
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def files_of(folder: Path, sub: str) -> dict[str, str]:
    """The record files of a run folder's ``sub`` (metrics, eval) by name, with their text."""
    return {p.name: p.read_text() for p in sorted((folder / sub).glob("*.jsonl"))}


def run_stopped_after(run, capsys, monkeypatch, chunks: int, *args):
    """(status, stdout, stderr) of ``run.main(args)`` with the trainer stopping after ``chunks`` chunks,
    as an interrupted run does; the trainer is whole again afterwards, for the resume."""
    import functools

    from xrl_jax import train as train_mod

    original = train_mod.train
    monkeypatch.setattr(train_mod, "train", functools.partial(original, stop_after_chunks=chunks))
    try:
        return call(run, capsys, *args)
    finally:
        monkeypatch.setattr(train_mod, "train", original)


def one_line_error(status, err, *fragments):
    """A CLI's bad-input exit: status 2 and one line on standard error holding every fragment."""
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
