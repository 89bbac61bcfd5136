"""Faithfulness measured: deleting objects from an observation, the total variation between policies,
the rankers, deletion curves, and an agent that acts on deleted observations inside the evaluation."""

import dataclasses
import functools
import math
from types import SimpleNamespace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from network_support import action_size
from scipy.stats import norm
from train_support import prepare_cache

from xrl_jax.actors import GaussianOutput
from xrl_jax.agents import PolicyActing, make_agent
from xrl_jax.config import preset
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture, squashed_gaussian
from xrl_jax.evaluation import make_evaluate
from xrl_jax.explain import explain, keep_components
from xrl_jax.explain.faithfulness import (
    RANKERS,
    DeletingAgent,
    action_distance,
    delete_objects,
    deletion_mask,
    policy_change_curve,
    rank_by_gradient_x_input,
    rank_by_occlusion,
    rank_by_weight,
    rank_random,
)
from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation
from xrl_jax.policies import CategoricalPolicy, SquashedGaussianPolicy
from xrl_jax.train import make_envs, resolve_config

SHAPE = ENV_OBSERVATIONS["country_road"]
SET_KEY = SHAPE.set_key
# Four states (batch axes (2, 2), as a multi-agent slot axis would add) with cones in scattered slots.
PRESENT_SLOTS = [[[0, 1, 2, 3, 4, 5], [3, 10, 11, 50, 99]], [[7, 8], [20, 21, 22, 23, 24, 25, 26]]]
DELETE_SLOTS = [[[1, 4], [99]], [[8], [20, 22, 26]]]
KS = (0, 1, 2, 3, 6)  # 6 exceeds every state's present − 1: the cap applies
CURVE_SAMPLES = 1024
F32_EPS = float(np.finfo(np.float32).eps)


@struct.dataclass
class ActorOnly:
    """The part of an agent state that policies and rankers read."""

    actor_params: Any


def slot_mask(slots) -> np.ndarray:
    mask = np.zeros((2, 2, SHAPE.num_objects), bool)
    for i, j in np.ndindex(2, 2):
        mask[i, j, slots[i][j]] = True
    return mask


def cone_observation(key) -> dict:
    key_state, key_set = jax.random.split(key)
    cones = np.array(jax.random.uniform(key_set, (2, 2, SHAPE.num_objects, SHAPE.object_features), minval=-1))
    present = slot_mask(PRESENT_SLOTS)
    cones[..., 0] = 1.0
    cones[~present] = 0.0
    return {
        "state": jax.random.uniform(key_state, (2, 2, SHAPE.state_dim), minval=-1),
        SET_KEY: jnp.asarray(cones),
    }


# ------------------------------------------------------------------------------------------------
# Hand cases
# ------------------------------------------------------------------------------------------------


def test_delete_objects_zeroes_exactly_the_chosen_rows():
    obs = cone_observation(jax.random.PRNGKey(0))
    delete = slot_mask(DELETE_SLOTS)
    deleted = delete_objects(obs, SET_KEY, jnp.asarray(delete))
    rows, before = np.asarray(deleted[SET_KEY]), np.asarray(obs[SET_KEY])
    assert np.all(rows[delete] == 0.0)
    np.testing.assert_array_equal(rows[~delete], before[~delete])
    assert deleted["state"] is obs["state"]
    np.testing.assert_array_equal(rows[..., 0] > 0, slot_mask(PRESENT_SLOTS) & ~delete)


