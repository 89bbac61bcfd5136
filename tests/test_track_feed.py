"""The fresh-track feed (envs/track_feed.py): every episode on a new track, in a fixed order, with fixed
memory, whatever the refill schedule; driven tracks are never overwritten; a dry feed is counted."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.track_feed import (
    FreshTrackEnvs,
    init_feed,
    refill_feed,
    reset_with_feed,
    step_with_feed,
    writable,
)
from envs.track_generator import generate_track

CAPACITY, NUM_ENVS = 12, 4
KEY = jax.random.PRNGKey(3)
# Track lengths compare two compilations of the same float32 generator (the feed's batched refill and
# a lone generate_track): XLA may fuse them differently, so they agree to rounding, not bit for bit.
# A length of ~500-800 m sums ~400 segment lengths, each within a few ulps (float32 eps 1.2e-7):
# 400 * 4 * 1.2e-7 * 800 m ~ 0.15 m bounds it; different tracks differ by metres.
LENGTH_ATOL = 0.2
DRIVE = np.array([0.0, 0.3, -1.0], np.float32)  # gentle throttle: an episode that lasts


@pytest.fixture(scope="module")
def env_and_template():
    from xrl_jax.tracks import cached_track_bank

    bank = cached_track_bank(1, 1)
    return envs.make("tracking", track=jax.tree.map(lambda leaf: leaf[0], bank))


@pytest.fixture(scope="module")
def feed_functions(env_and_template):
    env, template = env_and_template
    init = jax.jit(lambda key: init_feed(env, template, key, CAPACITY, NUM_ENVS))
    step = jax.jit(lambda key, states, actions, feed: step_with_feed(env, key, states, actions, feed))
    refill = jax.jit(lambda feed, count: refill_feed(env, feed, count), static_argnums=1)
    return env, init, step, refill


@jax.jit
def _stream_lengths(numbers):
    return jax.vmap(lambda n: generate_track(jax.random.fold_in(KEY, n)).length)(numbers)


def _lengths_of_numbers(numbers, padded_to=32):
    """Lengths of the stream's tracks ``numbers``, each generated on its own (not by a feed); padded to
    one shape, so that every call reuses one compiled generator."""
    numbers = list(numbers)
    assert len(numbers) <= padded_to
    padded = jnp.asarray(numbers + [0] * (padded_to - len(numbers)), jnp.int32)
    return np.asarray(_stream_lengths(padded))[: len(numbers)]


def _drive(feed_functions, ending, steps, refill_every=None, refill_count=4):
    """Step NUM_ENVS envs ``steps`` times; ``ending[e]``: env e sends a NaN action (its episode ends at
    once, done_reason 4) instead of driving on. Returns the length of every new episode's track in
    start order, the final feed and the states."""
    env, init, step, refill = feed_functions
    feed = init(KEY)
    _, states, feed = reset_with_feed(env, feed)
    started = [float(x) for x in feed.params.tracks.length[states.track_index]]
    actions = np.where(np.asarray(ending)[:, None], np.nan, DRIVE).astype(np.float32)
    for t in range(steps):
        if refill_every and t % refill_every == 0:
            feed = refill(feed, refill_count)
        _, states, _, terminated, truncated, _, feed = step(jax.random.PRNGKey(t), states, actions, feed)
        done = np.asarray(terminated | truncated)
        started += [float(x) for x in np.asarray(feed.params.tracks.length[states.track_index])[done]]
    return np.array(started), feed, states


@pytest.mark.slow  # ~20 s; the trainer's fresh-track test (tests/test_train.py) stays in the default tier
def test_episodes_take_the_streams_tracks_in_order_and_a_refill_schedule_changes_nothing(feed_functions):
    """Three envs end every step (a NaN action), one drives on: with refills after every step or every
    other step the new episodes get tracks 0, 1, 2, ... of the stream, each exactly once."""
    ending = [False, True, True, True]
    eager, feed_a, _ = _drive(feed_functions, ending, steps=6, refill_every=1, refill_count=4)
    lazy, feed_b, _ = _drive(feed_functions, ending, steps=6, refill_every=2, refill_count=CAPACITY // 2 + 2)
    expected = _lengths_of_numbers(range(NUM_ENVS + 3 * 6))
    np.testing.assert_allclose(eager, expected, atol=LENGTH_ATOL)
    np.testing.assert_allclose(lazy, expected, atol=LENGTH_ATOL)
    assert len(np.unique(np.round(expected))) == len(expected)  # the stream's tracks are all different
    for feed in (feed_a, feed_b):
        assert int(feed.issued) == NUM_ENVS + 18 and int(feed.reused) == 0
        assert feed.params.tracks.length.shape == (CAPACITY,)  # memory does not grow


def test_a_refill_never_replaces_the_track_an_env_is_driving(feed_functions):
    _, feed, states = _drive(feed_functions, [False, True, True, True], steps=8, refill_every=1)
    first_track_length = _lengths_of_numbers([0])[0]
    assert int(states.step_count[0]) == 8  # env 0 drove on the whole time, on track 0
    np.testing.assert_allclose(
        float(feed.params.tracks.length[states.track_index[0]]), first_track_length, atol=LENGTH_ATOL
    )
    _, slots, write = writable(feed, 4)
    assert not np.any(np.asarray(write) & (np.asarray(slots) == int(states.track_index[0])))
    # ... and the written tracks are a prefix of the next numbers (no gaps in the numbering)
    assert list(np.asarray(write)) == sorted(np.asarray(write), reverse=True)


def test_a_dry_feed_reuses_old_tracks_and_counts_them(feed_functions):
    """Without refills the feed's tracks last for as many episodes, then resets reuse old ones, counted."""
    started, feed, _ = _drive(feed_functions, [True] * NUM_ENVS, steps=3)
    assert int(feed.issued) == CAPACITY and int(feed.reused) == 3 * NUM_ENVS + NUM_ENVS - CAPACITY
    np.testing.assert_allclose(started[:CAPACITY], _lengths_of_numbers(range(CAPACITY)), atol=LENGTH_ATOL)
    assert set(np.round(started[CAPACITY:], 3)) <= set(np.round(started[:CAPACITY], 3))


