"""Per-object layers on the present objects only (xrl_jax.sets): the packed computation is the dense one.

Tolerance. Both computations evaluate the same expressions on the same numbers and differ only in how
sums are associated: matrix products of other shapes, per-set sums of packed rows instead of masked
sums over every slot, the mixture logits centred over the slots that carry weight. In float64 (unit
roundoff u = 1.1e-16) reassociating a sum of n terms moves it by at most n·u·Σ|terms|; with n ≤ 10³
terms per sum, a dozen layers and their gradients, every compared value stays within ~1e-11 of the
terms it sums, which are at most the largest magnitude of its group (a policy, a loss with its
metrics, a gradient). The group, not the value: a gradient that cancels to zero (the mixture logit's
bias, which the softmax ignores) is exact to its terms' size, not to its own. One layer amplifies:
the Deep Set's Fourier features sin(π·z) take z of magnitude up to ~50 (scale 30), so z's rounding
reaches their outputs (of magnitude 1) multiplied by ~π·50 ≈ 150: ~2e-9. We allow 1e-8 of the
group's largest magnitude, while a dropped or a doubled object changes the values by percents.
"""

import itertools
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from network_support import action_size
from train_support import xla_flags

from xrl_jax import sets
from xrl_jax.agents import make_agent
from xrl_jax.config import ALGOS, DISCRETE_ALGOS, preset
from xrl_jax.networks import ENV_OBSERVATIONS

ROOT = Path(__file__).resolve().parents[1]
RELATIVE = 1e-8
SMALL = dict(actor_width=16, critic_width=16, fe_width=8, actor_depth=2, critic_depth=2)


def _groups(tree):
    """The groups whose largest magnitude scales the tolerance: a dict's entries (and a loss's value,
    metrics and gradient apart), else the whole tree."""
    if isinstance(tree, dict) and not any(k == "params" for k in tree):
        for key, value in tree.items():
            yield from ((f"{key}/{name}", group) for name, group in _groups(value))
    elif isinstance(tree, tuple) and len(tree) == 2 and isinstance(tree[0], tuple):  # ((value, aux), grads)
        yield "value", tree[0][0]
        yield "metrics", tree[0][1]  # (mean_mixture_logits is 0 up to rounding of the logits' size)
        yield "gradient", tree[1]
    else:
        yield "", tree


def assert_same(packed, dense, what=""):
    """Every leaf equal within RELATIVE of its group's largest magnitude (the module doc's bound)."""
    for (name, got), (_, want) in zip(_groups(packed), _groups(dense), strict=True):
        leaves = [np.asarray(x, np.float64) for x in jax.tree.leaves(want)]
        scale = max([float(np.max(np.abs(x), initial=0.0)) for x in leaves] + [1e-30])
        for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(got), leaves, strict=True):
            np.testing.assert_allclose(
                np.asarray(a, np.float64),
                b,
                rtol=0,
                atol=RELATIVE * scale,
                err_msg=f"{what} {name} {jax.tree_util.keystr(path)}",
            )


def update_without_overflow_metric(out):
    """An update's (state, metrics) without ``packed_overflow``, which only packed agents report."""
    state, metrics = out
    return state, {k: v for k, v in metrics.items() if k != "packed_overflow"}


def set_batch(env: str, counts, rng, dtype=np.float64, scatter_last: bool = False) -> dict:
    """Observations whose sets hold ``counts[i]`` objects each, present rows first (as every scenario
    writes them; ``scatter_last``: the last set's present rows spread over its slots, as a user's env
    might), absent rows zero; features drawn like the scenario's (positions in [-1, 1], flags 0/1)."""
    shape = ENV_OBSERVATIONS[env]
    batch, slots = len(counts), shape.num_objects
    objects = rng.uniform(-1, 1, (batch, slots, shape.object_features))
    present = np.arange(slots)[None] < np.asarray(counts)[:, None]
    if scatter_last:
        present[-1] = rng.permutation(present[-1])
    objects[..., 0] = present
    objects = np.where(present[..., None], objects, 0.0)
    state = rng.uniform(-1, 1, (batch, shape.state_dim))
    return {"state": jnp.asarray(state, dtype), shape.set_key: jnp.asarray(objects, dtype)}