def test_deletion_mask_hand_cases():
    scores = jnp.array([[3.0, 1.0, 3.0, 2.0, 5.0], [0.0, 9.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0, 5.0]])
    present = jnp.array([[1, 1, 1, 1, 0], [0, 1, 0, 0, 0], [0, 0, 0, 0, 0]], bool)
    as_lists = lambda mask: [list(np.flatnonzero(row)) for row in np.asarray(mask)]
    # The absent slot 4 (score 5) is never chosen; the tie at 3 goes to the lower index first.
    assert as_lists(deletion_mask(scores, present, 1)) == [[0], [], []]  # a lone object stays
    assert as_lists(deletion_mask(scores, present, 2)) == [[0, 2], [], []]
    assert as_lists(deletion_mask(scores, present, 10)) == [[0, 2, 3], [], []]  # capped at present − 1
    assert as_lists(deletion_mask(scores, present, 10, keep_one=False)) == [[0, 1, 2, 3], [1], []]
    assert as_lists(deletion_mask(scores, present, 0)) == [[], [], []]


def numpy_probs(component_logits, mixture_logits) -> np.ndarray:
    def softmax(x):
        e = np.exp(x - x.max(-1, keepdims=True))
        return e / e.sum(-1, keepdims=True)

    return np.einsum("...o,...on->...n", softmax(mixture_logits), softmax(component_logits))


def test_categorical_distance_is_half_the_l1_distance():
    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    logits_p, logits_q = (np.asarray(jax.random.normal(k, (5, 4, 6)) * 2, np.float64) for k in keys[:2])
    mix_p, mix_q = (np.asarray(jax.random.normal(k, (5, 4)), np.float64) for k in keys[2:])
    p = CategoricalMixture.create(jnp.asarray(logits_p, jnp.float32), jnp.asarray(mix_p, jnp.float32))
    q = CategoricalMixture.create(jnp.asarray(logits_q, jnp.float32), jnp.asarray(mix_q, jnp.float32))
    expected = 0.5 * np.abs(numpy_probs(logits_p, mix_p) - numpy_probs(logits_q, mix_q)).sum(-1)
    # float32 probabilities (≤ 1, each a sum of 4 rounded products: a few ε) summed over 6 actions.
    np.testing.assert_allclose(action_distance(p, q, jax.random.PRNGKey(0)), expected, atol=1e-6)
    np.testing.assert_allclose(action_distance(p, p, jax.random.PRNGKey(0)), 0.0, atol=0.0)


def test_continuous_distance_matches_the_closed_form_and_numerical_integration():
    samples = 4096
    four_standard_errors = 4 * 0.5 / math.sqrt(samples)  # each term lies in [0, 1]: variance ≤ 1/4
    # Two 1-D squashed Gaussians of equal σ: TV = 2Φ(|μ1 − μ2| / 2σ) − 1 (tanh does not change TV).
    mu1, mu2, sigma = (
        np.array([0.3, 0.0, -0.5, 1.0]),
        np.array([0.3, 0.5, 0.5, -2.0]),
        np.array([0.5, 0.5, 1.0, 0.7]),
    )
    p = squashed_gaussian(jnp.asarray(mu1[:, None]), jnp.log(jnp.asarray(sigma[:, None])))
    q = squashed_gaussian(jnp.asarray(mu2[:, None]), jnp.log(jnp.asarray(sigma[:, None])))
    estimate = np.asarray(jax.jit(action_distance, static_argnums=3)(p, q, jax.random.PRNGKey(2), samples))
    closed_form = 2 * norm.cdf(np.abs(mu1 - mu2) / (2 * sigma)) - 1
    np.testing.assert_allclose(estimate, closed_form, atol=four_standard_errors)
    assert estimate[0] == 0.0  # identical policies: q/p is exactly 1 at every draw
    # Mixtures (3 components, 1-D) against ½∫|p − q| du over the pre-squash u, in float64 NumPy on a
    # grid of step 1e-3 over ±15: its error (≲ 1e-4 at the kinks of |p − q|, tails < 1e-6) is far below
    # the standard error.
    keys = jax.random.split(jax.random.PRNGKey(3), 6)

    def mixture(k):
        loc, log_scale = (
            jax.random.normal(k[0], (3, 3, 1)) * 1.5,
            jax.random.uniform(k[1], (3, 3, 1), maxval=0.5),
        )
        return SquashedGaussianMixture.create(loc, log_scale - 1.0, jax.random.normal(k[2], (3, 3)))

    def density(pi, u):  # Σ_k w_k N(u; μ_k, σ_k), (U, 3)
        loc, scale = np.asarray(pi.loc, np.float64)[..., 0], np.asarray(pi.scale, np.float64)[..., 0]
        return np.sum(np.asarray(pi.weights, np.float64) * norm.pdf(u[:, None, None], loc, scale), axis=-1)

    p, q = mixture(keys[:3]), mixture(keys[3:])
    u = np.arange(-15.0, 15.0, 1e-3)
    integral = 0.5 * np.sum(np.abs(density(p, u) - density(q, u)), axis=0) * 1e-3
    estimate = np.asarray(jax.jit(action_distance, static_argnums=3)(p, q, jax.random.PRNGKey(4), samples))
    np.testing.assert_allclose(estimate, integral, atol=four_standard_errors)
    assert np.all((estimate >= 0) & (estimate <= 1))


