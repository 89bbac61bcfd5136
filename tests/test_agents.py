"""Agents (docs/algorithms.md): update order (§1.5), jit + vmap over seeds, determinism, acting modes
(§3.7–3.8), the XSAC Monte-Carlo objective (§8 item 6), XDSAC closed form, κ, α direction (§8 item 10),
masking."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from network_support import action_size as algo_action_size
from network_support import float64_object_weights

from xrl_jax import losses
from xrl_jax.agents import ACT_MODES, AgentState, HyperParams, make_agent
from xrl_jax.config import TRACED_FIELDS, AgentConfig
from xrl_jax.distributions import SquashedGaussianMixture

ALGOS = ("sac", "dsac", "xsac", "xdsac")
O, F, S, B = 3, 4, 2, 5  # noqa: E741  (objects, features, state, batch)
NUM_ACTIONS = {"sac": 2, "xsac": 2, "dsac": 4, "xdsac": 4}
SEEDS = 2
EXAMPLE = {"state": jnp.zeros(S), "things_set": jnp.zeros((O, F))}


def tiny_config(algo: str, **changes) -> AgentConfig:
    base = dict(
        algo=algo,
        actor_width=8,
        actor_depth=1,
        critic_width=8,
        critic_depth=1,
        fe_width=8,
        feature_extractor="flat_pe",
        pe_freqs=1,
        actor_lr=1e-2,
        critic_lr=1e-2,
        tau=0.1,
        kappa=0.05,
    )
    base.update(changes)
    return AgentConfig(**base)


def make_batch(key, algo, batch=B, absent_value=0.0):
    """Random batch in the documented layout; slot 2 is absent in every observation."""
    keys = jax.random.split(key, 8)
    discrete = algo in ("dsac", "xdsac")

    def obs(k1, k2):
        rows = jax.random.uniform(k1, (batch, O, F), minval=-1, maxval=1)
        rows = rows.at[..., 0].set(1.0).at[:, 2, :].set(absent_value).at[:, 2, 0].set(0.0)
        return {"state": jax.random.normal(k2, (batch, S)), "things_set": rows}

    if discrete:
        action = jax.random.randint(keys[0], (batch,), 0, NUM_ACTIONS[algo])
    else:
        action = jax.random.uniform(keys[0], (batch, NUM_ACTIONS[algo]), minval=-1, maxval=1)
    return {
        "obs": obs(keys[1], keys[2]),
        "action": action,
        "reward": jax.random.normal(keys[3], (batch,)),
        "next_obs": obs(keys[4], keys[5]),
        "terminated": jnp.arange(batch) == 0,
        "truncated": jnp.zeros(batch, bool),
    }


@functools.cache
def vmapped_update_run(algo):
    """Agent, per-seed states (seed 0 wants low entropy, seed 1 high) and one vmapped, jitted update."""
    agent = make_agent(tiny_config(algo), EXAMPLE, NUM_ACTIONS[algo])
    states = jax.vmap(agent.init)(jax.random.split(jax.random.PRNGKey(0), SEEDS))
    states = states.replace(hparams=states.hparams.replace(target_entropy=jnp.array([-100.0, 100.0])))
    batches = jax.vmap(lambda k: make_batch(k, algo))(jax.random.split(jax.random.PRNGKey(1), SEEDS))
    update = jax.jit(jax.vmap(agent.update))
    keys = jax.random.split(jax.random.PRNGKey(2), SEEDS)
    new_states, metrics = update(keys, states, batches)
    return {
        "algo": algo,
        "agent": agent,
        "states": states,
        "batches": batches,
        "update": update,
        "keys": keys,
        "new_states": new_states,
        "metrics": metrics,
    }


@pytest.fixture(scope="module", params=ALGOS)
def setup(request):
    return vmapped_update_run(request.param)


def leaves_close(a, b, **kw):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(x, y, **kw)


def test_update_vmaps_over_seeds_and_is_finite(setup):
    metrics, new_states = setup["metrics"], setup["new_states"]
    expected = {"loss_actor", "loss_critic", "loss_ent_coef", "grad_norm_actor", "grad_norm_critic"}
    expected |= {"ent_coef", "entropy_mean", "q_val_min", "q_val_max"}
    if setup["algo"] in ("xsac", "xdsac"):
        expected |= {"mixture_entropy", "kappa"}
    assert expected <= set(metrics)
    for name, value in metrics.items():
        assert value.shape == (SEEDS,), name
        assert np.all(np.isfinite(value)), name
    np.testing.assert_array_equal(new_states.step, [1, 1])
    # seeds are independent: different parameters after init and after the update
    for leaf in jax.tree_util.tree_leaves(new_states.actor_params):
        if leaf.ndim >= 3:  # kernels (seed axis first): random init differs per seed
            assert not np.allclose(leaf[0], leaf[1])


def test_update_is_deterministic_under_a_fixed_key(setup):
    again, metrics = setup["update"](setup["keys"], setup["states"], setup["batches"])
    leaves_close(again, setup["new_states"], rtol=0, atol=0)
    leaves_close(metrics, setup["metrics"], rtol=0, atol=0)
    other, _ = setup["update"](setup["keys"][::-1], setup["states"], setup["batches"])
    if setup["algo"] in ("sac", "xsac"):  # the discrete updates use no randomness at all
        assert not np.allclose(
            other.critic_params["params"]["heads"]["q"]["kernel"],
            setup["new_states"].critic_params["params"]["heads"]["q"]["kernel"],
        )


def test_entropy_coefficient_moves_towards_target(setup):
    """§8 item 10 at agent level: seed 0 (target −100, entropy above it) lowers α, seed 1 raises it."""
    old = np.exp(np.asarray(setup["states"].log_alpha))
    new = np.asarray(setup["metrics"]["ent_coef"])
    np.testing.assert_allclose(old, 0.1, rtol=1e-6)
    assert new[0] < old[0] and new[1] > old[1]
    np.testing.assert_allclose(np.exp(setup["new_states"].log_alpha), new, rtol=1e-6)


def test_polyak_from_the_updated_critic(setup):
    old, new = setup["states"], setup["new_states"]
    tau = 0.1
    expected = jax.tree_util.tree_map(
        lambda t, c: (1 - tau) * t + tau * c, old.target_critic_params, new.critic_params
    )
    leaves_close(new.target_critic_params, expected, rtol=1e-5, atol=1e-7)


def adam_first_step(grads, params, lr):
    """optax.adam's first step from a fresh state, as each agent update takes on a new state."""
    adam = optax.adam(lr)
    updates, _ = adam.update(grads, adam.init(params))
    return optax.apply_updates(params, updates)


