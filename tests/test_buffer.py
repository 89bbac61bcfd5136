"""Replay buffer: exact next observations, truncation handling, codecs, wrap-around, seeds."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from xrl_jax.buffer import (
    CONE_SET_CODEC,
    buffer_add,
    buffer_add_packed,
    buffer_init,
    buffer_sample,
    bytes_per_transition,
    decode_obs,
    encode_obs,
)

NUM_ENVS = 3
sample_batch = jax.jit(buffer_sample, static_argnums=2)
add_row = jax.jit(buffer_add)


def cone_obs(step, env):
    """A deterministic cone observation that encodes (step, env) in its values."""
    cones = np.zeros((6, 5), np.float32)
    count = 1 + (step + env) % 5
    cones[:count, 0] = 1
    cones[:count, 1] = step / 100 + np.arange(count) / 1000
    cones[:count, 2] = env / 10
    kinds = (np.arange(count) + step) % 2
    cones[:count, 3] = kinds == 0
    cones[:count, 4] = kinds == 1
    return {"state": np.full(2, step + 10 * env, np.float32), "cones_set": cones}


def stacked_obs(step):
    per_env = [cone_obs(step, e) for e in range(NUM_ENVS)]
    return {k: jnp.asarray(np.stack([o[k] for o in per_env])) for k in per_env[0]}


def fill(buffer, steps, truncate_at=(), explicit=False):
    """Feed `steps` rows; row t: obs(t), action t, reward t, next obs obs(t+1)."""
    for t in range(steps):
        truncated = jnp.array([t in truncate_at] * NUM_ENVS)
        terminated = jnp.array([t % 7 == 6] * NUM_ENVS) & ~truncated
        action = jnp.full((NUM_ENVS, 2), t, jnp.float32)
        reward = jnp.full((NUM_ENVS,), float(t))
        next_obs = stacked_obs(t + 1) if explicit else None
        buffer = add_row(buffer, stacked_obs(t), action, reward, terminated, truncated, next_obs)
    return buffer


def example():
    return cone_obs(0, 0), np.zeros(2, np.float32)


def test_codec_is_lossless():
    rows = jnp.asarray(np.stack([cone_obs(s, e)["cones_set"] for s in range(5) for e in range(3)]))
    decoded = CONE_SET_CODEC.decode(CONE_SET_CODEC.encode(rows))
    np.testing.assert_array_equal(decoded, rows)
    obs = {k: jnp.asarray(v) for k, v in cone_obs(3, 1).items()}
    back = decode_obs(encode_obs(obs, {"cones_set": CONE_SET_CODEC}), {"cones_set": CONE_SET_CODEC})
    for k in obs:
        np.testing.assert_array_equal(back[k], obs[k])


@pytest.mark.parametrize("layout", ["compact", "explicit"])
def test_samples_are_exact_transitions(layout):
    buffer = buffer_init(*example(), capacity=60, num_envs=NUM_ENVS, layout=layout)
    buffer = fill(buffer, 12, explicit=layout == "explicit")
    batch = sample_batch(buffer, jax.random.PRNGKey(0), 256)
    steps = np.asarray(batch["reward"]).astype(int)
    envs = np.asarray(batch["obs"]["cones_set"][:, 0, 2] * 10).round().astype(int)
    seen_steps = set(steps.tolist())
    assert seen_steps <= set(range(11 if layout == "compact" else 12))
    assert len(seen_steps) >= 10
    for i, (t, e) in enumerate(zip(steps, envs, strict=True)):
        expected, expected_next = cone_obs(t, e), cone_obs(t + 1, e)
        for k in expected:
            np.testing.assert_array_equal(batch["obs"][k][i], expected[k])
            np.testing.assert_array_equal(batch["next_obs"][k][i], expected_next[k])
        np.testing.assert_array_equal(batch["action"][i], [t, t])
        assert bool(batch["terminated"][i]) == (t % 7 == 6)


def test_compact_layout_never_samples_truncated_transitions():
    buffer = buffer_init(*example(), capacity=60, num_envs=NUM_ENVS)
    buffer = fill(buffer, 12, truncate_at=(2, 5, 6))
    batch = sample_batch(buffer, jax.random.PRNGKey(1), 2000)
    sampled = set(np.asarray(batch["reward"]).astype(int).tolist())
    assert sampled == set(range(11)) - {2, 5, 6}


def test_sampling_ends_when_no_transition_is_valid():
    # The redraw loop is bounded (MAX_REDRAWS): with nothing valid it gives up instead of spinning.
    buffer = buffer_init(*example(), capacity=60, num_envs=NUM_ENVS)
    buffer = fill(buffer, 3, truncate_at=(0, 1))  # readable rows 0 and 1, both truncated
    batch = sample_batch(buffer, jax.random.PRNGKey(1), 8)
    assert set(np.asarray(batch["reward"]).astype(int).tolist()) <= {0, 1}


def test_explicit_layout_keeps_truncated_transitions():
    buffer = buffer_init(*example(), capacity=60, num_envs=NUM_ENVS, layout="explicit")
    buffer = fill(buffer, 12, truncate_at=(2, 5), explicit=True)
    sampled = set(
        np.asarray(sample_batch(buffer, jax.random.PRNGKey(1), 2000)["reward"]).astype(int).tolist()
    )
    assert {2, 5} <= sampled


def test_ring_overwrites_oldest_rows():
    buffer = buffer_init(*example(), capacity=5 * NUM_ENVS, num_envs=NUM_ENVS)  # 5 rows + 1
    buffer = fill(buffer, 20)
    batch = sample_batch(buffer, jax.random.PRNGKey(2), 1000)
    steps = np.asarray(batch["reward"]).astype(int)
    assert set(steps.tolist()) == set(range(14, 19))  # row 19 still waits for its next obs
    np.testing.assert_array_equal(batch["next_obs"]["state"][:, 0] % 10, (steps + 1) % 10)


def test_sampling_is_uniform():
    buffer = buffer_init(*example(), capacity=60, num_envs=NUM_ENVS)
    buffer = fill(buffer, 11)
    steps = np.asarray(sample_batch(buffer, jax.random.PRNGKey(3), 20000)["reward"]).astype(int)
    counts = np.bincount(steps, minlength=10)
    np.testing.assert_allclose(counts / counts.sum(), 0.1, atol=0.015)


def test_vmap_over_seeds_and_determinism():
    one = buffer_init(*example(), capacity=30, num_envs=NUM_ENVS)
    seeds = jax.tree.map(lambda x: jnp.stack([x, x]), one)
    obs = jax.tree.map(lambda x: jnp.stack([x, x + 1]), stacked_obs(0))
    zeros = jnp.zeros((2, NUM_ENVS), bool)
    add = jax.vmap(buffer_add)
    seeds = add(seeds, obs, jnp.zeros((2, NUM_ENVS, 2)), jnp.ones((2, NUM_ENVS)), zeros, zeros)
    seeds = add(seeds, obs, jnp.zeros((2, NUM_ENVS, 2)), jnp.ones((2, NUM_ENVS)), zeros, zeros)
    # The same key for both seeds draws the same slots, so the seeds' data must differ by exactly 1.
    sample = jax.jit(jax.vmap(buffer_sample, in_axes=(0, None, None)), static_argnums=2)
    key = jax.random.PRNGKey(0)
    a, b = sample(seeds, key, 8), sample(seeds, key, 8)
    np.testing.assert_array_equal(a["obs"]["state"], b["obs"]["state"])
    assert a["obs"]["state"].shape == (2, 8, 2)
    np.testing.assert_array_equal(a["obs"]["state"][1] - a["obs"]["state"][0], 1.0)


def test_country_road_memory_budget():
    obs = {"state": np.zeros(6, np.float32), "cones_set": np.zeros((100, 5), np.float32)}
    compact = buffer_init(obs, np.zeros(3, np.float32), capacity=1000, num_envs=4)
    explicit = buffer_init(obs, np.zeros(3, np.float32), capacity=1000, num_envs=4, layout="explicit")
    naive = 2 * (6 + 100 * 5) * 4 + 3 * 4 + 4 + 1
    assert bytes_per_transition(compact) < 0.25 * naive
    assert bytes_per_transition(explicit) < 0.5 * naive
    # 20 seeds x 1e6 transitions fit in the 40 GB budget with the default layout.
    assert 20 * 1e6 * bytes_per_transition(compact) < 40e9 / 2


def test_bad_arguments():
    with pytest.raises(ValueError, match="valid layouts: compact, explicit"):
        buffer_init(*example(), capacity=10, layout="fancy")
    with pytest.raises(ValueError, match="positive"):
        buffer_init(*example(), capacity=0)
    explicit = buffer_init(*example(), capacity=10, num_envs=NUM_ENVS, layout="explicit")
    with pytest.raises(ValueError, match="needs next_obs"):
        zeros = jnp.zeros(NUM_ENVS, bool)
        buffer_add(explicit, stacked_obs(0), jnp.zeros((NUM_ENVS, 2)), jnp.zeros(NUM_ENVS), zeros, zeros)


def test_packed_add_keeps_only_valid_transitions_in_order():
    """Multi-agent adds: the valid transitions of each call land in consecutive rows, in order,
    wrap around the ring, and sampling returns only them (no holes, no redraws needed)."""
    add = jax.jit(buffer_add_packed)
    buffer = buffer_init(
        {"state": np.zeros(2, np.float32)}, np.zeros(1, np.float32), 10, 1, layout="explicit"
    )
    written = []
    for call in range(5):
        ids = np.arange(4) + 4 * call
        valid = jnp.asarray((ids % 3) != 1)
        obs = {"state": jnp.asarray(np.stack([ids, ids], 1), jnp.float32)}
        next_obs = {"state": obs["state"] + 0.5}
        buffer = add(
            buffer,
            obs,
            jnp.asarray(ids[:, None], jnp.float32),
            jnp.asarray(ids, jnp.float32),
            jnp.zeros(4, bool),
            next_obs,
            valid,
        )
        written += [int(i) for i in ids if i % 3 != 1]
    assert int(buffer.filled_rows) == 10
    newest_ten = written[-10:]
    stored = np.asarray(buffer.reward[:, 0])
    assert sorted(stored.tolist()) == sorted(float(i) for i in newest_ten)
    assert int(buffer.write_row) == len(written) % 10
    batch = sample_batch(buffer, jax.random.PRNGKey(0), 64)
    np.testing.assert_array_equal(batch["obs"]["state"][:, 0], batch["reward"])
    np.testing.assert_array_equal(batch["next_obs"]["state"][:, 0], batch["reward"] + 0.5)
    assert set(np.asarray(batch["reward"]).astype(int)) <= set(newest_ten)
    compact = buffer_init({"state": np.zeros(2, np.float32)}, np.zeros(1, np.float32), 10, 1)
    with pytest.raises(ValueError, match="explicit"):
        buffer_add_packed(compact, obs, jnp.zeros((4, 1)), jnp.zeros(4), jnp.zeros(4, bool), next_obs, valid)