# ------------------------------------------------------------------------------------------------
# Gradient × input on linear actors, where it is exact: Σ_f x_{o,f} ∂y/∂x_{o,f} is object o's term
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class LinearActorAgent(PolicyActing):
    """Just what the rankers read: an actor whose output is linear in the cone rows (params = W)."""

    config: Any
    networks: Any
    obs_shape: Any = SHAPE


def linear_actor(policy, discrete: bool) -> SimpleNamespace:
    def apply(weights, obs):
        out = jnp.einsum("...of,dof->...d", obs[SET_KEY], weights) + jnp.sum(obs["state"], -1, keepdims=True)
        return out if discrete else GaussianOutput(out, jnp.zeros_like(out))

    return SimpleNamespace(actor=SimpleNamespace(apply=apply), policy=policy)


@pytest.mark.parametrize("discrete", [False, True])
def test_gradient_x_input_of_a_linear_actor(discrete):
    outputs = 12 if discrete else 3
    config = SimpleNamespace(algo="dsac" if discrete else "sac", is_discrete=discrete, is_mixture=False)
    policy = CategoricalPolicy() if discrete else SquashedGaussianPolicy(-20.0, 2.0)
    agent = LinearActorAgent(config, linear_actor(policy, discrete))
    weights = jax.random.normal(jax.random.PRNGKey(5), (outputs, SHAPE.num_objects, SHAPE.object_features))
    obs = cone_observation(jax.random.PRNGKey(6))
    gradient_x_input = jax.jit(rank_by_gradient_x_input, static_argnums=0)
    scores = np.asarray(gradient_x_input(agent, ActorOnly(weights), obs, jax.random.PRNGKey(0)))
    rows, w = np.asarray(obs[SET_KEY], np.float64), np.asarray(weights, np.float64)
    per_output = np.einsum("...of,dof->...od", rows, w)  # object o's term of output d
    if discrete:  # y = log softmax(l)[a*]: ∂y/∂l_b = 1[b = a*] − p_b
        logits = per_output.sum(-2) + np.asarray(obs["state"], np.float64).sum(-1, keepdims=True)
        probs = np.exp(logits - logits.max(-1, keepdims=True))
        probs /= probs.sum(-1, keepdims=True)
        dy_dl = np.eye(outputs)[np.argmax(logits, -1)] - probs
        expected = np.abs(np.einsum("...od,...d->...o", per_output, dy_dl))
    else:  # y = μ, linear: each output's term is exact
        expected = np.abs(per_output).sum(-1)
    present = slot_mask(PRESENT_SLOTS)
    assert np.all(scores[~present] == -np.inf)
    # float32 sums of ≤ 5 products of magnitude ≲ 3 per output and ≤ 12 outputs: a few ε of ~50.
    np.testing.assert_allclose(scores[present], expected[present], rtol=1e-5, atol=50 * 8 * F32_EPS)