# Comparing one update computed by two programs (different summation orders): Adam's first step
# lr·g/(|g| + 1e-8) turns a gradient error δ into a parameter error of up to lr·δ/1e-8 (1e6·δ at
# lr = 1e-2). In float32 the rounding of a near-zero gradient coordinate (~1e-10) thus becomes a
# sizeable, CPU-dependent fraction of lr, so these checks run in float64, where the gradients of
# these tiny networks (sums of ≲ 10³ terms, |terms| adding up to ≲ 10³) round by at most
# 10³·10³·1.1e-16 ≈ 1e-10, and a first Adam step by at most 1e6·1e-10 = 1e-4.
F64_GRAD_ATOL = 1e-10
F64_STEP_ATOL = 1e-4  # still 100× below the ±lr = 1e-2 (2.5e-3 in the decay test: 25×) of a step


def float64_state(state):
    """`state` with every floating leaf in float64 (call under x64: flax creates float32 parameters)."""
    return jax.tree.map(
        lambda x: x.astype(jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating) else x, state
    )


def assert_float64(tree):
    floats = [x for x in jax.tree_util.tree_leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    assert floats and all(x.dtype == jnp.float64 for x in floats)


@pytest.mark.parametrize("algo", ["xsac", "dsac"])
def test_update_follows_the_order_of_section_1_5(algo):
    """Rebuild one step by hand: critic → actor against the NEW critic with the OLD α → α from the
    actor step's entropies → Polyak from the new critic; the agent's update must match.

    Run in float64 (see F64_STEP_ATOL). Adam's first moment after one step is (1 − β1)·g, linear in
    the gradient, so it shows which gradient each step used; the parameters alone would not, as a
    first Adam step is ≈ ±lr whatever the gradient's size."""
    agent = make_agent(tiny_config(algo), EXAMPLE, NUM_ACTIONS[algo])

    def by_hand(state, batch, key):
        target_key, actor_key = jax.random.split(key)
        critic_grads, _ = jax.grad(agent.critic_loss, has_aux=True)(
            state.critic_params, state, batch, target_key
        )
        critic_params = adam_first_step(critic_grads, state.critic_params, 1e-2)
        with_new_critic = state.replace(critic_params=critic_params)
        actor_grads, aux = jax.grad(agent.actor_loss, has_aux=True)(
            state.actor_params, with_new_critic, batch, actor_key
        )
        actor_params = adam_first_step(actor_grads, state.actor_params, 1e-2)
        alpha_grad = jnp.mean(aux["entropy"]) - state.hparams.target_entropy  # d/d log α (§8 item 10)
        log_alpha = adam_first_step(alpha_grad, state.log_alpha, 1e-2)
        target = losses.polyak_update(state.target_critic_params, critic_params, 0.1)
        stale_grads, _ = jax.grad(agent.actor_loss, has_aux=True)(state.actor_params, state, batch, actor_key)
        return {
            "params": (critic_params, actor_params, log_alpha, target),
            "grads": (critic_grads, actor_grads, alpha_grad),
            "stale_actor_grads": stale_grads,
        }

    @jax.jit
    def run(state, batch, key):
        new_state, _ = agent.update(key, state, batch)
        return new_state, by_hand(state, batch, key)

    with jax.enable_x64(True):  # also for the arithmetic below: outside it jnp rounds to float32
        state = float64_state(agent.init(jax.random.PRNGKey(0)))
        # entropy far above the target: α's gradient is far from zero
        state = state.replace(hparams=state.hparams.replace(target_entropy=jnp.asarray(-100.0)))
        new_state, hand = run(state, make_batch(jax.random.PRNGKey(1), algo), jax.random.PRNGKey(2))
        assert_float64((new_state, hand))
        critic, actor, log_alpha, target = hand["params"]
        got = (new_state.critic_params, new_state.actor_params, new_state.log_alpha)
        leaves_close(got, (critic, actor, log_alpha), rtol=0, atol=F64_STEP_ATOL)
        # Polyak: τ = 0.1 times the critic's error
        leaves_close(new_state.target_critic_params, target, rtol=0, atol=0.1 * F64_STEP_ATOL)
        # the gradients each step used: Adam's μ = (1 − β1)·g = 0.1·g, so 0.1 × the gradients' tolerance
        mus = [adam_first_moment(getattr(new_state, f"{n}_opt_state")) for n in ("critic", "actor", "alpha")]
        expected = jax.tree.map(lambda g: 0.1 * g, hand["grads"])
        leaves_close(mus, list(expected), rtol=0, atol=0.1 * F64_GRAD_ATOL)
        # the pre-update critic would have given another actor gradient, far beyond that tolerance
        stale = jax.tree.map(lambda a, b: np.abs(a - b).max(), hand["stale_actor_grads"], hand["grads"][1])
        assert max(jax.tree_util.tree_leaves(stale)) > 1e3 * F64_GRAD_ATOL


def test_learning_rate_decay_scales_every_step_linearly():
    """With ``lr_decay_updates=4`` the update at step 3 is the constant-rate update at a quarter of
    every learning rate, and from step 4 on actor, critic and log α stop moving. (The schedule is
    the same code for every agent; one suffices.) In float64: see F64_STEP_ATOL."""
    algo = "xdsac"
    decaying = make_agent(tiny_config(algo, lr_decay_updates=4), EXAMPLE, NUM_ACTIONS[algo])
    quarter = make_agent(
        tiny_config(algo, actor_lr=2.5e-3, critic_lr=2.5e-3), EXAMPLE, NUM_ACTIONS[algo]
    )  # alpha_lr follows critic_lr

    def learned(agent, steps, state, batch, key):
        starts = jax.vmap(lambda s: state.replace(step=s))(jnp.asarray(steps, jnp.int32))
        new = jax.jit(jax.vmap(agent.update, in_axes=(None, 0, None)))(key, starts, batch)[0]
        moments = [adam_first_moment(getattr(new, f"{n}_opt_state")) for n in ("actor", "critic", "alpha")]
        rest = (moments, new.target_critic_params)
        return [
            jax.tree.map(lambda x, i=i: x[i], ((new.actor_params, new.critic_params, new.log_alpha), rest))
            for i in range(len(steps))
        ]

    with jax.enable_x64(True):
        state = float64_state(decaying.init(jax.random.PRNGKey(3)))
        batch, key = make_batch(jax.random.PRNGKey(4), algo), jax.random.PRNGKey(5)
        constant = state.replace(hparams=quarter.init(jax.random.PRNGKey(3)).hparams)
        [(at_quarter, (quarter_moments, quarter_target))] = learned(quarter, [3], constant, batch, key)
        (at_3, (moments_3, target_3)), (at_4, _), (at_9, _) = learned(decaying, [3, 4, 9], state, batch, key)
        before = (state.actor_params, state.critic_params, state.log_alpha)
        assert_float64((at_3, moments_3, at_quarter, constant.hparams))
        # same gradients (Adam's μ = 0.1·g): the decay changes learning rates only
        leaves_close(moments_3, quarter_moments, rtol=0, atol=0.1 * F64_GRAD_ATOL)
        leaves_close(at_3, at_quarter, rtol=0, atol=F64_STEP_ATOL)
        leaves_close(target_3, quarter_target, rtol=0, atol=0.1 * F64_STEP_ATOL)  # τ = 0.1 does not decay
        moved = jax.tree.map(lambda a, b: np.abs(a - b).max(), at_quarter, before)
        assert max(jax.tree_util.tree_leaves(moved)) > 1e-3
        leaves_close(at_4, before, rtol=0, atol=0)  # p − 0·u = p exactly
        leaves_close(at_9, before, rtol=0, atol=0)


@pytest.fixture(scope="module")
def xsac_agent():
    agent = make_agent(tiny_config("xsac"), EXAMPLE, 2)
    return agent, agent.init(jax.random.PRNGKey(6))


def test_xsac_objective_matches_monte_carlo_estimate():
    """§8 item 6: Σ_k w_k E_ε[α log π(a_k) − Q(a_k)] − κH(w) (one sample per component, as implemented)
    equals the brute-force E_{k~w, a~π_k}[α log π(a) − Q(a)] − κH(w) from ancestral sampling."""
    key = jax.random.PRNGKey(7)
    k1, k2, k3 = jax.random.split(key, 3)
    loc = jax.random.normal(k1, (2, 3, 1, 2))
    log_scale = jax.random.uniform(k2, (2, 3, 1, 2), minval=-1.5, maxval=0.0)
    logits = jax.random.normal(k3, (2, 3))
    present = jnp.array([[True, True, True], [True, True, False]])
    pi = SquashedGaussianMixture.from_objects(loc, log_scale, logits, present)
    alpha, kappa = 0.3, 0.1

    def q_fn(a):  # (..., A) -> (2, ...): a fixed two-critic "Q"
        base = -jnp.sum(jnp.square(a - 0.2), axis=-1)
        return jnp.stack([base, base + 0.1 * a[..., 0]])

    def implemented(k):
        actions, log_probs = pi.sample_per_component(k)  # (2, K, A), (2, K)
        return losses.xsac_actor_loss(pi.weights, log_probs, q_fn(actions), alpha, kappa)[0]

    draws = 20000
    impl_draws = jax.jit(jax.vmap(implemented))(jax.random.split(jax.random.PRNGKey(8), draws))
    impl = jnp.mean(impl_draws)

    def brute(k):
        action, log_prob = pi.sample_and_log_prob(k, floor_density=True)  # k ~ w, a ~ π_k
        return alpha * log_prob - jnp.min(q_fn(action), axis=0)

    samples = jax.jit(jax.vmap(brute))(jax.random.split(jax.random.PRNGKey(9), 10 * draws))  # (10·draws, 2)
    expected = jnp.mean(samples) - kappa * jnp.mean(pi.weights_entropy())
    stderr = np.hypot(np.std(impl_draws) / np.sqrt(draws), np.std(samples.mean(-1)) / np.sqrt(10 * draws))
    assert abs(float(impl - expected)) < 4 * float(stderr) + 1e-3, (impl, expected, stderr)
    assert float(stderr) < 0.005  # the check is tight enough to catch a missing term


def permute_slots(batch, perm):
    return {
        **batch,
        "obs": {**batch["obs"], "things_set": batch["obs"]["things_set"][:, perm]},
        "next_obs": {**batch["next_obs"], "things_set": batch["next_obs"]["things_set"][:, perm]},
    }


@functools.cache
def loss_checks(algo):
    """One jitted pass over the X agents' losses on clean / garbage-padded / permuted batches,
    with κ and with κ = 0 (a Deep Set critic, which masks absent slots and ignores slot order)."""
    agent = make_agent(tiny_config(algo, feature_extractor="deepset"), EXAMPLE, NUM_ACTIONS[algo])
    state = agent.init(jax.random.PRNGKey(13))
    clean = make_batch(jax.random.PRNGKey(14), algo)
    batches = {"clean": clean, "dirty": make_batch(jax.random.PRNGKey(14), algo, absent_value=1e4)}
    if algo == "xdsac":  # XSAC draws its noise per slot, so a permutation re-pairs noise and objects
        batches["permuted"] = permute_slots(clean, jnp.array([2, 0, 1]))
    no_kappa = state.replace(hparams=state.hparams.replace(kappa=jnp.zeros_like(state.hparams.kappa)))
    key = jax.random.PRNGKey(15)

    @jax.jit
    def run(state, no_kappa, batches):
        out = {}
        for name, batch in batches.items():
            # gradients with κ = 0, so that a gradient on φ cannot come from the κ term alone
            (actor, aux), actor_grads = jax.value_and_grad(agent.actor_loss, has_aux=True)(
                no_kappa.actor_params, no_kappa, batch, key
            )
            (critic, _), critic_grads = jax.value_and_grad(agent.critic_loss, has_aux=True)(
                state.critic_params, state, batch, key
            )
            out[name] = {"actor": actor, "critic": critic, "aux": aux}
            out[name]["grads"] = (actor_grads, critic_grads)
        out["with_kappa"], out["with_kappa_aux"] = agent.actor_loss(state.actor_params, state, clean, key)
        out["actor_output"] = agent.actor_output(state.actor_params, clean["obs"])
        out["weights"] = agent.policy(state.actor_params, clean["obs"]).weights
        if agent.is_discrete:
            out["q"] = agent.networks.critic.apply(state.critic_params, clean["obs"])
        return out

    return run(state, no_kappa, batches)


def mixture_logit_kernel(grads):
    return grads["params"]["trunk"]["mixture_logit"]["kernel"]


@pytest.mark.parametrize("algo", ["xsac", "xdsac"])
def test_actor_gradient_reaches_the_mixture_logits(algo):
    """§7.2.1: no stop-gradient on the weights; even with κ = 0 the φ layer is trained."""
    out = loss_checks(algo)
    phi = np.asarray(mixture_logit_kernel(out["clean"]["grads"][0]))
    assert np.all(np.isfinite(phi)) and np.abs(phi).max() > 1e-6
    for leaf in jax.tree_util.tree_leaves(out["clean"]["grads"]):
        assert np.all(np.isfinite(leaf))


@pytest.mark.parametrize("algo", ["xsac", "xdsac"])
def test_kappa_term_is_minus_kappa_times_weight_entropy(algo):
    out = loss_checks(algo)
    weights = out["weights"]
    h_w = -jnp.sum(weights * jnp.log(jnp.clip(weights, 1e-10, 1)), axis=-1)
    np.testing.assert_allclose(
        out["with_kappa"] - out["clean"]["actor"], -0.05 * jnp.mean(h_w), rtol=1e-4, atol=1e-7
    )
    np.testing.assert_allclose(out["with_kappa_aux"]["mixture_entropy"], jnp.mean(h_w), rtol=1e-5)
    # absent slot 2 carries exactly zero weight
    np.testing.assert_array_equal(weights.reshape(B, O, -1)[:, 2], 0.0)


def test_xdsac_actor_loss_equals_explicit_sum_over_actions():
    out = loss_checks("xdsac")
    w = float64_object_weights(out["actor_output"])
    q_obj = np.asarray(jax.nn.softmax(out["actor_output"].logits, axis=-1), np.float64)
    q = np.asarray(out["q"], np.float64).mean(0)
    total = 0.0
    for b in range(B):
        pi = sum(w[b, o] * q_obj[b, o] for o in range(O))
        np.testing.assert_allclose(pi.sum(), 1.0, rtol=1e-6)  # §8 item 7
        h_pi = -np.sum(pi * np.log(pi))
        h_w = -sum(x * np.log(x) for x in w[b] if x > 0)
        total += -(np.dot(pi, q[b]) + 0.1 * h_pi + 0.05 * h_w)
    np.testing.assert_allclose(out["with_kappa"], total / B, rtol=1e-5)


def test_permuting_object_slots_leaves_the_losses_unchanged():
    """§8 item 8 at agent level (XDSAC: no sampling noise to re-order)."""
    out = loss_checks("xdsac")
    for name in ("actor", "critic"):
        np.testing.assert_allclose(out["clean"][name], out["permuted"][name], rtol=1e-5)


# Garbage in absent slots (make_batch's absent_value) changes the X agents' losses and gradients by
# rounding only, never in value: the networks centre the mixture logits over *all* slots (§3.1 step
# 2), so the garbage slot's raw logit enters the present slots' centred logits (here ≈ 4e2 instead
# of ≲ 1) and each rounds by eps·|logit|; and the centring passes the absent slot a gradient
# −(1/O)·Σ_present g_k, zero in exact arithmetic but ≈ eps·|g| once rounded, which meets the
# garbage row's activations (inputs of GARBAGE, times layer gains) in the trunk's kernels. Both are
# eps × GARBAGE × (network gains, spread of the per-slot objectives, sums of ≲ 10² terms): a factor
# 10³ covers those, in float64 2.2e-16·1e4·1e3 ≈ 2e-9 on losses ~1 and gradients ~0.1–1, while a
# slot that leaks into the loss moves both by ≳ 1e-3. In float32 the same bound would be ≈ 1,
# so the comparison runs in float64.
GARBAGE = 1e4
F64_GARBAGE_ATOL = float(np.finfo(np.float64).eps) * GARBAGE * 1e3


@pytest.mark.parametrize("algo", ["xsac", "xdsac"])
def test_absent_slots_with_extreme_values_stay_finite_and_irrelevant(algo):
    """§7.2.4: absent rows are masked everywhere; garbage in them stays finite (float32, as in
    training) and changes neither loss nor gradient (float64: see F64_GARBAGE_ATOL)."""
    dirty = loss_checks(algo)["dirty"]  # float32; its absent slots hold 1e4 = GARBAGE
    for name, leaf in jax.tree_util.tree_leaves_with_path(dirty):
        assert np.all(np.isfinite(leaf)), jax.tree_util.keystr(name)

    agent = make_agent(tiny_config(algo, feature_extractor="deepset"), EXAMPLE, NUM_ACTIONS[algo])
    key = jax.random.PRNGKey(15)

    @jax.jit
    @functools.partial(jax.vmap, in_axes=(0, None))  # over (clean, dirty): one trace for both
    def losses_and_grads(batch, state):
        actor = jax.value_and_grad(lambda p: agent.actor_loss(p, state, batch, key)[0])(state.actor_params)
        critic = jax.value_and_grad(lambda p: agent.critic_loss(p, state, batch, key)[0])(state.critic_params)
        return actor, critic

    with jax.enable_x64(True):
        state = float64_state(agent.init(jax.random.PRNGKey(13)))
        pair = [make_batch(jax.random.PRNGKey(14), algo, absent_value=v) for v in (0.0, GARBAGE)]
        out = losses_and_grads(jax.tree.map(lambda *x: jnp.stack(x), *pair), state)
        assert_float64(out)
        clean, dirty = (jax.tree.map(lambda x, i=i: x[i], out) for i in range(2))
        leaves_close(dirty, clean, rtol=0, atol=F64_GARBAGE_ATOL)


def test_terminated_and_truncated_are_kept_separate():
    """done = terminated only; truncated transitions are dropped ("drop") or bootstrapped ("bootstrap")."""
    algo = "dsac"
    batch = make_batch(jax.random.PRNGKey(23), algo)
    drop = make_agent(tiny_config(algo), EXAMPLE, 4)
    boot = make_agent(tiny_config(algo, truncation="bootstrap"), EXAMPLE, 4)
    state = drop.init(jax.random.PRNGKey(24))
    truncated = {**batch, "truncated": jnp.arange(B) == 1}
    changed = {**truncated, "reward": truncated["reward"].at[1].add(50.0)}
    terminal = {**batch, "terminated": jnp.ones(B, bool)}

    @jax.jit
    def run(state):
        key = jax.random.PRNGKey(0)
        losses_ = {}
        for name, agent in (("drop", drop), ("boot", boot)):
            for tag, b in (("truncated", truncated), ("changed", changed)):
                losses_[name, tag] = agent.critic_loss(state.critic_params, state, b, key)[0]
        return losses_, drop.critic_loss(state.critic_params, state, terminal, key)[1]

    out, aux = run(state)
    # "drop": the truncated transition has no influence on the critic loss
    np.testing.assert_allclose(out["drop", "truncated"], out["drop", "changed"], rtol=1e-6)
    # "bootstrap": it counts (and is not masked like a terminal)
    assert float(out["boot", "changed"]) > float(out["boot", "truncated"]) + 1.0
    # terminated transitions regress on the bare reward: all-terminal batch ⇒ target = reward
    np.testing.assert_allclose(aux["q_val_min"], jnp.min(batch["reward"]), rtol=1e-6)
    np.testing.assert_allclose(aux["q_val_max"], jnp.max(batch["reward"]), rtol=1e-6)


@pytest.mark.parametrize("algo", ALGOS)
def test_act_modes(algo):
    agent = make_agent(tiny_config(algo, epsilon_random=0.0), EXAMPLE, NUM_ACTIONS[algo])
    state = agent.init(jax.random.PRNGKey(25))
    obs = make_batch(jax.random.PRNGKey(26), algo, batch=64)["obs"]

    @jax.jit
    def act_all(state, obs):
        keys = (jax.random.PRNGKey(1), jax.random.PRNGKey(2))
        out = {mode: [agent.act(k, state, obs, mode) for k in keys] for mode in ("train", "eval")}
        out["single"] = agent.act(keys[0], state, jax.tree_util.tree_map(lambda x: x[0], obs), "train")
        return out

    out = act_all(state, obs)
    discrete = algo in ("dsac", "xdsac")
    for mode in ("train", "eval"):
        a1, a2 = out[mode]
        if discrete:
            assert a1.shape == (64,) and a1.dtype == jnp.int32
            assert np.all((a1 >= 0) & (a1 < NUM_ACTIONS[algo]))
        else:
            assert a1.shape == (64, 2) and np.all(np.abs(a1) <= 1)
        stochastic = mode == "train" or algo == "xsac"  # §3.8: only XSAC evaluates stochastically
        assert (not np.array_equal(a1, a2)) == stochastic, (mode, algo)
    assert out["single"].shape == (() if discrete else (2,))
    with pytest.raises(ValueError, match="train"):
        agent.act(jax.random.PRNGKey(0), state, obs, "greedy")
    assert "deterministic" in ACT_MODES


@pytest.mark.slow
def test_discrete_exploration_epsilon():
    agent = make_agent(tiny_config("xdsac", epsilon_random=1.0), EXAMPLE, 4)
    state = agent.init(jax.random.PRNGKey(27))
    obs = make_batch(jax.random.PRNGKey(28), "xdsac", batch=400)["obs"]

    @jax.jit
    def run(state, obs):
        train = agent.act(jax.random.PRNGKey(1), state, obs, "train")
        greedy = agent.act(jax.random.PRNGKey(1), state, obs, "eval")  # never explores
        return train, greedy, agent.policy(state.actor_params, obs).mode()

    train, greedy, mode = run(state, obs)
    counts = np.bincount(np.asarray(train), minlength=4)
    assert counts.min() > 60  # uniform over 4 actions
    np.testing.assert_array_equal(greedy, mode)


@pytest.mark.parametrize("algo", ["dsac", pytest.param("xdsac", marks=pytest.mark.slow)])
def test_stochastic_mode_samples_the_policy_without_exploration(algo):
    # ε = 1 would make every "train" action uniform; "stochastic" must ignore it and follow π(a|s).
    agent = make_agent(tiny_config(algo, epsilon_random=1.0), EXAMPLE, NUM_ACTIONS[algo])
    state = agent.init(jax.random.PRNGKey(29))
    one_obs = make_batch(jax.random.PRNGKey(30), algo, batch=1)["obs"]
    draws = 20_000
    obs = jax.tree_util.tree_map(lambda x: jnp.repeat(x, draws, axis=0), one_obs)

    @jax.jit
    def run(state, obs):
        sampled = agent.act(jax.random.PRNGKey(3), state, obs, "stochastic")
        return sampled, agent.policy(state.actor_params, one_obs).probs()[0]

    sampled, probs = jax.device_get(run(state, obs))
    frequencies = np.bincount(sampled, minlength=NUM_ACTIONS[algo]) / draws
    # Each frequency is a mean of `draws` Bernoulli(p) draws: 5 standard errors (plus float32
    # rounding of p) bound it for any key with probability > 1 - 1e-5 per action.
    bound = 5 * np.sqrt(probs * (1 - probs) / draws) + 1e-6
    assert np.all(np.abs(frequencies - probs) <= bound), (frequencies, probs)
    assert np.ptp(probs) > 0.01  # the policy is not uniform, so ε = 1 would fail the check


def test_batch_layout_errors_are_clear():
    agent = make_agent(tiny_config("sac"), EXAMPLE, 2)
    state = agent.init(jax.random.PRNGKey(0))
    batch = make_batch(jax.random.PRNGKey(1), "sac")
    with pytest.raises(ValueError, match="missing"):
        agent.update(jax.random.PRNGKey(0), state, {k: v for k, v in batch.items() if k != "truncated"})
    with pytest.raises(ValueError, match="action"):
        agent.update(jax.random.PRNGKey(0), state, {**batch, "action": batch["action"][:, :1]})
    with pytest.raises(ValueError, match="things_set"):
        bad = {**batch, "obs": {**batch["obs"], "things_set": batch["obs"]["things_set"][:, :2]}}
        agent.update(jax.random.PRNGKey(0), state, bad)
    with pytest.raises(ValueError, match="unbatched"):
        make_agent(tiny_config("sac"), {"state": jnp.zeros((1, S)), "things_set": jnp.zeros((1, O, F))}, 2)
    with pytest.raises(TypeError):
        make_agent({"algo": "sac"}, EXAMPLE, 2)


def test_agent_state_is_a_pytree_with_traced_hparams(xsac_agent):
    _, state = xsac_agent
    assert isinstance(state, AgentState)
    leaves = jax.tree_util.tree_leaves(state.hparams)
    assert len(leaves) == 8 and all(leaf.shape == () for leaf in leaves)
    np.testing.assert_allclose(state.hparams.target_entropy, -2.0)  # −A default for XSAC
    np.testing.assert_allclose(state.hparams.alpha_lr, state.hparams.critic_lr)
    assert {f.name for f in dataclasses.fields(HyperParams)} == {*TRACED_FIELDS, "init_log_alpha"}
    np.testing.assert_allclose(state.log_alpha, state.hparams.init_log_alpha)


@pytest.mark.slow
def test_update_runs_in_float64():
    with jax.enable_x64(True):
        agent = make_agent(tiny_config("dsac"), {k: v.astype(jnp.float64) for k, v in EXAMPLE.items()}, 4)
        state = agent.init(jax.random.PRNGKey(0))
        batch = make_batch(jax.random.PRNGKey(1), "dsac")
        new_state, metrics = jax.jit(agent.update)(jax.random.PRNGKey(2), state, batch)
        assert new_state.log_alpha.dtype == jnp.float64
        assert jax.tree_util.tree_leaves(new_state.actor_params)[0].dtype == jnp.float64
        assert all(np.isfinite(v) for v in metrics.values())


# ---------------------------------------------------------------------------------------------
# Fixed α and gradient clipping (intersection: α = 0.015 for all four agents, clip 10 except SAC)
# ---------------------------------------------------------------------------------------------

FIXED_ALPHA, TINY_CLIP = 0.015, 1e-3
# SAC (critic-only clipping) and DSAC (the reference's broken fixed-α path) by default; the X agents share
# the code paths of DSAC and are compiled only in the slow run.
FIXED_ALPHA_ALGOS = ["sac", "dsac", *(pytest.param(a, marks=pytest.mark.slow) for a in ("xsac", "xdsac"))]


def rbg_key(seed):
    """Threefry kernels are slow to compile on CPU; the RBG generator keeps these compiles small."""
    return jax.random.key(seed, impl="unsafe_rbg")


@functools.cache
def fixed_alpha_clipped_run(algo):
    """One jitted update with a fixed α and a clip norm far below the gradient norms."""
    config = tiny_config(algo, auto_alpha=False, init_alpha=FIXED_ALPHA, clip_norm=TINY_CLIP)
    agent = make_agent(config, EXAMPLE, NUM_ACTIONS[algo])
    state = jax.jit(agent.init)(rbg_key(40))  # one compile instead of many eager op dispatches
    batch = make_batch(jax.random.PRNGKey(41), algo)
    new_state, metrics = jax.jit(agent.update)(rbg_key(42), state, batch)
    return agent, state, batch, new_state, metrics


def adam_first_moment(opt_state):
    """Adam's μ tree inside a (possibly chained) optax state."""
    found = [
        s
        for s in jax.tree_util.tree_leaves(opt_state, is_leaf=lambda x: isinstance(x, optax.ScaleByAdamState))
        if isinstance(s, optax.ScaleByAdamState)
    ]
    assert len(found) == 1
    return found[0].mu


@pytest.mark.parametrize("algo", FIXED_ALPHA_ALGOS)
def test_fixed_alpha_is_used_and_never_learned(algo):
    """The reference's DSAC fixed-α path crashes (§2.2 quirk); here every agent honours a fixed α."""
    agent, state, batch, new_state, metrics = fixed_alpha_clipped_run(algo)
    np.testing.assert_allclose(state.alpha, FIXED_ALPHA, rtol=1e-6)
    assert float(new_state.log_alpha) == float(state.log_alpha)
    np.testing.assert_allclose(metrics["ent_coef"], FIXED_ALPHA, rtol=1e-6)
    assert "loss_ent_coef" not in metrics
    assert all(np.isfinite(v) for v in metrics.values())
    if algo == "dsac":  # closed form −mean(Σ_a π Q̄ + α H) at α = 0.015, against the updated critic (§1.5)
        probs = agent.policy(state.actor_params, batch["obs"]).probs()
        mean_q = jnp.mean(agent.networks.critic.apply(new_state.critic_params, batch["obs"]), axis=0)
        entropy = -jnp.sum(probs * jnp.log(probs), axis=-1)
        expected = -jnp.mean(jnp.sum(probs * mean_q, axis=-1) + FIXED_ALPHA * entropy)
        np.testing.assert_allclose(metrics["loss_actor"], expected, rtol=1e-5)


@pytest.mark.parametrize("algo", FIXED_ALPHA_ALGOS)
def test_clip_norm_clips_critic_always_and_actor_except_for_sac(algo):
    """§1.4: with clip_norm set, SAC clips only its critic, DSAC/XSAC/XDSAC actor and critic.

    Adam's first moment after one step is (1 − β1)·g_clipped, so its global norm reveals the clipping.
    """
    _, _, _, new_state, metrics = fixed_alpha_clipped_run(algo)
    critic_mu = optax.tree.norm(adam_first_moment(new_state.critic_opt_state))
    actor_mu = optax.tree.norm(adam_first_moment(new_state.actor_opt_state))
    assert (
        float(metrics["grad_norm_critic"]) > 10 * TINY_CLIP
        and float(metrics["grad_norm_actor"]) > 10 * TINY_CLIP
    )
    np.testing.assert_allclose(critic_mu, 0.1 * TINY_CLIP, rtol=1e-4)
    expected_actor = metrics["grad_norm_actor"] if algo == "sac" else TINY_CLIP
    np.testing.assert_allclose(actor_mu, 0.1 * expected_actor, rtol=1e-4)


# ---------------------------------------------------------------------------------------------
# Multi-agent intersection agents (smoke sizes): per-agent observations, (E, 8) acting, 9 objects
# ---------------------------------------------------------------------------------------------


def intersection_observation(key, batch_shape, max_present=7):
    """Per-agent observations: present vehicle rows contiguous from row 0, count varying per agent."""
    k_rows, k_count, k_state = jax.random.split(key, 3)
    rows = jax.random.uniform(k_rows, (*batch_shape, 8, 7), minval=-1, maxval=1)
    count = jax.random.randint(k_count, batch_shape, 0, max_present + 1)
    present = jnp.arange(8) < count[..., None]
    rows = jnp.where(present[..., None], rows.at[..., 0].set(1.0), 0.0)
    state = jax.random.uniform(k_state, (*batch_shape, 66), minval=-1, maxval=1)
    return {"vehicles_set": rows, "state": state}


# XDSAC also acts and updates on Intersection batches in tests/test_train_intersection.py.
@pytest.mark.parametrize("algo", ["xsac", pytest.param("xdsac", marks=pytest.mark.slow)])
def test_intersection_agent_acts_on_agent_batches_and_updates(algo):
    from xrl_jax.config import preset
    from xrl_jax.networks import ENV_OBSERVATIONS

    discrete = algo == "xdsac"
    action_size = algo_action_size(algo)
    example = intersection_observation(jax.random.PRNGKey(50), ())
    agent = make_agent(preset("smoke", "intersection", algo), example, action_size)
    assert agent.obs_shape == ENV_OBSERVATIONS["intersection"]
    assert agent.networks.config.neutral_object and agent.neutral_object and agent.num_mixture_objects == 9
    state = jax.jit(agent.init)(rbg_key(51), example)
    obs = intersection_observation(jax.random.PRNGKey(52), (2, 8))
    obs = {k: v.at[0, 0].set(0.0) for k, v in obs.items()}  # agent (0, 0): no other vehicle, zero state

    @jax.jit
    def act_and_explain(state, obs):
        # "eval" is "train" (XSAC) or "deterministic" (XDSAC) without ε: not compiled twice here
        actions = {mode: agent.act(rbg_key(53), state, obs, mode) for mode in ("train", "deterministic")}
        pi = agent.policy(state.actor_params, obs)
        return actions, pi.weights, pi.present

    actions, weights, present = act_and_explain(state, obs)
    for action in actions.values():
        if discrete:
            assert action.shape == (2, 8) and action.dtype == jnp.int32
            assert np.all((action >= 0) & (action < 12))
        else:
            assert action.shape == (2, 8, 3) and np.all(np.abs(action) <= 1)
    assert weights.shape == present.shape == (2, 8, 9)
    np.testing.assert_allclose(jnp.sum(weights, -1), 1.0, rtol=1e-5)
    assert bool(jnp.all(present[..., 0])) and bool(jnp.all(weights[..., 0] > 0))
    np.testing.assert_array_equal(present[..., 1:], obs["vehicles_set"][..., 0] > 0)
    np.testing.assert_array_equal(jnp.where(present, 0.0, weights), 0.0)
    np.testing.assert_allclose(weights[0, 0], np.eye(9)[0])  # alone: only the neutral component

    # one update on per-agent transitions flattened into the batch axis
    batch_size = 6
    k_obs, k_next, k_action, k_reward = jax.random.split(jax.random.PRNGKey(54), 4)
    if discrete:
        action = jax.random.randint(k_action, (batch_size,), 0, 12)
    else:
        action = jax.random.uniform(k_action, (batch_size, 3), minval=-1, maxval=1)
    batch = {
        "obs": intersection_observation(k_obs, (batch_size,)),
        "action": action,
        "reward": jax.random.normal(k_reward, (batch_size,)),
        "next_obs": intersection_observation(k_next, (batch_size,)),
        "terminated": jnp.arange(batch_size) == 0,
        "truncated": jnp.zeros(batch_size, bool),
    }
    new_state, metrics = jax.jit(agent.update)(rbg_key(55), state, batch)
    for name in ("loss_actor", "loss_critic", "grad_norm_actor", "grad_norm_critic", "ent_coef"):
        assert np.isfinite(metrics[name]), name
    np.testing.assert_allclose(metrics["ent_coef"], 0.015, rtol=1e-6)  # fixed α
    assert float(new_state.log_alpha) == float(state.log_alpha)
    assert int(new_state.step) == 1
    changed = jax.tree_util.tree_map(
        lambda a, b: bool(jnp.any(a != b)), state.actor_params, new_state.actor_params
    )
    assert all(jax.tree_util.tree_leaves(changed))
