"""Fresh tracks for training: every episode starts on a track that was never used before.

The original trainer generates a new random track at every reset (docs/carenv-single-agent.md §5),
so a 10⁶-step run drives thousands of different tracks. Generating inside ``reset`` is a poor fit
for vectorised training: under ``vmap`` an auto-reset computes the reset of every env at every step,
i.e. one track generation per env step, which costs far more than the step itself. A
:class:`TrackFeed` instead keeps ``capacity`` generated tracks ahead, prepared as a bank (tables and
reset observations, so a reset stays a gather), and hands them out in order:

* track number ``n`` of a feed is ``generate_track(fold_in(key, n))``, a pure function of the feed's
  key and ``n``; episodes take the numbers 0, 1, 2, ... in the order they start (envs ending at the
  same step in env order). Which track an episode gets therefore does not depend on when, or how
  much, the feed is refilled;
* :func:`refill_feed` generates the next numbers into the slots whose tracks have been handed out
  and are not being driven (a track never changes under a running episode, however long it lasts);
  a trainer calls it between chunks of steps, away from the per-step hot path;
* should a feed run dry (more episodes between refills than tracks ready), the reset drives a track
  that was used before and ``reused`` counts it: the run stays correct, only less fresh, and says so.

``issued`` is the number of distinct tracks driven so far; memory is fixed (``capacity`` tracks, about
53 KB each in float32), however many episodes a run has.

:class:`FreshTrackEnvs` packages a feed and its envs as a vector env like any other (the feed is part
of its state, the refill its :meth:`~FreshTrackEnvs.refill`), so that a trainer restarts episodes the
same way whichever envs it drives.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from envs.core import VmapWrapper
from envs.racing import RacingEnv, RacingParams, with_bank
from envs.track_generator import generate_track, generation_batch_size

# The params fields with a leading bank axis; refills write these slot by slot.
_BANK_FIELDS = ("tracks", "tables", "start_s", "reset_obs")


@struct.dataclass
class TrackFeed:
    """``capacity`` prepared tracks, which track number each slot holds, and the feed's counters."""

    params: RacingParams  # a bank of ``capacity`` tracks with its reset cache
    key: jax.Array  # the feed's stream: track n = generate_track(fold_in(key, n))
    slot_number: jax.Array  # (capacity,) int32: the track number each slot holds
    issued: jax.Array  # int32: tracks handed to episodes, all distinct
    generated: jax.Array  # int32: tracks generated so far (numbers 0 .. generated - 1)
    reused: jax.Array  # int32: resets that found the feed empty and drove an old track again
    driving: jax.Array  # (E,) int32: the slot each env's current episode drives

    @property
    def capacity(self) -> int:
        return int(self.slot_number.shape[-1])