def counts_for(env: str, batch: int, rng) -> list[int]:
    """A batch's object counts: one empty set, one full set, the others as the scenario's."""
    slots = ENV_OBSERVATIONS[env].num_objects
    if env == "tracking":
        return [slots] * batch
    typical = rng.integers(0, 12, batch) if env == "country_road" else rng.integers(0, 3, batch)
    return [0, slots, *typical[2:].tolist()]


def agent_pair(env: str, algo: str, rows: float, **changes):
    """The packed agent (``rows`` per set) and the dense one, from one config."""
    shape = ENV_OBSERVATIONS[env]
    config = preset("smoke", env, algo).replace(**SMALL, packed_rows=rows, **changes)
    example = {
        "state": jnp.zeros(shape.state_dim),
        shape.set_key: jnp.zeros((shape.num_objects, shape.object_features)),
    }
    size = action_size(algo)
    return make_agent(config, example, size), make_agent(config.replace(dense_sets=True), example, size)


def transition_batch(env: str, algo: str, rng, batch: int = 10) -> dict:
    discrete = algo in DISCRETE_ALGOS
    return {
        "obs": set_batch(env, counts_for(env, batch, rng), rng, scatter_last=True),
        "next_obs": set_batch(env, counts_for(env, batch, rng)[::-1], rng),
        "action": jnp.asarray(rng.integers(0, 12, batch))
        if discrete
        else jnp.asarray(rng.uniform(-1, 1, (batch, 3))),
        "reward": jnp.asarray(rng.normal(size=batch)),
        "terminated": jnp.asarray(rng.uniform(size=batch) < 0.2),
        "truncated": jnp.zeros(batch, bool),
    }


def float64_state(agent, key):
    state = agent.init(key)
    return jax.tree.map(
        lambda x: x.astype(jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating) else x, state
    )


def everything(agent, state, batch, key):
    """What the agent computes from a batch: its policy, the critics, both losses and their gradients
    and the actions it takes (fast path). (A whole update adds Adam steps to these gradients.)"""
    obs = batch["obs"]
    pi = agent.policy(state.actor_params, obs)
    policy = {"weights": pi.weights}
    if agent.is_discrete:
        policy["probs"] = pi.probs()
        critic = agent.networks.critic.apply(state.critic_params, obs)
    else:
        policy.update(loc=pi.loc, log_scale=pi.log_scale)
        critic = agent.networks.critic.apply(state.critic_params, obs, batch["action"])
    critic_loss = jax.value_and_grad(agent.critic_loss, has_aux=True)(state.critic_params, state, batch, key)
    actor_loss = jax.value_and_grad(agent.actor_loss, has_aux=True)(state.actor_params, state, batch, key)
    actions = {mode: agent.act(key, state, obs, mode) for mode in ("train", "eval")}
    return {
        "policy": policy,
        "critic": critic,
        "critic_loss": critic_loss,
        "actor_loss": actor_loss,
        "actions": actions,
    }


# One agent per env in the default tier (a continuous and a discrete mixture agent); the rest of the
# env x agent matrix is marked slow.
DEFAULT_TIER_PAIRS = {("country_road", "xsac"), ("intersection", "xdsac")}


