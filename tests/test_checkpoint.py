"""Orbax checkpoints of the run state: exact round trip, newest-only retention, crash safety."""

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from xrl_jax.buffer import buffer_add, buffer_init
from xrl_jax.checkpoint import Checkpointer, latest_step, restore_checkpoint, save_checkpoint


@struct.dataclass
class Example:
    """Mimics the trainer's run state: nested dicts, a buffer with None fields, keys, static data."""

    params: Any
    buffer: Any
    key: jax.Array
    counter: jax.Array
    name: str = struct.field(pytree_node=False, default="run")


def make_state(offset: float = 0.0) -> Example:
    obs = {"state": jnp.zeros(3), "cones_set": jnp.zeros((4, 5))}
    buffer = buffer_init(obs, jnp.zeros(3), capacity=8, num_envs=2)
    cones = jnp.zeros((2, 4, 5)).at[:, 0, 0].set(1).at[:, 0, 1].set(0.25 + offset).at[:, 0, 3].set(1)
    buffer = buffer_add(
        buffer,
        {"state": jnp.full((2, 3), 0.5 + offset), "cones_set": cones},
        jnp.ones((2, 3)),
        jnp.array([1.0, -1.0]),
        jnp.array([False, True]),
        jnp.array([True, False]),
    )
    return Example(
        params={"w": jnp.arange(6.0).reshape(2, 3) + offset, "b": jnp.float32(offset)},
        buffer=buffer,
        key=jax.random.PRNGKey(7),
        counter=jnp.int32(3),
    )


def assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_round_trip_is_exact_and_keeps_metadata(tmp_path):
    state = make_state(0.125)
    save_checkpoint(tmp_path, 64, state, {"next_chunk": 1, "seeds": [0, 1]})
    restored, meta = restore_checkpoint(tmp_path, jax.eval_shape(lambda: state))
    assert_trees_equal(state, restored)
    assert meta == {"next_chunk": 1, "seeds": [0, 1]}
    assert restored.name == "run" and restored.buffer.next_obs is None


def test_only_the_newest_is_kept_and_restored(tmp_path):
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save(10, make_state(1.0), {"step": 10})
    checkpointer.save(20, make_state(2.0), {"step": 20})
    checkpointer.close()
    assert latest_step(tmp_path) == 20
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["20"]
    restored, meta = restore_checkpoint(tmp_path, jax.eval_shape(make_state))
    assert meta["step"] == 20
    assert float(restored.params["b"]) == 2.0


def test_an_interrupted_save_does_not_hide_the_last_good_checkpoint(tmp_path):
    save_checkpoint(tmp_path, 10, make_state(1.0), {"step": 10})
    # What a crash in the middle of writing step 20 leaves behind: an uncommitted temporary folder.
    partial = tmp_path / "20.orbax-checkpoint-tmp-1234"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "garbage").write_bytes(b"\x00" * 10)
    assert latest_step(tmp_path) == 10
    restored, meta = restore_checkpoint(tmp_path, jax.eval_shape(make_state))
    assert meta["step"] == 10
    assert_trees_equal(restored, make_state(1.0))


def test_missing_checkpoint_raises(tmp_path):
    assert latest_step(tmp_path / "absent") is None
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        restore_checkpoint(tmp_path, jax.eval_shape(make_state))
    with pytest.raises(ValueError, match="max_to_keep"):
        Checkpointer(tmp_path, max_to_keep=0)
