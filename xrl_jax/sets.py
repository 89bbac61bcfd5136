"""Per-object layers on the present objects only: packing the present rows of padded sets.

Observations pad every set to a fixed number of slots and flag the real objects in column 0. Most
slots are padding — about 70 % of Country Road's 100 cone slots and nine in ten of the
Intersection's vehicle slots (docs/performance.md) — yet a per-object layer computes the same
result whatever the padding holds. So the networks pack the present rows of a whole call (every set
of the batch) into one array of a fixed capacity, run their per-object layers on it, and then either
sum the rows back per set (Deep Set pooling) or unpack them into the padded layout with zeros in the
absent slots (the mixture actors' outputs, the critic's values of the mixture components).

Shapes never depend on data: the capacity is static, ``ceil(sets × rows_per_set)`` rounded up to a
multiple of 8. A call whose present rows exceed it takes the dense result instead, so no object is
ever dropped and the result is the dense one either way. The dense computation sits in a branch
(``nn.cond``) that runs only when some call overflows. Under ``jax.vmap`` a data-dependent branch
turns into a select that runs both sides; when the vmapped axis is named :data:`MEMBERS_AXIS` (the
trainer names its members' axis so), the members of that axis skip the dense branch together unless
one of them overflows, and each member still keeps its own result (packed, or dense if it overflowed).
Under any other ``vmap`` the result is the same, only slower (both run): name the axis.

The four moves between layouts come in adjoint pairs, each the other's gradient, all gathers:
:func:`pack` / :func:`unpack` (padded ↔ packed rows) and :func:`broadcast_to_rows` / :func:`sum_rows`
(one value per set ↔ every row of the set).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

Array = jax.Array

MEMBERS_AXIS = "vmapped_members"
"""Name of the ``vmap`` axis whose members decide together between packed and dense computation."""


@dataclasses.dataclass(frozen=True)
class Packing:
    """Static packing settings of one per-object layer (hashable: a Flax module attribute).

    ``rows_per_set``: rows reserved per set, on average over the sets of one call; a call of S sets
    with O slots each packs into ``min(S·O, ceil8(S · rows_per_set))`` rows.
    ``members_axis``: the vmap axis name whose members share the decision between packed and dense.
    **Name your vmap so**: a ``jax.vmap`` over several members' calls (agent states, seeds) must pass
    ``axis_name=members_axis`` (:data:`MEMBERS_AXIS` by default; the trainer and the evaluation do),
    or the dense branch runs on every call as a select (the same results, the dense cost). JAX gives
    no public way to tell that a call runs under an unnamed vmap, so this cannot be checked here.
    ``fallback=False`` compiles the packed computation alone, without the dense branch: only for
    counting its FLOPs (XLA's cost analysis counts the larger branch of a conditional); a call that
    overflows then drops objects. Leave it alone: :func:`xrl_jax.networks.packed_only` is the one
    place that sets it, for the FLOP counts of ``costs.py`` and ``paper.py --dry-run``.
    """

    rows_per_set: float
    members_axis: str = MEMBERS_AXIS
    fallback: bool = True

    def __post_init__(self):
        if not (isinstance(self.rows_per_set, (int, float)) and math.isfinite(self.rows_per_set)):
            raise ValueError(f"rows_per_set must be a finite number, got {self.rows_per_set!r}")
        if self.rows_per_set <= 0:
            raise ValueError(f"rows_per_set must be positive, got {self.rows_per_set}")
        if not (isinstance(self.members_axis, str) and self.members_axis):
            raise ValueError(
                f"members_axis must name a vmap axis (a non-empty str), got {self.members_axis!r}"
            )

    def capacity(self, num_sets: int, slots: int) -> int:
        """Packed rows for ``num_sets`` sets of ``slots`` slots (never more than all slots)."""
        reserved = 8 * math.ceil(num_sets * self.rows_per_set / 8)
        return min(num_sets * slots, reserved)

    def set_width(self, slots: int) -> int:
        """Slots kept per set by a per-set compaction (:func:`first_present`): twice the rows reserved
        per set, rounded up to a multiple of 8, never more than all ``slots``. A single set is far more
        variable than a batch's total, hence the margin."""
        return min(slots, 8 * math.ceil(2 * self.rows_per_set / 8))

    def scaled(self, factor: float, extra_rows: float = 0.0) -> Packing:
        """The packing of a derived set: ``(rows_per_set + extra_rows) · factor`` rows per set (e.g. an
        always-present neutral object adds a row, C mixture components per object multiply them)."""
        return dataclasses.replace(self, rows_per_set=(self.rows_per_set + extra_rows) * factor)


@struct.dataclass
class PresentRows:
    """Where the present rows of S padded sets of O slots go in a packed array of P rows.

    ``source`` (P,): the flat slot ``s·O + o`` of each packed row, ``S·O`` for unused rows;
    ``row`` (S·O,): the packed row of each slot, ``P`` for absent slots;
    ``set_index`` (P,): the set of each packed row, ``S`` for unused rows (ascending);
    ``fits``: every present row of this call has a place;
    ``all_fit``: every present row has a place in every member's call on the named vmap axis (if bound).
    """

    source: Array
    row: Array
    set_index: Array
    fits: Array
    all_fit: Array
    batch_shape: tuple[int, ...] = struct.field(pytree_node=False)
    slots: int = struct.field(pytree_node=False)

    @property
    def capacity(self) -> int:
        return self.source.shape[0]

    @property
    def num_sets(self) -> int:
        return math.prod(self.batch_shape)


def axis_bound(name: str) -> bool:
    """Whether a ``vmap`` (or mapped) axis called ``name`` is bound where this is traced."""
    try:
        jax.lax.axis_size(name)
    except NameError:
        return False
    return True


def find_present_rows(present: Array, capacity: int, members_axis: str | None = MEMBERS_AXIS) -> PresentRows:
    """The packing plan of a present mask (..., O): present slots in slot order, set after set."""
    present = jnp.asarray(present, bool)
    batch_shape, slots = tuple(present.shape[:-1]), int(present.shape[-1])
    per_set = present.reshape(-1, slots)
    flat = per_set.reshape(-1)
    num_slots = flat.shape[0]
    # The packed row of a present slot: the objects of the sets before it, then its rank in its set
    # (two short prefix sums rather than one over every slot of the call).
    counts = jnp.sum(per_set, axis=-1, dtype=jnp.int32)
    before = jnp.cumsum(counts) - counts
    rank = (before[:, None] + jnp.cumsum(per_set, axis=-1, dtype=jnp.int32) - 1).reshape(-1)
    placed = flat & (rank < capacity)
    target = jnp.where(placed, rank, capacity)  # everything else lands on a dropped extra row
    source = (
        jnp.full((capacity + 1,), num_slots, jnp.int32)
        .at[target]
        .set(jnp.arange(num_slots, dtype=jnp.int32), mode="drop")[:capacity]
    )
    row = jnp.where(flat, jnp.minimum(rank, capacity), capacity).astype(jnp.int32)
    set_index = (source // slots).astype(jnp.int32)
    fits = jnp.sum(flat, dtype=jnp.int32) <= capacity
    return PresentRows(source, row, set_index, fits, _every_member(fits, members_axis), batch_shape, slots)


def _every_member(fits: Array, members_axis: str | None) -> Array:
    """``fits`` of every member on the named vmap axis (if bound), else this call's own."""
    if members_axis is not None and axis_bound(members_axis):
        return jax.lax.psum((~fits).astype(jnp.int32), members_axis) == 0
    return fits


def _own_choice(fits: Array, result: Any, fallback: Any) -> Any:
    """Each member keeps its own result where it fits, the fallback's where it does not."""
    return jax.tree.map(lambda p, d: jnp.where(fits, p, d), result, fallback)


def _zeros_like_tree(tree: Any) -> Callable[..., Any]:
    shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), tree)
    return lambda *_: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def _with_zero_row(x: Array) -> Array:
    return jnp.concatenate([x, jnp.zeros((1, *x.shape[1:]), x.dtype)])