@pytest.mark.parametrize(
    "env,algo",
    [
        pytest.param(env, algo, marks=() if (env, algo) in DEFAULT_TIER_PAIRS else pytest.mark.slow)
        for env, algo in itertools.product(["country_road", "intersection"], ALGOS)
    ],
)
def test_packed_equals_dense_for_every_agent(env, algo):
    """Forward outputs, both losses, their gradients and the actions, on a batch with an empty set, a
    full set and a set whose objects are not in the first slots."""
    rng = np.random.default_rng(hash((env, algo)) % 2**32)
    rows = 30.0 if env == "country_road" else 3.0  # holds the batch (the empty set of an X actor: all rows)
    with jax.enable_x64(True):
        packed, dense = agent_pair(env, algo, rows)
        batch = transition_batch(env, algo, rng)
        state = float64_state(dense, jax.random.PRNGKey(1))
        key = jax.random.PRNGKey(2)
        plan = sets.plan_for(
            batch["obs"][ENV_OBSERVATIONS[env].set_key][..., 0] > 0, packed.networks.critic.extractor.packing
        )
        assert plan is not None and bool(plan.fits)  # the packed branch is the one compared
        got = jax.jit(lambda s, b, k: everything(packed, s, b, k))(state, batch, key)
        want = jax.jit(lambda s, b, k: everything(dense, s, b, k))(state, batch, key)
    if packed.is_discrete:
        np.testing.assert_array_equal(got.pop("actions")["train"], want.pop("actions")["train"])
    assert_same(got, want, f"{env} {algo}")


def test_tracking_sets_are_always_full_so_its_presets_compute_densely():
    for algo in ALGOS:
        config = preset("paper", "tracking", algo)
        assert config.packed_rows is None
    assert preset("paper", "country_road", "xsac").packed_rows is not None
    assert preset("paper", "intersection", "sac").packed_rows is not None
    assert preset("quick", "intersection", "sac").packed_rows is None  # small layers: not worth it


@pytest.mark.parametrize("algo", ["xsac"])
def test_an_overflowing_call_computes_densely_with_the_same_result(algo):
    """Fewer packed rows than present objects: every layer falls back to all slots, nothing is dropped."""
    rng = np.random.default_rng(7)
    with jax.enable_x64(True):
        packed, dense = agent_pair("country_road", algo, 2.0)
        batch = transition_batch("country_road", algo, rng)
        objects = batch["obs"]["cones_set"]
        plan = sets.plan_for(objects[..., 0] > 0, packed.networks.critic.extractor.packing)
        assert not bool(plan.fits)
        state = float64_state(dense, jax.random.PRNGKey(1))
        key = jax.random.PRNGKey(2)
        got = jax.jit(lambda s, b, k: everything(packed, s, b, k))(state, batch, key)
        want = jax.jit(lambda s, b, k: everything(dense, s, b, k))(state, batch, key)
    assert_same(got, want, algo)


def test_members_on_a_named_axis_share_a_real_branch_and_an_overflow():
    """vmap over members on sets.MEMBERS_AXIS keeps the packed-or-dense choice a real branch (one
    conditional, not a select of both); one member's overflow sends all of them to the dense branch,
    and every member's update equals the dense one, also under a vmap without the name."""
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        packed, dense = agent_pair("country_road", "xdsac", 30.0)
        batches = [transition_batch("country_road", "xdsac", rng) for _ in range(2)]
        crowded = set_batch("country_road", [100] * 10, rng)  # 1000 objects > 240 packed rows
        states = jax.vmap(lambda k: float64_state(dense, k))(jax.random.split(jax.random.PRNGKey(4), 2))
        keys = jax.random.split(jax.random.PRNGKey(5), 2)
        named = jax.jit(jax.vmap(packed.update, axis_name=sets.MEMBERS_AXIS))
        unnamed = jax.jit(jax.vmap(packed.update))
        reference = jax.jit(jax.vmap(dense.update))
        stacked = jax.tree.map(lambda *x: jnp.stack(x), *batches)
        assert "stablehlo.case" in named.lower(keys, states, stacked).as_text()
        assert "stablehlo.case" not in unnamed.lower(keys, states, stacked).as_text()
        for name, pair in (
            ("fits", batches),
            ("one overflows", [batches[0], {**batches[1], "obs": crowded}]),
        ):
            batch = jax.tree.map(lambda *x: jnp.stack(x), *pair)
            want = reference(keys, states, batch)
            for axis, update in (("named", named), ("unnamed", unnamed)):
                got = update_without_overflow_metric(update(keys, states, batch))
                assert_same(got, want, f"{name}, {axis} axis")
            assert np.array_equal(named(keys, states, batch)[1]["packed_overflow"], [0, name != "fits"])