def writable(feed: TrackFeed, count: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(numbers, slots, write)``: the next ``count`` track numbers, the slot each would go to, and
    which of them a refill writes now (as many as there are free slots: handed out and not driven;
    always a prefix, so the generated tracks stay numbered without gaps). Works on a batch of feeds
    (leading axes)."""
    if not 1 <= int(count) <= feed.capacity:
        raise ValueError(f"a refill writes 1..capacity ({feed.capacity}) tracks, got {count}")
    slot_ids = jnp.arange(feed.capacity, dtype=jnp.int32)
    driven = jnp.any(slot_ids[:, None] == feed.driving[..., None, :], axis=-1)  # (*batch, capacity)
    free = (feed.slot_number < feed.issued[..., None]) & ~driven
    slots = jnp.argsort(~free, axis=-1, stable=True)[..., : int(count)].astype(jnp.int32)  # free ones first
    write = jnp.arange(int(count)) < jnp.sum(free, axis=-1, keepdims=True)
    numbers = feed.generated[..., None] + jnp.arange(int(count), dtype=jnp.int32)
    return numbers, slots, write


def _generate(keys: jax.Array, numbers: jax.Array):
    """Tracks ``numbers`` (any shape) of the streams ``keys`` (same leading shape), generated a few at a
    time whatever the batch shape: the generator's temporaries are a few MB per track in flight."""
    flat_keys = jax.vmap(jax.random.fold_in)(
        keys.reshape(-1, *keys.shape[numbers.ndim :]), numbers.reshape(-1)
    )
    tracks = jax.lax.map(
        generate_track, flat_keys, batch_size=min(generation_batch_size(), flat_keys.shape[0])
    )
    return jax.tree.map(lambda leaf: leaf.reshape(numbers.shape + leaf.shape[1:]), tracks)


def _prepared(env: RacingEnv, template: RacingParams, tracks) -> RacingParams:
    """``template`` drawing from the bank ``tracks``, with its ring tables and reset cache."""
    return env.prepare(with_bank(template, tracks))


def init_feed(
    env: RacingEnv, template: RacingParams, key: jax.Array, capacity: int, num_envs: int
) -> TrackFeed:
    """A full feed of tracks 0 .. capacity - 1 of stream ``key`` for ``num_envs`` envs (``template``:
    the env's params, whose track bank is replaced). Start the envs with :func:`reset_with_feed`."""
    if not int(capacity) >= int(num_envs) >= 1:
        raise ValueError(f"need capacity >= num_envs >= 1, got capacity {capacity} and num_envs {num_envs}")
    numbers = jnp.arange(int(capacity), dtype=jnp.int32)
    tracks = _generate(jnp.broadcast_to(key, (int(capacity), *key.shape)), numbers)
    zero = jnp.zeros((), jnp.int32)
    driving = jnp.full((int(num_envs),), -1, jnp.int32)  # no env drives yet
    return TrackFeed(_prepared(env, template, tracks), key, numbers, zero, jnp.int32(capacity), zero, driving)


def refill_feed(env: RacingEnv, feed: TrackFeed, count: int) -> TrackFeed:
    """Generate the next ``count`` tracks (static) and write those that fit (see :func:`writable`).

    Works on one feed or on a batch of feeds (leading axes on every leaf, e.g. one feed per seed):
    then all ``count × batch`` tracks are generated together, a few at a time. Tracks that do not fit
    are dropped; being a function of their number only, they are generated again when their turn
    comes."""
    batch = feed.issued.shape
    numbers, slots, write = writable(feed, count)
    keys = jnp.broadcast_to(feed.key[..., None, :], (*numbers.shape, feed.key.shape[-1]))
    tracks = _generate(keys, numbers)

    def one(params, slot_number, new_tracks, numbers, slots, write):
        new = _prepared(env, params, new_tracks)

        def put(old, fresh):
            mask = write.reshape(write.shape + (1,) * (fresh.ndim - 1))
            return old.at[slots].set(jnp.where(mask, fresh, old[slots]))

        changes = {
            name: jax.tree.map(put, getattr(params, name), getattr(new, name)) for name in _BANK_FIELDS
        }
        return params.replace(**changes, reset_cache_for=params.reset_cache_for), put(slot_number, numbers)

    for _ in batch:  # one vmap per leading axis of the batch
        one = jax.vmap(one)
    params, slot_number = one(feed.params, feed.slot_number, tracks, numbers, slots, write)
    generated = feed.generated + jnp.sum(write, axis=-1, dtype=jnp.int32)
    return feed.replace(params=params, slot_number=slot_number, generated=generated)


def _take(feed: TrackFeed, starting: jax.Array):
    """Slots for the envs whose episode starts now (``starting``: (E,) bool), and the updated feed."""
    wanted = jnp.sum(starting, dtype=jnp.int32)
    numbers = feed.issued + jnp.cumsum(starting, dtype=jnp.int32) - 1
    holder = jnp.argmax(feed.slot_number[None, :] == numbers[:, None], axis=-1).astype(jnp.int32)
    # Past the generated tracks every slot holds a used one: drive slot n mod capacity again.
    slots = jnp.where(numbers < feed.generated, holder, numbers % feed.capacity)
    slots = jnp.where(starting, slots, feed.driving)
    fresh = jnp.clip(feed.generated - feed.issued, 0, wanted)
    return slots, feed.replace(issued=feed.issued + fresh, reused=feed.reused + wanted - fresh, driving=slots)


def reset_with_feed(env: RacingEnv, feed: TrackFeed):
    """``(obs, states, feed)``: the feed's envs (leading axis) starting on its next tracks."""
    slots, feed = _take(feed, jnp.ones(feed.driving.shape, bool))
    obs, states = jax.vmap(env.reset_on_track, in_axes=(None, 0))(feed.params, slots)
    return obs, states, feed


def step_with_feed(env: RacingEnv, key: jax.Array, states, actions, feed: TrackFeed):
    """One step of ``E`` envs (leading axis) that restart on the feed's next tracks when they end.

    Returns ``(obs, states, reward, terminated, truncated, info, feed)`` with the auto-reset
    convention of :class:`envs.core.AutoResetWrapper`: an ending env's ``obs``/``state`` are its new
    episode's and ``info["final_obs"]`` holds the observation of the ending step."""
    num_envs = jax.tree.leaves(states)[0].shape[0]
    keys = jax.random.split(key, num_envs)
    obs, stepped, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
        keys, states, actions, feed.params
    )
    done = terminated | truncated
    slots, feed = _take(feed, done)
    new_obs, new_states = jax.vmap(env.reset_on_track, in_axes=(None, 0))(feed.params, slots)

    def select(new, old):
        return jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old)

    info = dict(info, final_obs=obs)
    return (
        jax.tree.map(select, new_obs, obs),
        jax.tree.map(select, new_states, stepped),
        reward,
        terminated,
        truncated,
        info,
        feed,
    )