def _flat_rows(x: Array, leading: int) -> Array:
    return x.reshape((math.prod(x.shape[:leading]), *x.shape[leading:]))


@jax.custom_vjp
def _pack(rows: Array, plan: PresentRows) -> Array:
    return _with_zero_row(rows)[plan.source]


@jax.custom_vjp
def _unpack(packed: Array, plan: PresentRows) -> Array:
    return _with_zero_row(packed)[plan.row]


def _zero_plan_cotangent(plan: PresentRows):
    return jax.tree.map(lambda x: None, plan)


_pack.defvjp(
    lambda rows, plan: (_pack(rows, plan), plan),
    lambda plan, g: (_unpack(g, plan), _zero_plan_cotangent(plan)),
)
_unpack.defvjp(
    lambda packed, plan: (_unpack(packed, plan), plan),
    lambda plan, g: (_pack(g, plan), _zero_plan_cotangent(plan)),
)


def pack(rows: Array, plan: PresentRows) -> Array:
    """Padded rows (..., O, *D) → the present ones packed, (P, *D); unused packed rows are zero."""
    expected = (*plan.batch_shape, plan.slots)
    if tuple(rows.shape[: len(expected)]) != expected:
        raise ValueError(f"rows {rows.shape} must start with the plan's set shape {expected}")
    return _pack(_flat_rows(rows, len(expected)), plan)