@pytest.mark.distributed  # a child process with 4 forced host devices
def test_four_devices_give_the_dense_update():
    """Members spread over 4 forced host devices (shard_map, as the trainer spreads them), one device's
    member overflowing: every member's update equals the dense computation."""
    script = r"""
import jax, jax.numpy as jnp, numpy as np, sys
sys.path.insert(0, "tests")
from jax.sharding import Mesh, PartitionSpec as P
from test_sets import agent_pair, transition_batch, set_batch, float64_state, assert_same
from test_sets import update_without_overflow_metric
from xrl_jax import sets
assert len(jax.devices()) == 4
rng = np.random.default_rng(11)
with jax.enable_x64(True):
    packed, dense = agent_pair("country_road", "xdsac", 30.0)
    batches = [transition_batch("country_road", "xdsac", rng) for _ in range(8)]
    batches[5]["obs"] = set_batch("country_road", [100] * 10, rng)
    batch = jax.tree.map(lambda *x: jnp.stack(x), *batches)
    states = jax.vmap(lambda k: float64_state(dense, k))(jax.random.split(jax.random.PRNGKey(4), 8))
    keys = jax.random.split(jax.random.PRNGKey(5), 8)
    mesh = Mesh(np.array(jax.devices()), ("member",))
    def spread(agent):
        block = jax.vmap(agent.update, axis_name=sets.MEMBERS_AXIS)
        blocks = P("member")
        return jax.jit(jax.shard_map(block, mesh=mesh, in_specs=blocks, out_specs=blocks, check_vma=False))
    got = update_without_overflow_metric(spread(packed)(keys, states, batch))
    assert_same(got, jax.jit(jax.vmap(dense.update))(keys, states, batch))
print("ok")
"""
    devices = xla_flags("--xla_force_host_platform_device_count=4")
    env = dict(os.environ, PYTHONPATH=str(ROOT), XLA_FLAGS=devices)
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


# ---- the layout moves ---------------------------------------------------------------------------


def test_pack_and_unpack_move_present_rows_and_are_each_others_gradient():
    present = jnp.asarray([[1, 0, 1, 0], [0, 0, 0, 0], [1, 1, 1, 1]], bool)  # scattered, empty, full
    rows = jnp.arange(12.0 * 2).reshape(3, 4, 2)
    plan = sets.find_present_rows(present, 8)
    assert bool(plan.fits) and plan.capacity == 8
    packed = sets.pack(rows, plan)
    np.testing.assert_array_equal(packed[:6], rows.reshape(12, 2)[np.flatnonzero(present)])
    np.testing.assert_array_equal(packed[6:], 0.0)  # unused rows hold zeros
    np.testing.assert_array_equal(sets.unpack(packed, plan), jnp.where(present[..., None], rows, 0.0))
    np.testing.assert_array_equal(sets.sum_rows(packed, plan), jnp.where(present[..., None], rows, 0).sum(1))
    per_set = jnp.asarray([[1.0], [2.0], [3.0]])
    np.testing.assert_array_equal(sets.broadcast_to_rows(per_set, plan)[:, 0], [1, 1, 3, 3, 3, 3, 0, 0])
    # Gradients: each move's is its adjoint, the same as the dense masked computation's.
    weights = jnp.arange(1.0, 17.0).reshape(8, 2)
    grad_pack = jax.grad(lambda r: jnp.sum(sets.pack(r, plan) * weights))(rows)
    grad_dense = jax.grad(
        lambda r: jnp.sum(
            jnp.where(present[..., None], r, 0.0).reshape(12, 2)[np.flatnonzero(present)] * weights[:6]
        )
    )(rows)
    np.testing.assert_array_equal(grad_pack, grad_dense)
    grad_unpack = jax.grad(lambda p: jnp.sum(sets.unpack(p, plan) * rows))(packed)
    np.testing.assert_array_equal(grad_unpack, sets.pack(rows, plan))
    grad_sum = jax.grad(lambda p: jnp.sum(sets.sum_rows(p, plan) * per_set))(packed)
    np.testing.assert_array_equal(grad_sum, sets.broadcast_to_rows(jnp.broadcast_to(per_set, (3, 2)), plan))
    grad_broadcast = jax.grad(lambda v: jnp.sum(sets.broadcast_to_rows(v, plan) * weights[:, :1]))(per_set)
    np.testing.assert_array_equal(grad_broadcast[:, 0], [1 + 3, 0, 5 + 7 + 9 + 11])


