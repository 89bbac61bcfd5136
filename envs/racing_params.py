"""Settings and track bank of the racing envs (Country Road, Tracking): :class:`RacingParams`.

The params carry the track bank as well as the settings: reset draws an index into it, so a batch
of envs shares one bank and the state stays small. :func:`default_racing_params` is the bank
``envs.make`` gives without overrides (generated once per process); it lives here, below the env
classes, so that ``RacingEnv.default_params`` needs nothing from the registry above them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from envs.core import default_float
from envs.ring_geometry import RingTables, ring_tables
from envs.track import Track
from envs.track_generator import make_track_bank
from envs.vehicle_state import VehicleParams

DEFAULT_BANK_SIZE = 128


@jax.tree_util.register_dataclass  # a pytree as flax's struct.dataclass makes one, with its own replace
@dataclasses.dataclass(frozen=True)
class RacingParams:
    """Everything configurable about a racing episode. Numeric leaves may be traced (vmapped sweeps).

    ``tracks`` is a bank with a leading axis and ``tables`` its :class:`RingTables` (same axis; use
    :func:`with_bank` / :func:`with_track` to set both). ``track_source`` is static.

    ``start_s``, ``reset_obs`` and ``reset_cache_for`` are a cache of each bank track's start arc
    length and reset observation, built only by :meth:`RacingEnv.prepare` for the env configuration
    ``reset_cache_for``. They cannot go stale: ``replace`` of a field they depend on drops them, and
    reset uses them only for the env they were built for (otherwise it computes the start on the fly).
    """

    vehicle: VehicleParams
    tracks: Track | None
    tables: RingTables | None = None
    start_s: jax.Array | None = None  # (bank,) start arc lengths
    reset_obs: dict | None = None  # (bank, ...) reset observations
    # RacingEnv._config() of the env the cache was built for
    reset_cache_for: tuple | None = dataclasses.field(default=None, metadata={"static": True})
    k_forwards: float = 0.1
    k_base: float = 0.0
    k_center: float = 0.0
    cone_penalty: float = 0.2
    offtrack_reward: float = -1.0
    track_width: float = 8.0
    idle_speed: float = 0.1
    max_steps: int = 600  # MaxTime truncation at this step count (60 s / 0.1 s)
    max_idle_steps: int = 51  # Idling truncation at this many consecutive idle steps (> 5 s)
    # Cone sensor (Country Road): strict bbox in the body frame and the single normaliser.
    cone_bbox: tuple = (-15.0, 45.0, -30.0, 30.0)
    cone_normaliser: float = 45.0
    # Trajectory sensor (Tracking): spacing of the lookahead points along the centre line.
    lookahead_spacing: float = 2.0
    track_source: str = dataclasses.field(default="bank", metadata={"static": True})

    @property
    def bank_size(self) -> int:
        return 0 if self.tracks is None else int(self.tracks.num_points.shape[0])

    def replace(self, **updates) -> RacingParams:
        """``dataclasses.replace`` that drops the reset cache when a field it depends on changes (any
        field but the cache itself and those of ``_NOT_IN_RESET``, so a new field is covered by default).
        Flax's ``struct.dataclass`` would install a plain ``replace`` over this one, hence the plain
        dataclass registered as a pytree above."""
        if set(updates) - set(RESET_CACHE_FIELDS) - set(_NOT_IN_RESET):
            updates = {**dict.fromkeys(RESET_CACHE_FIELDS), **updates}
        return dataclasses.replace(self, **updates)


RESET_CACHE_FIELDS = ("start_s", "reset_obs", "reset_cache_for")
# Fields the reset observation and start arc length do not depend on (rewards and endings only).
_NOT_IN_RESET = (
    "k_forwards",
    "k_base",
    "k_center",
    "cone_penalty",
    "offtrack_reward",
    "track_width",
    "idle_speed",
    "max_steps",
    "max_idle_steps",
)


def stack_tracks(tracks) -> Track:
    """Stack single tracks into a bank (leading axis)."""
    tracks = list(tracks)
    if not tracks or not all(isinstance(t, Track) for t in tracks):
        raise ValueError("stack_tracks needs a non-empty sequence of Track")
    return jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *tracks)


def with_bank(params: RacingParams, bank: Track) -> RacingParams:
    """Params drawing from ``bank`` (a ``Track`` with a leading axis) at every reset."""
    if not isinstance(bank, Track) or jnp.ndim(bank.num_points) != 1:
        raise ValueError("bank must be a Track with a leading bank axis (see stack_tracks / make_track_bank)")
    tables = jax.jit(jax.vmap(ring_tables))(bank)
    return params.replace(tracks=bank, tables=tables, track_source="bank")


def with_track(params: RacingParams, track: Track) -> RacingParams:
    """Params whose bank holds exactly ``track`` (a single, un-batched ``Track``), e.g. for replays."""
    if not isinstance(track, Track) or jnp.ndim(track.num_points) != 0:
        raise ValueError("with_track needs a single (un-batched) Track, e.g. from track_from_arrays")
    return with_bank(params, stack_tracks([track]))


@functools.lru_cache(maxsize=8)
def _cached_bank(seed: int, size: int, dtype_name: str) -> Track:
    return make_track_bank(jax.random.PRNGKey(seed), size)


def track_bank(seed: int = 0, size: int = DEFAULT_BANK_SIZE) -> Track:
    """A bank of ``size`` generated tracks (leading axis), cached per (seed, size, dtype)."""
    if int(size) < 1:
        raise ValueError(f"track_bank_size must be a positive integer, got {size!r}")
    return _cached_bank(int(seed), int(size), str(default_float()))


def default_racing_params(env) -> RacingParams:
    """``env.default_params`` of a racing env: what ``envs.make`` gives it without overrides (the
    default bank, prepared for ``env``), cached per (env configuration, dtype), so that
    ``env.reset(key)`` works without params as in gymnax."""
    return _cached_default_params(env, str(default_float()))


@functools.lru_cache(maxsize=8)
def _cached_default_params(env, dtype_name: str) -> RacingParams:
    return env.prepare(with_bank(RacingParams(vehicle=VehicleParams(), tracks=None), track_bank()))