def unpack(packed: Array, plan: PresentRows) -> Array:
    """Packed rows (P, *D) → the padded layout (..., O, *D), absent slots exactly zero."""
    if packed.shape[0] != plan.capacity:
        raise ValueError(f"packed rows {packed.shape} must have the plan's {plan.capacity} rows")
    flat = _unpack(packed, plan)
    return flat.reshape((*plan.batch_shape, plan.slots, *packed.shape[1:]))


@jax.custom_vjp
def _broadcast(per_set: Array, plan: PresentRows) -> Array:
    return _with_zero_row(per_set)[plan.set_index]


@jax.custom_vjp
def _sum(packed: Array, plan: PresentRows) -> Array:
    return jax.ops.segment_sum(packed, plan.set_index, plan.num_sets, indices_are_sorted=True)


_broadcast.defvjp(
    lambda per_set, plan: (_broadcast(per_set, plan), plan),
    lambda plan, g: (_sum(g, plan), _zero_plan_cotangent(plan)),
)
_sum.defvjp(
    lambda packed, plan: (_sum(packed, plan), plan),
    lambda plan, g: (_broadcast(g, plan), _zero_plan_cotangent(plan)),
)


def broadcast_to_rows(per_set: Array, plan: PresentRows) -> Array:
    """One value per set (..., *D) → that value on each of the set's packed rows, (P, *D)."""
    if tuple(per_set.shape[: len(plan.batch_shape)]) != plan.batch_shape:
        raise ValueError(f"per-set values {per_set.shape} must start with the sets' shape {plan.batch_shape}")
    return _broadcast(_flat_rows(per_set, len(plan.batch_shape)), plan)


def sum_rows(packed: Array, plan: PresentRows) -> Array:
    """Packed rows (P, *D) → their sum per set (..., *D); unused rows (set index S) are dropped."""
    if packed.shape[0] != plan.capacity:
        raise ValueError(f"packed rows {packed.shape} must have the plan's {plan.capacity} rows")
    return _sum(packed, plan).reshape((*plan.batch_shape, *packed.shape[1:]))


def plan_for(present: Array, packing: Packing | None) -> PresentRows | None:
    """The packing plan of a present mask (..., O), or ``None`` when the layer computes densely: no
    packing set, or a capacity that would hold every slot anyway."""
    if packing is None:
        return None
    num_sets, slots = math.prod(present.shape[:-1]), present.shape[-1]
    capacity = packing.capacity(num_sets, slots)
    if capacity >= num_sets * slots:
        return None
    plan = find_present_rows(present, capacity, packing.members_axis)
    return plan if packing.fallback else plan.replace(fits=None, all_fit=None)