def test_rank_by_weight_refuses_an_agent_without_weights():
    agent = make_agent(preset("smoke", "country_road", "sac"), dummy_observation(SHAPE), action_size("sac"))
    with pytest.raises(ValueError, match="no mixture weights"):
        rank_by_weight(agent, None, cone_observation(jax.random.PRNGKey(0)), None)
    assert set(RANKERS) == {"weight", "random", "occlusion", "gradient_x_input"}


@pytest.mark.slow  # Deep Set agents compiled; default-tier sibling: test_gradient_x_input_of_a_linear_actor
@pytest.mark.parametrize("algo", ["sac", "dsac"])
def test_attributions_of_the_deep_set_baselines(algo):
    config = preset("smoke", "country_road", algo)
    agent = make_agent(config, dummy_observation(SHAPE), action_size(algo))
    actor_params = jax.jit(agent.networks.actor.init)(jax.random.PRNGKey(0), dummy_observation(SHAPE))
    obs = cone_observation(jax.random.PRNGKey(10))
    # Forward mode cannot pass the packed rows' custom VJP: the reference runs the same parameters on
    # every slot, which computes the same function.
    dense = make_agent(config.replace(packed_rows=None), dummy_observation(SHAPE), action_size(algo))

    def greedy_output(rows):  # written out again: DSAC log π(argmax), SAC the pre-squash mean μ
        out = dense.actor_output(actor_params, {**obs, SET_KEY: rows})
        if agent.is_discrete:
            log_probs = jax.nn.log_softmax(out, axis=-1)
            return jnp.take_along_axis(log_probs, jnp.argmax(out, -1)[..., None], axis=-1)
        return out.mean

    def attributions(key):
        state = ActorOnly(actor_params)

        def along(one_hot):  # forward mode: d/dt y(row o scaled by 1 + t) = Σ_f x_{o,f} ∂y/∂x_{o,f}
            rows = obs[SET_KEY]
            tangent = jnp.where(one_hot[:, None], rows, 0.0)
            return jnp.sum(jnp.abs(jax.jvp(greedy_output, (rows,), (tangent,))[1]), axis=-1)

        forward = jax.vmap(along)(jnp.eye(SHAPE.num_objects, dtype=bool))
        return (
            rank_by_gradient_x_input(agent, state, obs, key),
            jnp.moveaxis(forward, 0, -1),
            rank_by_occlusion(agent, state, obs, key),
        )

    backward, forward, occlusion = jax.device_get(jax.jit(attributions)(jax.random.PRNGKey(11)))
    present = slot_mask(PRESENT_SLOTS)
    assert np.all(backward[~present] == -np.inf) and np.all(occlusion[~present] == -np.inf)
    # Reverse and forward mode sum the same chain-rule products in other orders: float32 rounding of
    # ~10³ products of a network 16 wide, 1e-4 of the largest attribution.
    largest = float(np.max(np.abs(forward[present])))
    np.testing.assert_allclose(backward[present], forward[present], rtol=1e-4, atol=1e-4 * largest)
    assert np.all((occlusion[present] >= 0) & (occlusion[present] <= 1))
    assert np.all(occlusion[present] > 0)  # a Deep Set sees every cone: each deletion changes π


# ------------------------------------------------------------------------------------------------
# X agents: deletion is dropping components; the rankings and curves on real networks
# ------------------------------------------------------------------------------------------------

X_AGENTS = {
    "xdsac": dict(algo="xdsac"),
    "xdsac_neutral": dict(algo="xdsac", neutral_object=True),
    "xsac": dict(algo="xsac"),
    # Every slot computed, as the Intersection's quick preset (the others pack their rows: half the compile).
    "xsac_neutral_2_components": dict(
        algo="xsac", neutral_object=True, components_per_object=2, packed_rows=None
    ),
}
RANKED = ("xdsac", "xsac_neutral_2_components")  # the rankings and curves: one agent of each action kind


