"""Networks: shapes, set invariances, masking, fast acting path, critic broadcasting, sizes
(docs/algorithms.md §3-§4)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from network_support import (
    component_weights,
    make_test_networks,
    mixture_policy,
    object_weights,
    trajectory_to_set,
)

from xrl_jax import networks as N
from xrl_jax.benchmarks import table_one as costs
from xrl_jax.benchmarks.table_one import count_params
from xrl_jax.config import ALGOS
from xrl_jax.distributions import LOG_STD_MAX, MIXTURE_LOG_STD_MIN, SAC_LOG_STD_MIN

# Threefry kernels are slow to compile on CPU; the RBG generator keeps these tests fast.
KEY = jax.random.key(0, impl="unsafe_rbg")
TINY = dict(actor_width=8, critic_width=8, fe_width=8)
BATCH = (2, 3)


def rng_key(seed):
    return jax.random.key(seed, impl="unsafe_rbg")


def random_observation(seed, batch_shape, num_objects, object_features, num_present, state_dim=6):
    """Set with the first ``num_present`` rows present (flag 1) and all-zero padding (numpy: no compiles)."""
    rng = np.random.default_rng(seed)
    rows = rng.uniform(-1, 1, (*batch_shape, num_objects, object_features)).astype(np.float32)
    rows[..., 0] = 1.0
    rows[..., num_present:, :] = 0.0
    state = rng.uniform(-1, 1, (*batch_shape, state_dim)).astype(np.float32)
    return {"state": jnp.asarray(state), "cones_set": jnp.asarray(rows)}


def random_params(init, *args, seed=0, scale=0.5):
    """Parameters with the module's structure, drawn with numpy instead of compiling the Flax init.

    Initial-value statistics do not matter for these tests (the Fourier init has its own test), and
    compiling one random kernel per layer would dominate the suite's run time on CPU.
    """
    rng = np.random.default_rng(seed)
    shapes = jax.eval_shape(init, KEY, *args)
    return jax.tree_util.tree_map(
        lambda s: jnp.asarray(scale * rng.standard_normal(s.shape), s.dtype), shapes
    )


@pytest.fixture(scope="module")
def small_obs():
    """One batch of Country-Road-like observations with 7 slots, 4 present."""
    return random_observation(1, BATCH, 7, 5, 4)


# ---------------------------------------------------------------------------------------------
# Shapes for every (env, algo) pair, with leading batch axes, through jit
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env", ["country_road", "tracking", "intersection"])
@pytest.mark.parametrize("algo", ALGOS)
def test_output_shapes_with_leading_batch_axes(env, algo):
    nets = make_test_networks(env, algo, **TINY)
    obs = nets.dummy_observation(BATCH)
    # the intersection X actors carry the neutral object in front of the 8 vehicle slots
    o, a_dim, n = nets.obs_shape.num_objects + int(nets.config.neutral_object), 3, 12
    assert o == (9 if (env, nets.config.is_mixture) == ("intersection", True) else nets.obs_shape.num_objects)
    actor_params = jax.eval_shape(nets.init_actor, KEY)
    critic_params = jax.eval_shape(nets.init_critic, KEY)
    out = jax.eval_shape(nets.actor.apply, actor_params, obs)
    if algo == "sac":
        assert out.mean.shape == out.log_std.shape == (*BATCH, a_dim)
    elif algo == "dsac":
        assert out.shape == (*BATCH, n)
    elif algo == "xsac":
        assert out.means.shape == out.log_stds.shape == (*BATCH, o, 1, a_dim)
        assert out.mixture_logits.shape == out.present.shape == (*BATCH, o)
    else:
        assert out.logits.shape == (*BATCH, o, n)
        assert out.mixture_logits.shape == out.present.shape == (*BATCH, o)
        probs = jax.eval_shape(lambda p, o: mixture_policy(nets.actor.apply(p, o)).probs(), actor_params, obs)
        assert probs.shape == (*BATCH, n)
    if not nets.config.is_discrete:
        k_actions = jnp.zeros((*BATCH, 5, a_dim))
        q = jax.eval_shape(nets.critic.apply, critic_params, obs, k_actions)
        assert q.shape == (2, *BATCH, 5)
        q = jax.eval_shape(nets.critic.apply, critic_params, obs, nets.dummy_action(BATCH))
        assert q.shape == (2, *BATCH)
    else:
        q = jax.eval_shape(nets.critic.apply, critic_params, obs)
        assert q.shape == (2, *BATCH, n)


def test_jit_runs_actor_and_critic_and_outputs_are_finite():
    nets = make_test_networks("country_road", "xsac", **TINY)
    actor_params = jax.jit(nets.init_actor)(KEY)
    critic_params = random_params(nets.critic.init, nets.dummy_observation(), nets.dummy_action())
    obs = random_observation(2, (4,), 100, 5, 30)
    out = jax.jit(nets.actor.apply)(actor_params, obs)
    actions = jnp.tanh(out.means)  # (4, 100, 1, 3): every component's squashed mean
    q = jax.jit(nets.critic.apply)(critic_params, obs, actions)
    assert q.shape == (2, 4, 100, 1)
    for leaf in jax.tree_util.tree_leaves((out, q)):
        assert jnp.all(jnp.isfinite(leaf))


def test_float64_inputs_work_under_x64():
    with jax.enable_x64(True):
        nets = make_test_networks("tracking", "sac", actor_depth=1, critic_depth=1, **TINY)
        obs = nets.dummy_observation((2,))
        assert obs["state"].dtype == jnp.float64
        out = jax.jit(nets.actor.apply)(jax.jit(nets.init_actor)(KEY), obs)
        q = jax.jit(nets.critic.apply)(
            random_params(nets.critic.init, obs, jnp.zeros((2, 3))), obs, jnp.zeros((2, 3))
        )
        assert out.mean.dtype == jnp.float64 and q.dtype == jnp.float64
        assert N.tracking_index_feature(25).dtype == jnp.float64


# ---------------------------------------------------------------------------------------------
# Observation helpers, positional encoding, Fourier layer
# ---------------------------------------------------------------------------------------------


def test_tracking_index_feature_quirk_divides_by_length():
    index = np.asarray(N.tracking_index_feature(25))
    assert index.shape == (25,)
    np.testing.assert_allclose(index[:3], [-1.0, -0.92, -0.84], atol=1e-6)
    np.testing.assert_allclose(index[-1], 0.92, atol=1e-6)  # not +1: 2i/L - 1, §4.2 quirk
    np.testing.assert_allclose(np.diff(index), 0.08, atol=1e-6)


def test_trajectory_to_set_rows():
    flat = jnp.arange(50.0).reshape(1, 50) / 100
    rows = trajectory_to_set(flat)
    assert rows.shape == (1, 25, 4)
    np.testing.assert_array_equal(rows[0, :, 0], 1.0)
    np.testing.assert_allclose(rows[0, :, 1], N.tracking_index_feature(25))
    np.testing.assert_allclose(rows[0, 3, 2:], [0.06, 0.07])


def test_positional_encoding_frequency_major_layout():
    v = jnp.array([[0.1, -0.3, 0.7]])
    pe = N.positional_encoding(v)
    assert pe.shape == (1, 27)  # 9·D
    table = np.asarray(pe).reshape(9, 3)
    for k in range(4):
        np.testing.assert_allclose(table[k], np.cos(np.pi * 2**k * np.asarray(v[0])), atol=1e-6)
        np.testing.assert_allclose(table[4 + k], np.sin(np.pi * 2**k * np.asarray(v[0])), atol=1e-6)
    np.testing.assert_allclose(table[8], v[0])
    assert N.positional_encoding(v, include_input=False).shape == (1, 24)


def test_flat_pe_extractor_size_and_sorted_key_order():
    obs = {"state": jnp.full((6,), 0.2), "trajectory_set": trajectory_to_set(jnp.full((50,), -0.4))}
    features = jax.jit(N.FlatPEExtractor().apply)({}, obs)
    assert features.shape == (9 * 6 + 9 * 50,)
    np.testing.assert_allclose(features[:54], N.positional_encoding(obs["state"]), atol=1e-6)
    np.testing.assert_allclose(features[54:], N.positional_encoding(jnp.full((50,), -0.4)), atol=1e-6)


def test_fourier_layer_init_statistics_and_formula():
    layer = N.FourierFeatures(features=4096, scale=30.0)
    x = jnp.array([0.3, -0.2, 0.5, 0.1])
    params = jax.jit(layer.init)(KEY, x)
    kernel, bias = params["params"]["linear"]["kernel"], params["params"]["linear"]["bias"]
    assert abs(float(jnp.std(kernel)) / 7.5 - 1) < 0.03  # std = b / d_in = 30 / 4
    assert abs(float(jnp.mean(kernel))) < 0.3
    assert float(bias.min()) >= -1 and float(bias.max()) <= 1 and abs(float(bias.mean())) < 0.05
    np.testing.assert_allclose(
        jax.jit(layer.apply)(params, x), jnp.sin(jnp.pi * (x @ kernel + bias)), atol=1e-4
    )


def test_object_inputs_reshaper_and_neutral_object(small_obs):
    inputs, present = N.object_inputs(small_obs)
    assert inputs.shape == (*BATCH, 7, 11) and present.shape == (*BATCH, 7)
    np.testing.assert_array_equal(inputs[..., :5], small_obs["cones_set"])
    np.testing.assert_array_equal(inputs[..., 2, 5:], small_obs["state"])
    np.testing.assert_array_equal(present[0, 0], [True] * 4 + [False] * 3)
    # The neutral row (docs/algorithms.md §4.1): as in the original all zero, present column included,
    # while the mask counts it present; with neutral_flag its present column is 1. The other rows and
    # their mask are unchanged behind it.
    for flag, first_column in ((False, 0.0), (True, 1.0)):
        inputs, present = N.object_inputs(small_obs, neutral_object=True, neutral_flag=flag)
        assert inputs.shape == (*BATCH, 8, 11)
        np.testing.assert_array_equal(
            inputs[..., 0, :5], jnp.broadcast_to(jnp.array([first_column, 0, 0, 0, 0]), (*BATCH, 5))
        )
        np.testing.assert_array_equal(inputs[..., 0, 5:], small_obs["state"])
        np.testing.assert_array_equal(inputs[..., 1:, :5], small_obs["cones_set"])
        np.testing.assert_array_equal(present[0, 0], [True] + [True] * 4 + [False] * 3)
        assert bool(jnp.all(present[..., 0]))


def test_bad_inputs_raise_clear_errors(small_obs):
    with pytest.raises(ValueError, match="weight_depth"):
        N.MixtureCategoricalActor(width=4, depth=3, weight_depth=4).init(KEY, small_obs)
    with pytest.raises(ValueError, match="exactly the keys"):
        N.object_inputs({"state": small_obs["state"]})
    with pytest.raises(ValueError, match="batch axes"):
        N.object_inputs({"state": small_obs["state"][0], "cones_set": small_obs["cones_set"]})
    with pytest.raises(ValueError, match="feature batch axes"):
        N.broadcast_features(jnp.zeros((4, 8)), jnp.zeros((5, 3)))


# ---------------------------------------------------------------------------------------------
# Deep Set invariances
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def deep_set():
    extractor = N.DeepSetExtractor(width=16, state_width=16)
    obs = random_observation(3, (), 9, 5, 5)
    params = random_params(extractor.init, obs)
    return jax.jit(extractor.apply), params, obs


def test_deep_set_is_permutation_invariant(deep_set):
    apply, params, obs = deep_set
    reference = apply(params, obs)
    assert reference.shape == (32,)
    for seed in range(3):
        order = np.random.default_rng(seed).permutation(9)  # mixes present and absent slots
        permuted = {**obs, "cones_set": obs["cones_set"][order]}
        np.testing.assert_allclose(apply(params, permuted), reference, rtol=1e-5, atol=1e-5)


def test_deep_set_ignores_absent_rows_and_extra_padding(deep_set):
    apply, params, obs = deep_set
    reference = apply(params, obs)
    garbage = jnp.asarray(np.random.default_rng(4).uniform(-1, 1, (4, 5)), jnp.float32).at[:, 0].set(0.0)
    dirty = {**obs, "cones_set": obs["cones_set"].at[5:].set(garbage)}
    np.testing.assert_allclose(apply(params, dirty), reference, atol=1e-6)
    padded = {
        **obs,
        "cones_set": jnp.concatenate([obs["cones_set"], jnp.zeros((6, 5), obs["cones_set"].dtype)]),
    }
    np.testing.assert_allclose(apply(params, padded), reference, atol=1e-6)
    # a present row does matter
    moved = {**obs, "cones_set": obs["cones_set"].at[0, 1].add(0.3)}
    assert not np.allclose(apply(params, moved), reference, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# Mixture weights and the myopic actors
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mc_obs():
    """Two different observations (7 slots, 4 present), each repeated 2000 times on a second batch axis."""
    obs = random_observation(7, (2, 1), 7, 5, 4)
    return jax.tree_util.tree_map(lambda x: jnp.repeat(x, 2000, axis=1), obs)


@pytest.fixture(scope="module", params=[1, 3])
def gaussian_actor(request, small_obs):
    """φ_d = 1 (layers 2-3 run only for the sampled object) and φ_d = 3 (the configs' default, only the
    heads run for it). The parameter tree does not depend on φ_d, so both share one set."""
    actor = N.MixtureGaussianActor(
        action_dim=3, width=8, depth=3, weight_depth=request.param, components_per_object=2
    )
    params = random_params(N.MixtureGaussianActor(width=8, depth=3, components_per_object=2).init, small_obs)
    full = jax.jit(actor.apply)
    fast = jax.jit(lambda p, o, k: actor.apply(p, o, k, method="sample_fast"))
    return actor, params, full, fast


def test_gaussian_actor_policy_masks_absent_objects(gaussian_actor, small_obs):
    _, params, full, _ = gaussian_actor
    out = full(params, small_obs)
    assert out.means.shape == (*BATCH, 7, 2, 3)
    np.testing.assert_array_equal(out.present[..., :4], True)
    np.testing.assert_array_equal(out.present[..., 4:], False)
    # centred over the slots that carry weight (§3.1 step 2 over the present ones: softmax-neutral)
    np.testing.assert_allclose(out.mixture_logits[..., :4].mean(-1), 0.0, atol=1e-6)
    weights = object_weights(out)
    np.testing.assert_array_equal(weights[..., 4:], 0.0)
    assert bool(jnp.all(weights[..., :4] > 0))
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(component_weights(out).sum((-1, -2)), 1.0, rtol=1e-6)
    # the branch depth changes where φ reads from, so the weights differ between φ_d but stay valid
    garbage = small_obs["cones_set"].at[..., 4:, 1:].set(0.7)  # absent rows' contents are irrelevant
    dirty = full(params, {**small_obs, "cones_set": garbage})
    np.testing.assert_allclose(object_weights(dirty), weights, rtol=1e-6)
    np.testing.assert_allclose(dirty.means[..., :4, :, :], out.means[..., :4, :, :], rtol=1e-6)


def test_fast_path_matches_full_path_and_mixture_frequencies(gaussian_actor, mc_obs):
    _, params, full, fast = gaussian_actor
    out = full(params, mc_obs)
    sample = fast(params, mc_obs, rng_key(5))
    assert sample.action.shape == (2, 2000, 3) and sample.object_index.shape == (2, 2000)
    assert bool(jnp.all(jnp.abs(sample.action) <= 1))
    assert bool(jnp.all(sample.object_index < 4))  # only present objects are drawn
    np.testing.assert_allclose(
        sample.mixture_logits[..., :4], out.mixture_logits[..., :4], rtol=1e-6, atol=1e-6
    )
    assert bool(jnp.all(sample.mixture_logits[..., 4:] < -1e29))  # absent: the distributions' sentinel
    # the head run for the sampled object alone reproduces the full path's outputs for that object
    idx = sample.object_index[..., None, None, None]
    fast_means, fast_log_stds = sample.head
    np.testing.assert_allclose(fast_means, jnp.take_along_axis(out.means, idx, -3)[..., 0, :, :], atol=1e-6)
    chosen_log_stds = jnp.take_along_axis(out.log_stds, idx, -3)[..., 0, :, :]
    np.testing.assert_allclose(
        fast_log_stds, jnp.clip(chosen_log_stds, MIXTURE_LOG_STD_MIN, LOG_STD_MAX), atol=1e-6
    )
    # objects are drawn with frequencies w_o, components uniformly (C = 2), per batch row independently
    draws = mc_obs["state"].shape[1]
    tolerance = 4 * np.sqrt(0.25 / draws)
    for row in range(2):
        freq = np.bincount(np.asarray(sample.object_index[row]), minlength=7) / draws
        np.testing.assert_allclose(freq, object_weights(out)[row, 0], atol=tolerance)
        assert abs(float(jnp.mean(sample.component_index[row])) - 0.5) < tolerance
    # the action is tanh(μ + σ ε) of the chosen component: ε recovered from it is standard normal
    comp = sample.component_index[..., None, None]
    mean = jnp.take_along_axis(fast_means, comp, -2)[..., 0, :]
    std = jnp.exp(jnp.take_along_axis(fast_log_stds, comp, -2)[..., 0, :])
    noise = (jnp.arctanh(jnp.clip(sample.action, -1 + 1e-6, 1 - 1e-6)) - mean) / std
    assert abs(float(noise.mean())) < 0.05 and abs(float(noise.std()) - 1) < 0.05


def test_gaussian_actor_is_permutation_equivariant(gaussian_actor, small_obs):
    _, params, full, _ = gaussian_actor
    order = jnp.array([3, 6, 0, 2, 5, 1, 4])
    permuted = {**small_obs, "cones_set": small_obs["cones_set"][..., order, :]}
    out, out_p = full(params, small_obs), full(params, permuted)
    np.testing.assert_allclose(object_weights(out_p), object_weights(out)[..., order], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(out_p.means, out.means[..., order, :, :], rtol=1e-5, atol=1e-6)


def test_actors_return_raw_log_stds_and_the_fast_path_clips(small_obs):
    actor = N.MixtureGaussianActor(width=4, depth=1)
    params = random_params(actor.init, small_obs)
    apply = jax.jit(actor.apply)
    fast = jax.jit(lambda p, o, k: actor.apply(p, o, k, method="sample_fast"))
    for bias, clipped in ((100.0, LOG_STD_MAX), (-100.0, MIXTURE_LOG_STD_MIN)):
        params["params"]["log_std"]["bias"] = jnp.full((3,), bias)
        assert bool(jnp.all(jnp.abs(apply(params, small_obs).log_stds) > 50))  # not clipped
        np.testing.assert_array_equal(fast(params, small_obs, rng_key(1)).head[1], clipped)
    tracking_obs = {"state": jnp.zeros(6), "trajectory_set": trajectory_to_set(jnp.zeros(50))}
    actor = N.GaussianActor(N.FlatPEExtractor(), widths=(4,))
    params = random_params(actor.init, tracking_obs)
    params["params"]["log_std"]["bias"] = jnp.full((3,), -100.0)
    assert bool(jnp.all(jax.jit(actor.apply)(params, tracking_obs).log_std < SAC_LOG_STD_MIN))


def test_uniform_mixture_ablation_has_no_phi_and_uniform_weights(small_obs):
    actor = N.MixtureCategoricalActor(width=4, depth=2, uniform_mixture=True)
    params = random_params(actor.init, small_obs)
    assert set(params["params"]["trunk"]) == {"hidden_0", "hidden_1"}
    out = jax.jit(actor.apply)(params, small_obs)
    expected = jnp.broadcast_to(jnp.array([0.25] * 4 + [0.0] * 3), (*BATCH, 7))
    np.testing.assert_allclose(object_weights(out), expected)


@pytest.fixture(scope="module", params=[1])
def categorical_actor(request, small_obs):
    actor = N.MixtureCategoricalActor(num_actions=12, width=8, depth=3, weight_depth=request.param)
    params = random_params(N.MixtureCategoricalActor(width=8, depth=3).init, small_obs)
    fast = jax.jit(lambda p, o, k: actor.apply(p, o, k, method="sample_fast"))
    return actor, params, jax.jit(actor.apply), fast


def test_categorical_mixture_outputs(categorical_actor, small_obs):
    _, params, full, _ = categorical_actor
    out = full(params, small_obs)
    np.testing.assert_allclose(out.logits.mean(-1), 0.0, atol=1e-6)  # centred over actions
    policy = mixture_policy(out)
    np.testing.assert_allclose(policy.probs().sum(-1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(policy.weights[..., 4:], 0.0)
    object_probs = jax.nn.softmax(out.logits, axis=-1)
    np.testing.assert_allclose(
        policy.probs(), jnp.einsum("...o,...on->...n", policy.weights, object_probs), rtol=1e-6
    )
    # with one present object the mixture is that object's distribution (§8 item 7)
    one = full(params, random_observation(8, BATCH, 7, 5, 1))
    np.testing.assert_allclose(mixture_policy(one).probs(), jax.nn.softmax(one.logits[..., 0, :]), rtol=1e-6)


def test_categorical_fast_path(categorical_actor, mc_obs):
    _, params, full, fast = categorical_actor
    out = full(params, mc_obs)
    sample = fast(params, mc_obs, rng_key(9))
    assert sample.action.shape == (2, 2000) and sample.action.dtype == jnp.int32
    assert bool(jnp.all(sample.object_index < 4))
    chosen = jnp.take_along_axis(out.logits, sample.object_index[..., None, None], axis=-2)[..., 0, :]
    np.testing.assert_allclose(sample.head, chosen, atol=1e-6)
    # ancestral sampling reproduces the mixture probabilities π(a|s)
    draws = mc_obs["state"].shape[1]
    for row in range(2):
        freq = np.bincount(np.asarray(sample.action[row]), minlength=12) / draws
        np.testing.assert_allclose(freq, mixture_policy(out).probs()[row, 0], atol=4 * np.sqrt(0.25 / draws))


def test_categorical_mixture_is_permutation_invariant(categorical_actor, small_obs):
    _, params, full, _ = categorical_actor
    order = jnp.array([6, 3, 1, 0, 5, 2, 4])
    permuted = {**small_obs, "cones_set": small_obs["cones_set"][..., order, :]}
    probs = [mixture_policy(full(params, obs)).probs() for obs in (permuted, small_obs)]
    np.testing.assert_allclose(*probs, rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# Critics
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def continuous_critic(small_obs):
    critic = N.ContinuousCritic(N.DeepSetExtractor(width=8, state_width=8), widths=(8, 8), n_critics=2)
    params = random_params(critic.init, small_obs, jnp.zeros((*BATCH, 3)))
    return critic, params, jax.jit(critic.apply)


def test_critic_over_k_actions_equals_k_separate_calls(continuous_critic, small_obs):
    _, params, apply = continuous_critic
    actions = jnp.asarray(np.random.default_rng(11).uniform(-1, 1, (*BATCH, 7, 2, 3)), jnp.float32)
    q_all = apply(params, small_obs, actions)
    assert q_all.shape == (2, *BATCH, 7, 2)
    per_action = jax.jit(jax.vmap(jax.vmap(apply, (None, None, -2), -1), (None, None, -3), -2))
    np.testing.assert_allclose(per_action(params, small_obs, actions), q_all, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(q_all[..., 3, 1], apply(params, small_obs, actions[..., 3, 1, :]), rtol=1e-5)
    # same as tiling the observation explicitly (§8 item 9)
    tiled = jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x[:, :, None, None], (*BATCH, 7, 2, *x.shape[2:])), small_obs
    )
    np.testing.assert_allclose(apply(params, tiled, actions), q_all, rtol=1e-5, atol=1e-6)


def test_critic_split_first_layer_equals_concatenation(continuous_critic, small_obs):
    critic, params, apply = continuous_critic
    action = jnp.asarray(np.random.default_rng(12).uniform(-1, 1, (*BATCH, 3)), jnp.float32)
    features = jax.jit(lambda p, o: critic.apply(p, o, method="features"))(params, small_obs)
    heads = params["params"]["heads"]
    x = jnp.concatenate([features, action], axis=-1)
    expected = []
    for j in range(2):
        h = jax.nn.relu(x @ heads["dense_0"]["kernel"][j] + heads["dense_0"]["bias"][j])
        h = jax.nn.relu(h @ heads["dense_1"]["kernel"][j] + heads["dense_1"]["bias"][j])
        expected.append((h @ heads["q"]["kernel"][j] + heads["q"]["bias"][j])[..., 0])
    np.testing.assert_allclose(apply(params, small_obs, action), jnp.stack(expected), rtol=1e-5, atol=1e-5)
    from_features = jax.jit(lambda p, f, a: critic.apply(p, f, a, method="q_from_features"))
    np.testing.assert_allclose(
        from_features(params, features, action), jnp.stack(expected), rtol=1e-5, atol=1e-5
    )


def test_critic_ensemble_members_are_initialised_independently():
    critic = N.ContinuousCritic(N.FlatPEExtractor(), widths=(4,), n_critics=3)
    obs = {"state": jnp.zeros(6), "trajectory_set": trajectory_to_set(jnp.zeros(4))}
    kernel = jax.jit(critic.init)(KEY, obs, jnp.zeros(3))["params"]["heads"]["dense_0"]["kernel"]
    assert kernel.shape == (3, 9 * 6 + 9 * 4 + 3, 4)
    assert not np.allclose(kernel[0], kernel[1]) and not np.allclose(kernel[1], kernel[2])


def test_duelling_critic_mean_advantage_is_zero(small_obs):
    critic = N.DiscreteCritic(N.DeepSetExtractor(width=8, state_width=8), 12, widths=(8, 8), duelling=True)
    params = random_params(critic.init, small_obs)
    q = jax.jit(critic.apply)(params, small_obs)
    assert q.shape == (2, *BATCH, 12)
    features = jax.jit(lambda p, o: critic.apply(p, o, method="features"))(params, small_obs)
    heads = params["params"]["heads"]
    for j in range(2):
        h = features
        for i in range(2):
            layer = heads["mlp"][f"dense_{i}"]
            h = jax.nn.relu(h @ layer["kernel"][j] + layer["bias"][j])
        value = (h @ heads["value"]["kernel"][j] + heads["value"]["bias"][j])[..., 0]
        advantage = h @ heads["advantage"]["kernel"][j] + heads["advantage"]["bias"][j]
        np.testing.assert_allclose(q[j].mean(-1), value, rtol=1e-5, atol=1e-5)  # mean_a Q = V
        np.testing.assert_allclose(
            q[j] - value[..., None], advantage - advantage.mean(-1, keepdims=True), atol=1e-5
        )
    plain = N.DiscreteCritic(N.FlatPEExtractor(), 12, widths=(8,), duelling=False)
    tracking_obs = {"state": jnp.zeros(6), "trajectory_set": trajectory_to_set(jnp.zeros(4))}
    shapes = jax.eval_shape(plain.init, KEY, tracking_obs)
    assert set(shapes["params"]["heads"]) == {"mlp", "q"}
    assert jax.eval_shape(plain.apply, shapes, tracking_obs).shape == (2, 12)


# ---------------------------------------------------------------------------------------------
# Sizes: parameter counts (paper Table I) and FLOPs of the fast path
# ---------------------------------------------------------------------------------------------


def count(env, algo, which, **overrides):
    nets = make_test_networks(env, algo, **overrides)
    init = nets.init_actor if which == "actor" else nets.init_critic
    return count_params(jax.eval_shape(init, KEY))


def test_country_road_parameter_counts_match_paper_table_1():
    # XSAC actor: 11→256→256→256 trunk, μ and log σ (3 each) and φ (1); independent of φ_d.
    for weight_depth in (1, 2, 3):
        assert count("country_road", "xsac", "actor", weight_depth=weight_depth) == 136_455
    # SAC baseline: LFF Deep Set (128) + state Dense(128) → 256×2 → μ, log σ.
    assert count("country_road", "sac", "actor") == 200_710
    assert count("country_road", "sac", "critic") == count("country_road", "xsac", "critic") == 332_802


def test_fast_path_flops_against_paper_table_1():
    table = {1: 988_262, 2: 14_015_078, 3: 27_041_896}
    full = costs.mixture_actor_sample_flops(100, 11, 256, 3, 3, 6, fast=False)
    for weight_depth, paper in table.items():
        fast = costs.mixture_actor_sample_flops(100, 11, 256, 3, weight_depth, 6, fast=True)
        assert fast <= full
        assert abs(fast / paper - 1) < 0.10  # dense layers dominate; the paper also counts the sampler
    assert costs.mixture_actor_sample_flops(100, 11, 256, 3, 1, 6, fast=True) < full / 25


@pytest.mark.slow
@pytest.mark.optimised  # XLA counts what it built: unoptimised, it fuses less and counts ~6 % more
def test_fast_path_xla_flops_match_paper_table_1():
    """XLA's own FLOP count of the jitted fast sampler at full Country Road size (paper Table I), every
    slot computed as the paper counts (dense_sets: the paper preset's packing puts a packed and a dense
    branch in the program, and XLA counts both). The first layer computes the state's half (6 inputs
    -> 256) once per observation instead of once per slot (docs/benchmarks.md): 99 fewer of those
    products, 2 * 6 * 256 FLOPs each, than the paper counts."""
    table = {1: 988_262, 2: 14_015_078, 3: 27_041_896}
    shape = N.ENV_OBSERVATIONS["country_road"]
    state_half_once = (shape.num_objects - 1) * 2 * shape.state_dim * 256
    obs = N.dummy_observation(shape)
    obs["cones_set"] = obs["cones_set"].at[:, 0].set(1.0)
    for weight_depth, paper in table.items():
        nets = costs.country_road_networks("xsac", dense_sets=True, weight_depth=weight_depth)
        params = jax.eval_shape(nets.init_actor, KEY)
        sample = lambda p, o, k, nets=nets: nets.actor.apply(p, o, k, method="sample_fast")
        cost = jax.jit(sample).lower(params, obs, KEY).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, list) else cost
        if not cost or "flops" not in cost:
            pytest.skip("backend gives no cost analysis")
        assert abs((cost["flops"] + state_half_once) / paper - 1) < 0.01, (weight_depth, cost["flops"])


# ---------------------------------------------------------------------------------------------
# Multi-agent intersection (docs/algorithms.md Appendix A, docs/carenv-intersection.md §8.7)
# ---------------------------------------------------------------------------------------------


def test_intersection_observation_layout_and_defaults():
    shape = N.ENV_OBSERVATIONS["intersection"]
    assert shape == N.ObservationShape("vehicles_set", 8, 7, 66)
    obs = N.dummy_observation(shape, (2, 8))
    assert N.find_set_key(obs) == "vehicles_set"
    assert obs["vehicles_set"].shape == (2, 8, 8, 7) and obs["state"].shape == (2, 8, 66)
    for algo in ALGOS:
        nets = make_test_networks("intersection", algo)
        config = nets.config
        assert (config.feature_extractor, config.fe_width, config.fourier_scale) == ("deepset", 256, None)
        assert (config.fe_item_depth, config.fe_set_depth, config.critic_depth) == (3, 2, 2)
        assert config.actor_depth == (3 if config.is_mixture else 2)
        assert config.neutral_object == config.is_mixture
        assert nets.num_mixture_objects == (9 if config.is_mixture else 1)
    with pytest.raises(ValueError, match="neutral_object"):
        make_test_networks("intersection", "sac", neutral_object=True)


def test_intersection_critic_extractor_parameter_count():
    """Deep Set 256 without Fourier features: items (6 features, present dropped) → 3 × Dense(256), sum,
    set encoder 2 × Dense(256); state Dense(66 → 256); 512 features (vehicles_set then state)."""
    width = 256
    item = (6 * width + width) + 2 * (width * width + width)
    set_encoder = 2 * (width * width + width)
    state = 66 * width + width
    extractor = N.make_extractor(make_test_networks("intersection", "xsac").config)
    obs = N.dummy_observation(N.ENV_OBSERVATIONS["intersection"], (3,))
    params = jax.eval_shape(extractor.init, KEY, obs)
    assert count_params(params) == item + set_encoder + state
    assert "FourierFeatures_0" not in str(params) and "linear" not in params["params"]["deep_set"]["item_0"]
    assert jax.eval_shape(extractor.apply, params, obs).shape == (3, 2 * width)
    # critic: extractor + 2 heads of (512 + 3 → 256 → 256 → 1)
    heads = 2 * ((2 * width + 3) * width + width + width * width + width + width + 1)
    assert count("intersection", "sac", "critic") == item + set_encoder + state + heads


def test_deep_set_depths_are_configurable():
    extractor = N.DeepSetExtractor(width=4, item_depth=1, set_depth=0, fourier_scale=None, state_width=3)
    obs = random_observation(4, (), 5, 5, 2)
    params = jax.eval_shape(extractor.init, KEY, obs)
    assert count_params(params) == (4 * 4 + 4) + (6 * 3 + 3)
    nets = make_test_networks("country_road", "sac", fe_item_depth=2, fe_set_depth=1, **TINY)
    deep_set = jax.eval_shape(nets.init_critic, KEY)["params"]["extractor"]["deep_set"]
    assert sorted(deep_set) == ["item_0", "item_1", "set_encoder"]
    assert sorted(deep_set["set_encoder"]) == ["dense_0"]
    with pytest.raises(ValueError, match="fe_item_depth"):
        make_test_networks("country_road", "sac", fe_item_depth=0)


def test_neutral_object_is_a_state_only_component():
    """With no vehicle present the neutral object takes all the weight; it never depends on the set."""
    nets = make_test_networks("intersection", "xdsac", **TINY)
    params = random_params(nets.actor.init, nets.dummy_observation())
    apply = jax.jit(nets.actor.apply)
    rng = np.random.default_rng(5)
    state = jnp.asarray(rng.uniform(-1, 1, (4, 66)), jnp.float32)
    vehicles = np.zeros((4, 8, 7), np.float32)
    empty = apply(params, {"state": state, "vehicles_set": jnp.asarray(vehicles)})
    np.testing.assert_array_equal(object_weights(empty), np.eye(9)[[0] * 4])
    vehicles[:, :3] = rng.uniform(-1, 1, (4, 3, 7))
    vehicles[:, :3, 0] = 1.0
    full = apply(params, {"state": state, "vehicles_set": jnp.asarray(vehicles)})
    np.testing.assert_array_equal(full.present[:, :4], True)
    np.testing.assert_array_equal(full.present[:, 4:], False)
    weights = object_weights(full)
    np.testing.assert_allclose(jnp.sum(weights, -1), 1.0, rtol=1e-6)
    assert bool(jnp.all(weights[:, 0] > 0)) and bool(jnp.all(weights[:, 0] < 1))
    np.testing.assert_allclose(full.logits[:, 0], empty.logits[:, 0], rtol=1e-6)  # neutral head: state only