def test_a_plan_that_cannot_hold_every_present_row_says_so():
    present = jnp.ones((3, 4), bool)
    assert not bool(sets.find_present_rows(present, 8).fits)
    assert bool(sets.find_present_rows(present, 12).fits)


def test_capacity_rule_and_bad_settings():
    assert sets.Packing(36.0).capacity(256, 100) == 9216
    assert sets.Packing(36.0).capacity(1, 100) == 40  # rounded up to a multiple of 8
    assert sets.Packing(36.0).capacity(2, 25) == 50  # never more rows than slots
    assert sets.Packing(1.0).scaled(2.0, extra_rows=1).rows_per_set == 4.0
    assert sets.plan_for(jnp.ones((2, 25), bool), sets.Packing(36.0)) is None  # as many rows as slots
    for bad in (0.0, -1.0, float("nan"), "8"):
        with pytest.raises(ValueError, match="rows_per_set"):
            sets.Packing(bad)
    for bad in (None, ""):  # no axis would leave the members' shared decision unnamed
        with pytest.raises(ValueError, match="members_axis must name a vmap axis"):
            sets.Packing(8.0, members_axis=bad)


def test_the_packed_only_networks_are_built_in_one_place_and_only_lose_the_fallback():
    """Packing without its fallback (a FLOPs-only switch: a call that overflows drops objects) ran
    through make_agent, make_networks, set_packing and country_road_networks; now only
    networks.packed_only builds it, and its lowered update has no conditional where the agent's has."""
    import inspect

    from xrl_jax import networks
    from xrl_jax.benchmarks.table_one import country_road_networks

    for api in (make_agent, networks.make_networks, networks.set_packing, country_road_networks):
        assert not any("fallback" in name for name in inspect.signature(api).parameters), api
    config = preset("smoke", "country_road", "xdsac").replace(packed_rows=4.0)
    agent = make_agent(config, networks.dummy_observation(ENV_OBSERVATIONS["country_road"]), 12)
    packed = networks.packed_only(agent.networks)
    assert packed.config == agent.networks.config and packed is not agent.networks
    obs = networks.dummy_observation(ENV_OBSERVATIONS["country_road"], (16,))
    params = jax.eval_shape(agent.networks.init_actor, jax.random.PRNGKey(0))

    def lowered(nets):
        return jax.jit(nets.actor.apply).lower(params, obs).as_text()

    assert "case" in lowered(agent.networks) and "case" not in lowered(packed)