def component_keep_mask(agent, keep_objects: jax.Array) -> jax.Array:
    """Object keep flags (..., O) as the policy's component flags: the neutral first, C per object."""
    if agent.config.neutral_object:
        keep_objects = jnp.concatenate([jnp.ones((*keep_objects.shape[:-1], 1), bool), keep_objects], -1)
    return jnp.repeat(keep_objects, agent.config.components_per_object, axis=-1)


ACTIONS = jax.random.uniform(jax.random.PRNGKey(7), (16, 1, 1, 3), minval=-0.9, maxval=0.9)


def x_agent_facts(agent, rankings, actor_params, obs, delete, key):
    """Everything the X-agent tests read, in one program per agent (one compilation)."""
    state = ActorOnly(actor_params)
    full = agent.policy(actor_params, obs)
    facts = {
        "full": full,
        "deleted": agent.policy(actor_params, delete_objects(obs, SET_KEY, delete)),
        "kept": keep_components(full, component_keep_mask(agent, ~delete)),
    }
    if not agent.is_discrete:
        facts["deleted_log_prob"] = facts["deleted"].log_prob(ACTIONS)
        facts["kept_log_prob"] = facts["kept"].log_prob(ACTIONS)
    if not rankings:
        return facts
    facts |= {
        "explanation_weights": explain(agent, state, obs).weights,
        "weight_scores": rank_by_weight(agent, state, obs, key),
        "random_scores": rank_random(agent, state, obs, key),
        "occlusion": rank_by_occlusion(agent, state, obs, key),
        "curve": policy_change_curve(agent, state, obs, SET_KEY, rank_by_weight, KS, key, CURVE_SAMPLES),
    }
    top = deletion_mask(facts["occlusion"], obs[SET_KEY][..., 0] > 0, 1)
    deleted_top = agent.policy(actor_params, delete_objects(obs, SET_KEY, top))
    facts["top_occluded"] = action_distance(full, deleted_top, key)
    return facts


@functools.cache
def facts_of(name: str):
    settings = dict(X_AGENTS[name])
    algo = settings.pop("algo")
    config = preset("smoke", "country_road", algo).replace(**settings)
    agent = make_agent(config, dummy_observation(SHAPE), action_size(algo))
    actor_params = jax.jit(agent.networks.actor.init)(jax.random.PRNGKey(0), dummy_observation(SHAPE))
    obs, delete = cone_observation(jax.random.PRNGKey(8)), jnp.asarray(slot_mask(DELETE_SLOTS))
    facts = jax.jit(x_agent_facts, static_argnums=(0, 1))(
        agent, name in RANKED, actor_params, obs, delete, jax.random.PRNGKey(9)
    )
    return agent, jax.device_get(facts)


@pytest.fixture(params=list(X_AGENTS))
def x_agent(request):
    return facts_of(request.param)


@pytest.fixture(params=RANKED)
def ranked_x_agent(request):
    return facts_of(request.param)


# Tolerances: float32 (ε ≈ 1.2e-7). Weights and probabilities are ≤ 1, each a softmax or a sum of at
# most 2·100 rounded products, reached by two paths (the network on fewer rows against the full
# mixture renormalised): a few ε each, so 1e-6. Log densities of these untrained components (σ ≈ 1,
# |u − μ| ≲ 3, values ≲ 10) move by ≲ 10·|δμ| for a rounding δμ of the locations: 1e-5.
PROBABILITY_ATOL = 1e-6
LOG_DENSITY_TOL = 1e-5


def test_deleting_objects_equals_dropping_their_components(x_agent):
    agent, facts = x_agent
    deleted, kept = facts["deleted"], facts["kept"]
    np.testing.assert_array_equal(deleted.present, kept.present)
    np.testing.assert_allclose(deleted.weights, kept.weights, atol=PROBABILITY_ATOL)
    if agent.is_discrete:
        np.testing.assert_allclose(deleted.probs(), kept.probs(), atol=PROBABILITY_ATOL)
    else:
        np.testing.assert_allclose(
            facts["deleted_log_prob"], facts["kept_log_prob"], rtol=LOG_DENSITY_TOL, atol=LOG_DENSITY_TOL
        )


