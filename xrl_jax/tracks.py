"""Track banks for the racing scenarios: the training bank and the fixed evaluation tracks, cached on
disk (the generator is slow to compile, so even a few tracks are worth keeping), and a racing env
with params that hold a bank. Below the evaluation and the trainer, which both drive on these banks
(the racing kind, :mod:`xrl_jax.train.kinds.racing`, builds a run's envs from them)."""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import envs
import envs.track
import envs.track_cones
import envs.track_generator
import envs.track_shape
from envs.racing import with_bank
from envs.track import Track
from envs.track_generator import make_track_bank


def cache_dir() -> Path:
    """Where generated track banks (and JAX's compilation cache, see run.py) are kept."""
    return Path(os.environ.get("XRL_JAX_CACHE_DIR", Path.home() / ".cache" / "xrl-jax"))


def _generator_fingerprint() -> str:
    """A hash of the generator's sources: the track type and constants, and the generator itself
    (centre line, cones, and the rejection loop that joins them)."""
    digest = hashlib.sha256()
    for module in (envs.track, envs.track_shape, envs.track_cones, envs.track_generator):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()[:12]


def track_cache_path(seed: int, size: int) -> Path:
    """The cache file of the bank ``(seed, size)`` for this generator version, backend and dtype."""
    dtype = jnp.result_type(float).name
    name = f"tracks-{_generator_fingerprint()}-{jax.default_backend()}-{dtype}-{seed}-{size}.npz"
    return cache_dir() / "tracks" / name


def cached_track_bank(seed: int, size: int):
    """``size`` generated tracks from ``seed``, cached on disk (the generator is slow to compile).

    The file name carries a hash of the generator's source and the backend, so a changed generator
    never serves stale tracks. Writes are atomic (temporary file + rename).
    """
    path = track_cache_path(seed, size)
    fields = [f.name for f in dataclasses.fields(Track)]
    if path.exists():
        try:
            with np.load(path) as data:
                return Track(**{k: jnp.asarray(data[k]) for k in fields})
        except (OSError, KeyError, ValueError):
            pass  # unreadable cache entry: regenerate below
    bank = jax.device_get(make_track_bank(jax.random.PRNGKey(seed), size))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
        np.savez(tmp, **{k: np.asarray(getattr(bank, k)) for k in fields})
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache only costs time
    return jax.tree.map(jnp.asarray, bank)


def racing_env(env_name: str, *banks):
    """``(env, params_1, ..., params_n)``: racing scenario ``env_name`` and, per track bank, params
    that hold it with its ring tables and reset cache (each bank prepared in one compiled call)."""
    # A user track: envs.make generates nothing.
    env, params = envs.make(env_name, track=jax.tree.map(lambda leaf: leaf[0], banks[0]))
    attach = jax.jit(lambda params, bank: env.prepare(with_bank(params, bank)))
    return (env, *(attach(params, bank) for bank in banks))