def test_first_present_compacts_each_set_in_slot_order():
    present = jnp.asarray([[0, 1, 0, 1, 1], [0, 0, 0, 0, 0], [1, 0, 0, 0, 0]], bool)
    plan = sets.first_present(present, 3)
    np.testing.assert_array_equal(plan.order[0], [1, 3, 4])
    np.testing.assert_array_equal(plan.valid, [[1, 1, 1], [0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(plan.order[2, :1], [0])
    np.testing.assert_array_equal(jnp.where(present, plan.place, -1)[0], [-1, 0, -1, 1, 2])
    assert bool(plan.fits) and not bool(sets.first_present(present, 2).fits)
    assert sets.Packing(32.0).set_width(100) == 64 and sets.Packing(2.0).set_width(9) == 8
    assert sets.per_set_plan(present, sets.Packing(4.0)) is None  # 8 ≥ 5 slots: nothing to compact


def test_the_mixture_density_on_weighted_components_is_the_full_one():
    """XSAC's eq. 9 densities formed among each sample's weighted components only (a per-set
    compaction) equal those over all K components at the weighted slots, gradients included; a
    sample with more weighted components than the width falls back to all K; under vmap on the
    members' axis the fallback is a real branch."""
    from xrl_jax.distributions import SquashedGaussianMixture

    rng = np.random.default_rng(5)
    slots, width = 20, 8
    counts = [3, 0, 8, 1]  # an empty set: all 20 slots carry weight, more than 8
    present = jnp.asarray(np.arange(slots)[None] < np.asarray(counts)[:, None])
    present = present.at[0].set(jnp.asarray(rng.permutation(np.asarray(present[0]))))
    packing = sets.Packing(width / 2)
    with jax.enable_x64(True):
        loc = jnp.asarray(rng.normal(size=(4, slots, 2)))
        log_scale = jnp.asarray(rng.uniform(-1.5, 0.0, (4, slots, 2)))
        logits = jnp.asarray(rng.normal(size=(4, slots)))

        def loss(params, rows, packing):
            mixture = SquashedGaussianMixture.create(
                params[0][rows], params[1][rows], params[2][rows], present[rows]
            )
            _, log_probs = mixture.sample_per_component(jax.random.PRNGKey(0), packing=packing)
            return jnp.sum(mixture.weights * log_probs), jnp.where(mixture.weighted, log_probs, 0.0)

        params = (loc, log_scale, logits)
        for rows, compacts in ((np.array([0, 2, 3]), True), (np.arange(4), False)):
            # an empty set's slots all carry weight (docs/algorithms.md §3.1.4)
            weighted = present[rows] | ~jnp.any(present[rows], axis=-1, keepdims=True)
            assert bool(sets.first_present(weighted, width).fits) == compacts
            got = jax.value_and_grad(loss, has_aux=True)(params, rows, packing)
            want = jax.value_and_grad(loss, has_aux=True)(params, rows, None)
            assert_same(got, want, f"compacts={compacts}")
        members = jax.vmap(lambda p: loss(p, np.array([0, 2, 3]), packing)[0], axis_name=sets.MEMBERS_AXIS)
        stacked = jax.tree.map(lambda x: jnp.stack([x, x]), params)
        assert "stablehlo.case" in jax.jit(members).lower(stacked).as_text()


def test_xsac_losses_with_compacted_mixture_pairs_equal_the_dense_ones():
    """The agent-level twin of the test above, on Country Road sets that all fit the pair width (the
    every-agent test's empty and full sets make XSAC's pairs fall back to all slots)."""
    rng = np.random.default_rng(9)
    with jax.enable_x64(True):
        packed, dense = agent_pair("country_road", "xsac", 30.0)
        batch = transition_batch("country_road", "xsac", rng)
        batch["obs"] = set_batch("country_road", rng.integers(1, 40, 10), rng, scatter_last=True)
        weighted = batch["obs"]["cones_set"][..., 0] > 0
        plan = sets.per_set_plan(weighted, packed.networks.component_packing)
        assert plan is not None and bool(plan.fits)
        state = float64_state(dense, jax.random.PRNGKey(1))
        key = jax.random.PRNGKey(2)
        got = jax.jit(lambda s, b, k: everything(packed, s, b, k))(state, batch, key)
        want = jax.jit(lambda s, b, k: everything(dense, s, b, k))(state, batch, key)
    assert_same(got, want, "xsac, compacted pairs")