@struct.dataclass
class FedStates:
    """The state of :class:`FreshTrackEnvs`: its envs' states (leading env axis) and their feed."""

    envs: Any
    feed: TrackFeed


def split_states(state) -> tuple[Any, TrackFeed | None]:
    """``(envs' states, feed)`` of a vector env's state: the feed of :class:`FreshTrackEnvs`, None
    for any other vector env (whose state is its envs' states)."""
    return (state.envs, state.feed) if isinstance(state, FedStates) else (state, None)


def join_states(envs, feed: TrackFeed | None):
    """The inverse of :func:`split_states`."""
    return envs if feed is None else FedStates(envs, feed)


class FreshTrackEnvs(VmapWrapper):
    """``num_envs`` racing envs in lock-step that start every episode on the next track of their own
    feed of ``capacity`` tracks, with the auto-reset convention of :class:`envs.core.AutoResetWrapper`.

    ``reset(key, params)``: ``key`` is the feed's stream (its tracks are a function of it alone) and
    ``params`` a template whose track bank the feed replaces; ``step`` drives on the feed's tracks.
    :meth:`refill` writes ``refill_count`` new tracks when every one of them fits."""

    def __init__(self, env: RacingEnv, num_envs: int, capacity: int, refill_count: int):
        super().__init__(env, num_envs)
        if not 1 <= int(refill_count) <= int(capacity):
            raise ValueError(f"a refill writes 1..capacity ({capacity}) tracks, got {refill_count}")
        self.capacity = int(capacity)
        self.refill_count = int(refill_count)

    def reset_key(self, env_key: jax.Array, tracks_key: jax.Array) -> jax.Array:
        del env_key  # a fed reset draws nothing: the tracks come from the member's stream
        return tracks_key

    def reset_env(self, key, params):
        feed = init_feed(self._env, params, key, self.capacity, self.num_envs)
        obs, states, feed = reset_with_feed(self._env, feed)
        return obs, FedStates(states, feed)

    def step_env(self, key, state: FedStates, action, params):
        del params  # the envs drive on the feed's tracks
        *step, feed = step_with_feed(self._env, key, state.envs, action, state.feed)
        obs, states, reward, terminated, truncated, info = step
        return obs, FedStates(states, feed), reward, terminated, truncated, info

    def refill(self, state: FedStates, agree=lambda flag: flag) -> FedStates:
        """New tracks into every feed's free slots (a batch of states: leading axes) once some feed can
        take all ``refill_count`` of them; ``agree`` shares that decision between devices, so that it
        is a real branch: upkeep without a refill generates nothing. Which track an episode gets does
        not depend on when refills happen."""
        room = jnp.any(writable(state.feed, self.refill_count)[2][..., -1])  # room for all of them
        feed = jax.lax.cond(
            agree(room), lambda f: refill_feed(self._env, f, self.refill_count), lambda f: f, state.feed
        )
        return state.replace(feed=feed)

    def refill_bytes(self, state: FedStates) -> int:
        """A refill's new tracks before they are written in: half a feed's bytes."""
        leaves = jax.tree.leaves(state.feed)
        return int(sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in leaves)) // 2

    def counters(self, state: FedStates) -> dict[str, jax.Array]:
        """Distinct tracks driven so far, and resets that found the feed empty."""
        return {"tracks_used": state.feed.issued, "tracks_reused": state.feed.reused}