def packed_or_dense(
    module: nn.Module,
    plan: PresentRows | None,
    packed: Callable[..., Any],
    dense: Callable[..., Any],
    *operands: Any,
) -> Any:
    """``packed(module, plan, *operands)`` where the plan fits, else ``dense(module, *operands)``.

    Both must return the same result up to float rounding; ``dense`` alone runs without a plan, and
    at initialisation, so that parameters start from the same draws with packing or without. The
    packed computation always runs; the dense one only when some member's call overflows, and each
    member keeps its own choice, so that what a member computes never depends on which members share
    its device. That is a real branch only when a ``jax.vmap`` over members names its axis
    ``packing.members_axis`` (:data:`MEMBERS_AXIS`); under an unnamed one both sides always run.
    """
    if plan is None or module.is_initializing():
        return dense(module, *operands)
    result = packed(module, plan, *operands)
    if plan.fits is None:  # Packing(fallback=False): the packed computation alone
        return result
    fallback = nn.cond(plan.all_fit, _zeros_like_tree(result), dense, module, *operands)
    return _own_choice(plan.fits, result, fallback)


@struct.dataclass
class FirstPresent:
    """The first W present slots of every set of (..., O) slots, in slot order: for work that pairs
    the objects of one set with each other, which packing the whole call's rows cannot serve.

    ``order`` (..., W): the slot of each set's w-th present object (an absent slot past its count);
    ``valid`` (..., W): whether that is a present object; ``place`` (..., O): each present slot's
    place in ``order`` (clipped for the others); ``fits`` / ``all_fit`` as in :class:`PresentRows`.
    """

    order: Array
    valid: Array
    place: Array
    fits: Array | None
    all_fit: Array | None


def first_present(present: Array, width: int, members_axis: str | None = MEMBERS_AXIS) -> FirstPresent:
    """The per-set compaction of a present mask (..., O) to ``width`` slots (a stable sort puts the
    present slots first)."""
    present = jnp.asarray(present, bool)
    order = jnp.argsort((~present).astype(jnp.int8), axis=-1, stable=True)[..., :width].astype(jnp.int32)
    valid = jnp.take_along_axis(present, order, axis=-1)
    place = jnp.clip(jnp.cumsum(present, axis=-1, dtype=jnp.int32) - 1, 0, width - 1)
    fits = jnp.all(jnp.sum(present, axis=-1, dtype=jnp.int32) <= width)
    return FirstPresent(order, valid, place, fits, _every_member(fits, members_axis))


def per_set_plan(present: Array, packing: Packing | None) -> FirstPresent | None:
    """:func:`first_present` at ``packing.set_width``, or ``None`` when that keeps every slot."""
    if packing is None:
        return None
    width = packing.set_width(present.shape[-1])
    if width >= present.shape[-1]:
        return None
    plan = first_present(present, width, packing.members_axis)
    return plan if packing.fallback else plan.replace(fits=None, all_fit=None)


def compact_or_dense(
    plan: FirstPresent | None, compact: Callable[..., Any], dense: Callable[..., Any], *operands: Any
) -> Any:
    """``compact(plan, *operands)`` where every set fits the plan's width, else ``dense(*operands)``;
    the plain-function twin of :func:`packed_or_dense`, with the same branch and choice per member."""
    if plan is None:
        return dense(*operands)
    result = compact(plan, *operands)
    if plan.fits is None:
        return result
    fallback = jax.lax.cond(plan.all_fit, _zeros_like_tree(result), dense, *operands)
    return _own_choice(plan.fits, result, fallback)


__all__ = [
    "MEMBERS_AXIS",
    "FirstPresent",
    "Packing",
    "PresentRows",
    "broadcast_to_rows",
    "compact_or_dense",
    "find_present_rows",
    "first_present",
    "pack",
    "packed_or_dense",
    "per_set_plan",
    "plan_for",
    "sum_rows",
    "unpack",
]