def test_final_obs_and_the_new_episode_follow_the_auto_reset_convention(feed_functions):
    env, init, step, _ = feed_functions
    feed = init(KEY)
    _, states, feed = reset_with_feed(env, feed)
    actions = np.stack([DRIVE, [np.nan] * 3, DRIVE, DRIVE]).astype(np.float32)
    new_obs, new_states, _, terminated, _, info, feed = step(jax.random.PRNGKey(0), states, actions, feed)
    assert list(np.asarray(terminated)) == [False, True, False, False]
    assert int(info["done_reason"][1]) == 4
    assert int(new_states.step_count[1]) == 0 and int(new_states.step_count[0]) == 1
    assert int(new_states.track_index[1]) == NUM_ENVS % CAPACITY  # track number 4
    reset_obs, _ = env.reset_on_track(feed.params, NUM_ENVS)
    np.testing.assert_array_equal(new_obs["trajectory_set"][1], reset_obs["trajectory_set"])
    assert not np.array_equal(info["final_obs"]["trajectory_set"][1], new_obs["trajectory_set"][1])
    np.testing.assert_array_equal(info["final_obs"]["state"][0], new_obs["state"][0])


def test_bad_arguments_are_refused(env_and_template, feed_functions):
    env, template = env_and_template
    with pytest.raises(ValueError, match="capacity >= num_envs"):
        init_feed(env, template, KEY, 2, 4)
    feed = feed_functions[1](KEY)
    with pytest.raises(ValueError, match=r"1\.\.capacity"):
        writable(feed, CAPACITY + 1)


@pytest.mark.slow  # ~20 s: a long drive compared step by step
def test_the_vector_env_drives_exactly_as_the_feed_functions(env_and_template, feed_functions):
    """:class:`FreshTrackEnvs` is the functions above behind the reset/step interface of any vector
    env: its reset key is the feed's stream, its state the envs' states and the feed, and its refill
    (on a batch of feeds) writes half a feed when every track fits."""
    env, template = env_and_template
    _, _, step, refill = feed_functions
    venv = FreshTrackEnvs(env, NUM_ENVS, CAPACITY, CAPACITY // 2)
    assert venv.reset_key(jax.random.PRNGKey(0), KEY) is KEY
    obs, fed = jax.jit(venv.reset)(KEY, template)
    # The same computation compiled the same way (params as an argument, not a folded constant).
    expected_obs, states, feed = jax.jit(
        lambda key, params: reset_with_feed(env, init_feed(env, params, key, CAPACITY, NUM_ENVS))
    )(KEY, template)
    actions = np.stack([DRIVE, [np.nan] * 3, DRIVE, DRIVE]).astype(np.float32)
    stepped = jax.jit(venv.step)(jax.random.PRNGKey(5), fed, actions, template)
    expected = step(jax.random.PRNGKey(5), states, actions, feed)
    for got, want in [(obs, expected_obs), (fed, (states, feed)), (stepped[0], expected[0]),
                      (stepped[1], (expected[1], expected[-1])), (stepped[2:], expected[2:-1])]:  # fmt: skip
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # A refill on a batch of one feed: one slot is free (env 1 moved on), so a refill of one track
    # writes it and one of half a feed waits until all of it fits.
    batch = jax.tree.map(lambda leaf: leaf[None], stepped[1])
    assert int(jax.jit(venv.refill)(batch).feed.generated[0]) == CAPACITY
    one_track = FreshTrackEnvs(env, NUM_ENVS, CAPACITY, 1)
    refilled = jax.jit(one_track.refill)(batch).feed
    manual = refill(expected[-1], 1)
    assert int(refilled.generated[0]) == int(manual.generated) == CAPACITY + 1
    np.testing.assert_array_equal(refilled.slot_number[0], manual.slot_number)
    counters = {name: int(value) for name, value in venv.counters(stepped[1]).items()}
    assert counters == {"tracks_used": NUM_ENVS + 1, "tracks_reused": 0}
