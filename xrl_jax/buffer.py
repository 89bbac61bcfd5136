"""Device-resident replay buffer as a pytree: ``buffer_init / buffer_add / buffer_sample``.

Memory is the constraint that shapes this module: 20 seeds × 10⁶ Country Road transitions with
observation and next observation stored as float32 ``(100, 5)`` cone sets would need ~80 GB. Two
lossless measures bring it under 20 GB:

1. **Each observation is stored once** (``layout="compact"``, the default). The buffer holds rows of
   ``E`` transitions, one row per vector-env step, time-major per env. The next observation of row
   ``i``, env ``e`` is the observation of row ``i + 1``, env ``e``. At an episode end that row holds
   the reset observation instead of the final one: harmless for a *terminated* transition (its
   bootstrap is masked) and wrong for a *truncated* one, which is why truncated transitions are
   marked invalid and never sampled — exactly the reference's "drop truncated" rule (docs/algorithms.md §5.3).
   ``layout="explicit"`` stores ``next_obs`` separately (twice the observation memory) so that
   truncated transitions can be kept and bootstrapped from their true final observation.
2. **One-hot set columns are stored as one integer code** (:class:`SetCodec`): a cone row
   ``[present, x, y, is_blue, is_yellow]`` becomes ``(x, y)`` float32 plus an int8 kind
   (0 absent, 1 blue, 2 yellow), 9 bytes instead of 20, decoded exactly.

Sampling is uniform over valid stored transitions, with replacement, in O(batch): candidates are
drawn uniformly and invalid ones redrawn (a bounded ``while_loop``; invalid transitions are rare).
Everything is pure and jittable, and vmaps over a leading seed axis.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

LAYOUTS = ("compact", "explicit")
MAX_REDRAWS = 64


@dataclass(frozen=True)
class SetCodec:
    """Stores a padded object set ``(..., O, F)`` whose column 0 is the present flag and whose
    ``onehot_columns`` are a one-hot kind, as the remaining float columns plus one int8 kind code.

    The kind code is 0 for an absent row and ``1 + j`` for a present row whose one-hot is column
    ``onehot_columns[j]``. Absent rows decode to all zeros, as the sensors produce them.
    """

    num_columns: int
    onehot_columns: tuple[int, ...]

    @property
    def float_columns(self) -> tuple[int, ...]:
        return tuple(c for c in range(1, self.num_columns) if c not in self.onehot_columns)

    def encode(self, rows: jax.Array) -> dict[str, jax.Array]:
        present = rows[..., 0] > 0.5
        onehot = rows[..., list(self.onehot_columns)]
        kind = jnp.where(present, 1 + jnp.argmax(onehot, axis=-1), 0).astype(jnp.int8)
        return {"values": rows[..., list(self.float_columns)].astype(jnp.float32), "kind": kind}

    def decode(self, stored: Mapping[str, jax.Array]) -> jax.Array:
        kind = stored["kind"].astype(jnp.int32)
        dtype = stored["values"].dtype
        columns = [None] * self.num_columns
        columns[0] = (kind > 0).astype(dtype)
        for index, column in enumerate(self.float_columns):
            columns[column] = stored["values"][..., index]
        for index, column in enumerate(self.onehot_columns):
            columns[column] = (kind == index + 1).astype(dtype)
        return jnp.stack(columns, axis=-1)


# Country Road cones: [present, x, y, is_type1 (blue, right), is_type2 (yellow, left)].
CONE_SET_CODEC = SetCodec(num_columns=5, onehot_columns=(3, 4))
DEFAULT_CODECS: dict[str, SetCodec] = {"cones_set": CONE_SET_CODEC}


def encode_obs(obs: Mapping[str, jax.Array], codecs: Mapping[str, SetCodec]) -> dict[str, Any]:
    return {k: codecs[k].encode(v) if k in codecs else v.astype(jnp.float32) for k, v in obs.items()}


def decode_obs(stored: Mapping[str, Any], codecs: Mapping[str, SetCodec]) -> dict[str, jax.Array]:
    return {k: codecs[k].decode(v) if k in codecs else v for k, v in stored.items()}


@struct.dataclass
class ReplayBuffer:
    """Ring buffer of ``rows`` × ``num_envs`` transitions (leading axes ``[row, env]``).

    ``write_row`` is the next row to write; ``filled_rows`` how many rows hold data (≤ rows).
    """

    obs: Any
    next_obs: Any  # ``None`` in the compact layout
    action: jax.Array
    reward: jax.Array
    terminated: jax.Array
    valid: jax.Array
    write_row: jax.Array
    filled_rows: jax.Array
    codecs: Mapping[str, SetCodec] = struct.field(pytree_node=False)
    layout: str = struct.field(pytree_node=False)

    @property
    def rows(self) -> int:
        return self.reward.shape[-2]

    @property
    def num_envs(self) -> int:
        return self.reward.shape[-1]

    @property
    def capacity(self) -> int:
        return self.rows * self.num_envs


def buffer_init(
    obs_example: Mapping[str, Any],
    action_example: Any,
    capacity: int,
    num_envs: int = 1,
    *,
    layout: str = "compact",
    codecs: Mapping[str, SetCodec] | None = None,
) -> ReplayBuffer:
    """An empty buffer for at least ``capacity`` transitions collected by ``num_envs`` envs.

    ``obs_example``/``action_example`` are ONE env's observation dict and action (shapes and
    dtypes only). The capacity is rounded up to whole rows of ``num_envs``; the compact layout
    adds one row, because the newest row is only readable as a next observation.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"unknown buffer layout {layout!r}; valid layouts: {', '.join(LAYOUTS)}")
    if int(capacity) < 1 or int(num_envs) < 1:
        raise ValueError(f"capacity and num_envs must be positive, got {capacity} and {num_envs}")
    codecs = dict(DEFAULT_CODECS if codecs is None else codecs)
    codecs = {k: c for k, c in codecs.items() if k in obs_example}
    rows = -(-int(capacity) // int(num_envs)) + (1 if layout == "compact" else 0)

    def zeros(x):
        x = jnp.asarray(x)
        return jnp.zeros((rows, num_envs, *x.shape), x.dtype)

    stored_obs = jax.tree.map(zeros, encode_obs({k: jnp.asarray(v) for k, v in obs_example.items()}, codecs))
    action = jnp.asarray(action_example)
    return ReplayBuffer(
        obs=stored_obs,
        next_obs=jax.tree.map(jnp.zeros_like, stored_obs) if layout == "explicit" else None,
        action=zeros(action.astype(jnp.int32 if jnp.issubdtype(action.dtype, jnp.integer) else jnp.float32)),
        reward=jnp.zeros((rows, num_envs), jnp.float32),
        terminated=jnp.zeros((rows, num_envs), bool),
        valid=jnp.zeros((rows, num_envs), bool),
        write_row=jnp.zeros((), jnp.int32),
        filled_rows=jnp.zeros((), jnp.int32),
        codecs=codecs,
        layout=layout,
    )


def buffer_add(
    buffer: ReplayBuffer,
    obs: Mapping[str, jax.Array],
    action: jax.Array,
    reward: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    next_obs: Mapping[str, jax.Array] | None = None,
) -> ReplayBuffer:
    """Append one row: the transitions of all ``num_envs`` envs from one vector-env step.

    ``obs`` is the observation the action was taken in. In the explicit layout ``next_obs`` is
    required and must be the step's *final* observation (``info["final_obs"]`` of the auto-reset
    wrapper); truncated transitions are then kept. In the compact layout they are marked invalid.
    """
    row = buffer.write_row

    def put(store, value):
        return jax.lax.dynamic_update_index_in_dim(store, value.astype(store.dtype), row, axis=0)

    explicit = buffer.layout == "explicit"
    if explicit and next_obs is None:
        raise ValueError("the explicit buffer layout needs next_obs (the step's final observation)")
    valid = jnp.ones_like(truncated, dtype=bool) if explicit else ~truncated
    return buffer.replace(
        obs=jax.tree.map(put, buffer.obs, encode_obs(obs, buffer.codecs)),
        next_obs=(
            jax.tree.map(put, buffer.next_obs, encode_obs(next_obs, buffer.codecs)) if explicit else None
        ),
        action=put(buffer.action, action),
        reward=put(buffer.reward, reward),
        terminated=put(buffer.terminated, terminated),
        valid=put(buffer.valid, valid),
        write_row=(row + 1) % buffer.rows,
        filled_rows=jnp.minimum(buffer.filled_rows + 1, buffer.rows),
    )


def buffer_add_packed(
    buffer: ReplayBuffer,
    obs: Mapping[str, jax.Array],
    action: jax.Array,
    reward: jax.Array,
    terminated: jax.Array,
    next_obs: Mapping[str, jax.Array],
    valid: jax.Array,
) -> ReplayBuffer:
    """Append only the ``valid`` ones of a flat batch of ``n`` transitions, packed one per row.

    For multi-agent rollouts, where each env step yields a varying number of agent transitions (the
    agents alive at the start of the step): the valid ones go to consecutive rows, so the buffer holds
    no holes and sampling needs no redraws. Needs the explicit layout with ``num_envs == 1``; every
    leading-axis-``n`` input is one transition. Transitions flagged truncated must be passed with
    ``terminated=False`` (they are bootstrapped from ``next_obs``).
    """
    if buffer.layout != "explicit" or buffer.num_envs != 1:
        raise ValueError("buffer_add_packed needs an explicit-layout buffer with num_envs=1")
    count = valid.shape[0]
    if count > buffer.rows:
        raise ValueError(f"{count} transitions per add exceed the buffer's {buffer.rows} rows")
    offset = jnp.cumsum(valid.astype(jnp.int32)) - 1
    target = jnp.where(valid, (buffer.write_row + offset) % buffer.rows, buffer.rows)  # rows: dropped
    added = jnp.sum(valid, dtype=jnp.int32)

    def put(store, value):
        return store.at[target, 0].set(value.astype(store.dtype), mode="drop")

    return buffer.replace(
        obs=jax.tree.map(put, buffer.obs, encode_obs(obs, buffer.codecs)),
        next_obs=jax.tree.map(put, buffer.next_obs, encode_obs(next_obs, buffer.codecs)),
        action=put(buffer.action, action),
        reward=put(buffer.reward, reward),
        terminated=put(buffer.terminated, terminated),
        valid=put(buffer.valid, jnp.ones_like(valid)),
        write_row=(buffer.write_row + added) % buffer.rows,
        filled_rows=jnp.minimum(buffer.filled_rows + added, buffer.rows),
    )


def readable_rows(buffer: ReplayBuffer) -> jax.Array:
    """Rows that can be sampled: in the compact layout the newest row still lacks its next obs."""
    if buffer.layout == "compact":
        return jnp.maximum(buffer.filled_rows - 1, 0)
    return buffer.filled_rows


def buffer_sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> dict[str, Any]:
    """``batch_size`` valid transitions, uniformly with replacement.

    Returns ``{"obs", "action", "reward", "next_obs", "terminated"}`` with decoded observations.
    The caller must only sample once at least one valid transition is stored (the trainer's
    warm-up guarantees it); otherwise the returned transitions are arbitrary.
    """
    readable = readable_rows(buffer)
    oldest = (buffer.write_row - buffer.filled_rows) % buffer.rows

    def draw(key):
        flat = jax.random.randint(key, (batch_size,), 0, jnp.maximum(readable, 1) * buffer.num_envs)
        offset, env = flat // buffer.num_envs, flat % buffer.num_envs
        return (oldest + offset) % buffer.rows, env

    def is_valid(rows, envs):
        return buffer.valid[rows, envs]

    def redraw(carry):
        key, rows, envs, count = carry
        key, sub = jax.random.split(key)
        new_rows, new_envs = draw(sub)
        keep = is_valid(rows, envs)
        return key, jnp.where(keep, rows, new_rows), jnp.where(keep, envs, new_envs), count + 1

    def needs_redraw(carry):
        # Ends after at most MAX_REDRAWS rounds whatever the buffer holds (the loop reads only keys and
        # the boolean valid flags, nothing that can be NaN). The bound only matters when invalid
        # transitions are common: with an invalid fraction p a candidate is still invalid after it
        # with probability p**MAX_REDRAWS (below 1e-170 for the ~1/600 truncated steps of the compact layout).
        # A buffer with no valid transition returns invalid ones after the last round.
        _, rows, envs, count = carry
        return jnp.any(~is_valid(rows, envs)) & (count < MAX_REDRAWS)

    key, sub = jax.random.split(key)
    rows, envs = draw(sub)
    _, rows, envs, _ = jax.lax.while_loop(needs_redraw, redraw, (key, rows, envs, jnp.zeros((), jnp.int32)))

    def gather(store, at_rows):
        return store[at_rows, envs]

    if buffer.layout == "compact":
        next_stored = jax.tree.map(lambda s: gather(s, (rows + 1) % buffer.rows), buffer.obs)
    else:
        next_stored = jax.tree.map(lambda s: gather(s, rows), buffer.next_obs)
    return {
        "obs": decode_obs(jax.tree.map(lambda s: gather(s, rows), buffer.obs), buffer.codecs),
        "action": gather(buffer.action, rows),
        "reward": gather(buffer.reward, rows),
        "next_obs": decode_obs(next_stored, buffer.codecs),
        "terminated": gather(buffer.terminated, rows),
    }


def bytes_per_transition(buffer: ReplayBuffer) -> float:
    """Device bytes per transition slot (works for a seed-batched buffer too)."""
    return sum(x.nbytes for x in jax.tree.leaves(buffer)) / buffer.reward.size