def object_weights(agent, facts) -> np.ndarray:
    weights = np.asarray(facts["explanation_weights"], np.float64)
    return weights[..., 1:] if agent.config.neutral_object else weights


def test_weight_ranking_is_the_explanation(ranked_x_agent):
    agent, facts = ranked_x_agent
    present = slot_mask(PRESENT_SLOTS)
    scores, weights = np.asarray(facts["weight_scores"]), object_weights(agent, facts)
    assert np.all(scores[~present] == -np.inf)
    np.testing.assert_allclose(scores[present], weights[present], rtol=1e-6)
    top_two = np.argsort(-np.where(present, weights, -np.inf), axis=-1, kind="stable")[..., :2]
    chosen = np.asarray(deletion_mask(jnp.asarray(scores), jnp.asarray(present), 2))
    for i, j in np.ndindex(2, 2):
        assert set(np.flatnonzero(chosen[i, j])) == set(top_two[i, j][: len(PRESENT_SLOTS[i][j]) - 1])
    random = np.asarray(facts["random_scores"])
    assert np.all(random[~present] == -np.inf) and np.all((random[present] >= 0) & (random[present] < 1))


def test_occlusion_score_is_the_change_of_deleting_that_object(ranked_x_agent):
    agent, facts = ranked_x_agent
    present = slot_mask(PRESENT_SLOTS)
    occlusion = np.asarray(facts["occlusion"])
    assert np.all(occlusion[~present] == -np.inf) and np.all(occlusion[present] >= 0)
    top = np.max(occlusion, axis=-1)
    # The same draws in both (the key is shared); only the rounding of a vmapped pass differs.
    np.testing.assert_allclose(
        facts["top_occluded"], top, atol=PROBABILITY_ATOL if agent.is_discrete else 1e-5
    )
    if agent.is_discrete:  # exact TV: deleting o changes π by w_o·TV(q_o, π without o) ≤ w_o
        assert np.all(occlusion[present] <= object_weights(agent, facts)[present] + PROBABILITY_ATOL)


def deleted_by_weight(weights: np.ndarray, k: int) -> np.ndarray:
    """(2, 2, O) the top-k present objects by weight per state, at most present − 1 of them."""
    present, deleted = slot_mask(PRESENT_SLOTS), np.zeros(weights.shape, bool)
    for i, j in np.ndindex(2, 2):
        order = np.argsort(-np.where(present[i, j], weights[i, j], -np.inf), kind="stable")
        deleted[i, j, order[: min(k, len(PRESENT_SLOTS[i][j]) - 1)]] = True
    return deleted


def test_deleting_by_weight_changes_the_policy_by_at_most_the_removed_weight(ranked_x_agent):
    agent, facts = ranked_x_agent
    curve, weights = np.asarray(facts["curve"], np.float64), object_weights(agent, facts)
    assert curve.shape == (len(KS), 2, 2)
    # k = 0 deletes nothing: the same policy twice, up to the rounding of two compiled passes.
    np.testing.assert_allclose(curve[0], 0.0, atol=PROBABILITY_ATOL if agent.is_discrete else 1e-5)
    # π = (1 − r)·π' + r·ρ, so TV(π, π') = r·TV(ρ, π') ≤ r; the Monte Carlo estimate within 4 SE.
    slack = PROBABILITY_ATOL if agent.is_discrete else 4 * 0.5 / math.sqrt(CURVE_SAMPLES)
    removed = np.stack([np.sum(weights * deleted_by_weight(weights, k), axis=-1) for k in KS])
    assert np.all(curve <= removed + slack)
    assert np.all((curve >= 0) & (curve <= 1))
    if agent.is_discrete:  # the equality case: the exact TV of the full mixture against its kept part
        w = np.asarray(facts["full"].weights, np.float64)
        q = np.asarray(facts["full"].component_probs(), np.float64)
        neutral = np.zeros((2, 2, 1 if agent.config.neutral_object else 0), bool)
        full = np.einsum("...k,...kn->...n", w, q)
        for index, k in enumerate(KS):
            kept_w = w * ~np.concatenate([neutral, deleted_by_weight(weights, k)], -1)
            kept = np.einsum("...k,...kn->...n", kept_w / kept_w.sum(-1, keepdims=True), q)
            np.testing.assert_allclose(curve[index], 0.5 * np.abs(full - kept).sum(-1), atol=PROBABILITY_ATOL)


