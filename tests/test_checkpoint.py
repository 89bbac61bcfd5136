"""Orbax checkpoints of the run state: exact round trip, retention, crash safety, damage detection."""

import shutil
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from xrl_jax.buffer import buffer_add, buffer_init
from xrl_jax.checkpoint import (
    MANIFEST_NAME,
    Checkpointer,
    CorruptCheckpointError,
    NoGoodCheckpointError,
    latest_step,
    restore_checkpoint,
    save_checkpoint,
)


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


def test_the_newest_two_are_kept_and_the_newest_restored(tmp_path):
    checkpointer = Checkpointer(tmp_path)
    for step in (10, 20, 30):
        checkpointer.save(step, make_state(step / 10), {"step": step})
    checkpointer.close()
    assert latest_step(tmp_path) == 30
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["20", "30"]
    restored, meta = restore_checkpoint(tmp_path, jax.eval_shape(make_state))
    assert meta["step"] == 30
    assert float(restored.params["b"]) == 3.0


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


# ---------------------------------------------------------------------------------------------
# Damaged checkpoints: detected before they are trusted, with a fallback to the previous one
# ---------------------------------------------------------------------------------------------


def _data_files(folder):
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.parent.name == "d")


def _flip_bytes(folder):
    """What the issue found: random bytes written into a data file (orbax restored them silently)."""
    for path in _data_files(folder / "state"):
        data = bytearray(path.read_bytes())
        middle = len(data) // 2
        data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
        path.write_bytes(bytes(data))


def _truncate(folder):
    for path in _data_files(folder / "state"):
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


DAMAGE = {
    "flipped bytes": _flip_bytes,
    "truncated data": _truncate,
    "broken metadata": lambda folder: (folder / "meta" / "metadata").write_text("{broken"),
    "broken array metadata": lambda folder: (folder / "state" / "_METADATA").write_text("garbage"),
    "missing state": lambda folder: shutil.rmtree(folder / "state"),
}


def _two_checkpoints(folder):
    checkpointer = Checkpointer(folder)
    checkpointer.save(10, make_state(1.0), {"step": 10})
    checkpointer.save(20, make_state(2.0), {"step": 20})
    return checkpointer


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_damaged_newest_checkpoint_falls_back_to_the_previous_one(tmp_path, damage):
    checkpointer = _two_checkpoints(tmp_path / "ckpt")
    DAMAGE[damage](tmp_path / "ckpt" / "20")
    lines = []
    state, meta = checkpointer.restore_newest_good(jax.eval_shape(make_state), log=lines.append)
    checkpointer.close()
    assert meta["step"] == 10
    assert_trees_equal(state, make_state(1.0))
    assert len(lines) == 1 and "ckpt/20 is damaged" in lines[0] and "falling back to step 10" in lines[0]
    # set aside, so that it is neither restored again nor in the way of a new save of step 20
    assert latest_step(tmp_path / "ckpt") == 10
    assert [p.name.split("-")[0] for p in (tmp_path / "ckpt.rejected").iterdir()] == ["20"]


def test_no_good_checkpoint_stops_with_every_reason(tmp_path):
    checkpointer = _two_checkpoints(tmp_path / "ckpt")
    _flip_bytes(tmp_path / "ckpt" / "20")
    shutil.rmtree(tmp_path / "ckpt" / "10" / "state")
    with pytest.raises(NoGoodCheckpointError) as info:
        checkpointer.restore_newest_good(jax.eval_shape(make_state), log=lambda _: None)
    checkpointer.close()
    message = str(info.value)
    assert "\n" not in message and "step 20: file state/" in message and "step 10: file state/" in message


def test_the_callers_check_rejects_a_checkpoint(tmp_path):
    """The trainer passes a finiteness check: a checkpoint that reads fine but holds NaN is refused."""
    checkpointer = _two_checkpoints(tmp_path / "ckpt")

    def check(state, meta):
        return "not finite" if meta["step"] == 20 else None

    lines = []
    _, meta = checkpointer.restore_newest_good(jax.eval_shape(make_state), check, lines.append)
    checkpointer.close()
    assert meta["step"] == 10 and "(not finite)" in lines[0]


def test_a_checkpoint_without_manifest_restores_with_a_warning(tmp_path):
    """Checkpoints of earlier versions have no manifest: they restore, and the log says unverified."""
    checkpointer = _two_checkpoints(tmp_path / "ckpt")
    for step in ("10", "20"):
        (tmp_path / "ckpt" / step / MANIFEST_NAME).unlink()
    lines = []
    _, meta = checkpointer.restore_newest_good(jax.eval_shape(make_state), log=lines.append)
    checkpointer.close()
    assert meta["step"] == 20 and len(lines) == 1 and "unverified" in lines[0]
    assert checkpointer.unverified_steps == [20]


def test_a_verified_checkpoint_is_preferred_to_a_newer_one_without_digests(tmp_path):
    """Issue 48 (e): a kill -9 between orbax's commit and the manifest leaves the newest checkpoint
    without digests; one flipped byte in it was then restored silently (a resume with other results).
    Nothing can tell such a checkpoint from a damaged one, so the older, verified checkpoint wins even
    over an intact one, and the newer one is set aside (the resume saves its step again)."""
    checkpointer = _two_checkpoints(tmp_path / "ckpt")
    (tmp_path / "ckpt" / "20" / MANIFEST_NAME).unlink()
    lines = []
    state, meta = checkpointer.restore_newest_good(jax.eval_shape(make_state), log=lines.append)
    checkpointer.close()
    assert meta["step"] == 10 and checkpointer.unverified_steps == []
    assert_trees_equal(state, make_state(1.0))
    assert len(lines) == 1 and "ckpt/20 has no file digests" in lines[0] and "verified step 10" in lines[0]
    assert latest_step(tmp_path / "ckpt") == 10
    assert [p.name.split("-")[0] for p in (tmp_path / "ckpt.rejected").iterdir()] == ["20"]


@struct.dataclass
class Before:
    """A state as an older version wrote it."""

    params: Any
    counter: jax.Array


@struct.dataclass
class After:
    """The same state with a field added since, listed as one whose zero the older version implied."""

    params: Any
    counter: jax.Array
    owed: Any = None
    FIELDS_ADDED_LATER: ClassVar[tuple[str, ...]] = ("owed",)


@struct.dataclass
class Unlisted:
    """The same state with a field added since that its class does not list."""

    params: Any
    counter: jax.Array
    owed: Any = None


def test_a_field_added_since_restores_as_zeros_and_any_other_difference_fails(tmp_path):
    checkpointer = Checkpointer(tmp_path)
    checkpointer.save(1, Before(params={"w": jnp.arange(3.0)}, counter=jnp.int32(4)), {"step": 1})
    owed = jax.ShapeDtypeStruct((2,), jnp.int32)
    abstract = After(params={"w": jax.ShapeDtypeStruct((3,), jnp.float32)}, counter=jnp.int32(0), owed=owed)
    # Read by a fresh checkpointer, as a resume in a new process reads it (the one that saved knew the
    # state's handler already, which hid that a fresh one could not read the state's metadata).
    state, meta = Checkpointer(tmp_path).restore(abstract)
    assert meta == {"step": 1} and int(state.counter) == 4
    np.testing.assert_array_equal(state.params["w"], np.arange(3.0))
    assert state.owed.shape == (2,) and state.owed.dtype == jnp.int32 and not np.any(state.owed)
    # A field the class does not list is a mismatch like any other: the checkpoint is unreadable.
    with pytest.raises(CorruptCheckpointError, match="unreadable"):
        checkpointer.restore(Unlisted(abstract.params, abstract.counter, owed))