# ------------------------------------------------------------------------------------------------
# The deleted policy's return, scored by the project's own evaluation
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tracking_xsac(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    cfg = resolve_config("tracking", "xsac", "smoke")
    env, _, eval_params = make_envs(cfg)
    obs_example = dummy_observation(ENV_OBSERVATIONS["tracking"])
    agent = make_agent(cfg.agent, obs_example, action_size("xsac"))
    return (
        env,
        eval_params,
        agent,
        ActorOnly(jax.jit(agent.networks.actor.init)(jax.random.PRNGKey(0), obs_example)),
    )


def test_deleting_agent_is_scored_by_the_evaluation(tracking_xsac):
    env, eval_params, agent, state = tracking_xsac

    def evaluate(acting):  # XSAC is evaluated on samples: the key stream matters
        return jax.device_get(
            jax.jit(make_evaluate(env, eval_params, acting, 2))(jax.random.PRNGKey(1), state)
        )

    wrapped = DeletingAgent(agent, rank_by_weight, 0)
    assert wrapped.is_discrete == agent.is_discrete and wrapped.config is agent.config  # delegated
    assert wrapped != DeletingAgent(agent, rank_by_weight, 0) and hash(wrapped) == object.__hash__(wrapped)
    own, same = evaluate(agent), evaluate(wrapped)
    for field in own:  # k = 0 is the agent itself, bit for bit
        np.testing.assert_array_equal(same[field], own[field])
    deleted = evaluate(DeletingAgent(agent, rank_random, 5))
    with pytest.raises(ValueError, match="int >= 0"):
        DeletingAgent(agent, rank_random, -1)
    assert np.all(np.isfinite(deleted["return"])) and np.all(deleted["length"] > 0)
    # The count as part of the state (one program for every k) deletes the same objects: the mask
    # compares integer ranks with k, the rest is the same computation, op by op when run eagerly.
    # (Two compiled evaluations need not agree: their fusions may round a last bit differently, and
    # hundreds of steps of car dynamics make that a different episode.)
    obs, _ = jax.vmap(env.reset_env, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(3), 2), eval_params
    )
    key = jax.random.PRNGKey(5)
    static = DeletingAgent(agent, rank_random, 5).act(key, state, obs, "eval")
    traced = DeletingAgent(agent, rank_random, None).act(key, (state, jnp.asarray(5, jnp.int32)), obs, "eval")
    np.testing.assert_array_equal(traced, static)
    assert not np.array_equal(static, agent.act(key, state, obs, "eval"))  # five of the points deleted


def test_a_seed_whose_evaluation_left_no_observation_has_a_nan_policy_change_not_a_crash():
    """A seed with nothing to delete from (no evaluation step kept) is NaN, which the IQM over seeds
    skips, where it divided by zero before."""
    from xrl_jax.explain.run_deletion import _policy_change

    def never_called(*args):
        raise AssertionError("no observation: the policy must not be evaluated")

    empty = {"cones": np.zeros((0, 4, 3), np.float32)}
    change = _policy_change(never_called, None, empty, jax.random.key(0), num_ks=3)
    assert change.shape == (3,) and np.isnan(change).all()
