"""The scenarios as gymnax 1.0 environments (envs.gymnax): gymnax's own spaces and auto-reset, the
Intersection's episode-level flags, and a third-party trainer (rejax's PPO) learning on Tracking."""

import chex
import numpy as np
import pytest

gymnax = pytest.importorskip(
    "gymnax", reason="the gymnax extra is not installed (pip install -e '.[gymnax]')"
)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from gymnax.environments import spaces  # noqa: E402

from envs import gymnax as carenv_gymnax  # noqa: E402
from envs.intersection import MAX_AGENTS  # noqa: E402

SMALL_BANK = dict(track_bank_size=4)  # reset draws from the bank; four tracks keep the build short


def random_action(env, params, key):
    space = env.action_space(params)
    if env.multi_agent:
        return jax.vmap(space.sample)(jax.random.split(key, MAX_AGENTS))
    return space.sample(key)


@pytest.mark.parametrize(
    "name, overrides",
    [  # one env per family in the default tier
        ("tracking", SMALL_BANK),
        pytest.param("country_road_discrete", SMALL_BANK, marks=pytest.mark.slow),
        ("intersection", {}),
    ],
)
def test_observations_and_actions_lie_in_gymnax_spaces(name, overrides):
    env, params = carenv_gymnax.make(name, **overrides)
    flat_env, _ = carenv_gymnax.make(name, flat_obs=True, **overrides)
    assert isinstance(env, gymnax.environments.environment.Environment)
    obs, state = env.reset(jax.random.PRNGKey(3), params)
    action = random_action(env, params, jax.random.PRNGKey(4))
    stepped = env.step(jax.random.PRNGKey(5), state, action, params)

    def rows(tree):  # per vehicle on the Intersection, whose spaces are per vehicle
        if not env.multi_agent:
            return [tree]
        return [jax.tree.map(lambda x, i=i: x[i], tree) for i in range(MAX_AGENTS)]

    as_gym = spaces.gymnax_space_to_gym_space(env.observation_space(params))
    flat_space = flat_env.observation_space(params)
    for observation in (obs, stepped[0]):
        for row in rows(observation):
            assert as_gym.contains({k: np.asarray(v) for k, v in row.items()})
            flat = carenv_gymnax.flatten_observation(row)
            assert flat.shape == flat_space.shape and bool(flat_space.contains(flat))
    for row in rows(action):
        assert bool(env.action_space(params).contains(row))
    # The episode-level flags are scalars everywhere (gymnax's auto-reset selects on them).
    assert stepped[3].shape == () and stepped[4].shape == ()
    assert stepped[2].shape == ((MAX_AGENTS,) if env.multi_agent else ())
    # The flat env observes the flattened dict. Both run op by op (not jitted), so the same operations
    # on the same inputs give the same bits.
    with jax.disable_jit():
        dict_step = env.step_env(jax.random.PRNGKey(5), state, action, params)
        flat_step = flat_env.step_env(jax.random.PRNGKey(5), state, action, params)
    np.testing.assert_array_equal(flat_step[0], carenv_gymnax.flatten_observation(dict_step[0]))


def test_auto_reset_follows_gymnax_and_keeps_the_ending_observation():
    """The racing time limit, shortened to three steps, ends the episode as a truncation: gymnax's step
    returns the reset of the step key's second half and keeps the ending observation in info."""
    env, params = carenv_gymnax.make("tracking", max_steps=3, **SMALL_BANK)
    assert params.max_steps_in_episode == 3
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    throttle = jnp.array([0.0, 1.0, 0.0])
    with jax.disable_jit():  # op by op, so that the scenario's own step gives the same bits
        for step in range(1, 4):
            key = jax.random.PRNGKey(10 + step)
            inner_obs, inner_state, *_ = env.scenario.step_env(key, state.inner, throttle, params.inner)
            obs, state, _, terminated, truncated, info = env.step(key, state, throttle, params)
            assert not bool(terminated) and bool(truncated) == (step == 3)
        reset_obs, _ = env.reset_env(jax.random.split(key)[1], params)
    for name in obs:
        np.testing.assert_array_equal(obs[name], reset_obs[name])
        np.testing.assert_array_equal(info["final_observation"][name], inner_obs[name])
    assert int(state.time) == 0 and int(state.inner.step_count) == 0
    assert int(inner_state.step_count) == 3


def test_intersection_episode_ends_at_its_time_limit_with_per_vehicle_flags():
    env, params = carenv_gymnax.make("intersection", episode_steps=2)
    _, state = env.reset(jax.random.PRNGKey(0), params)
    standing = jnp.zeros((MAX_AGENTS, 3))
    with jax.disable_jit():  # op by op, so that the scenario's own step gives the same bits
        for step in (1, 2):
            key = jax.random.PRNGKey(step)
            inner = env.scenario.step_env(key, state.inner, standing, params.inner)
            _, state, reward, terminated, truncated, info = env.step(key, state, standing, params)
            assert not bool(terminated) and bool(truncated) == (step == 2)
            np.testing.assert_array_equal(reward, inner[2])
            np.testing.assert_array_equal(info["agent_terminated"], inner[3])
            np.testing.assert_array_equal(info["agent_truncated"], inner[4])
    # The cars that acted in the last step are cut off by the limit; the ending observation is theirs.
    assert bool(jnp.all(info["agent_truncated"] == info["acted"]))
    np.testing.assert_array_equal(info["final_observation"]["state"], inner[5]["final_obs"]["state"])
    assert int(state.time) == 0 and int(state.inner.step) == 0


def test_the_adaptors_ask_the_env_how_many_agents_act_and_its_time_limit():
    """One way to know "multi-agent" and one name for the time limit: the env answers both."""
    cases = (("tracking", dict(max_steps=7, **SMALL_BANK)), ("intersection", dict(episode_steps=9)))
    for name, overrides in cases:
        env, params = carenv_gymnax.make(name, **overrides)
        assert env.multi_agent == env.scenario.multi_agent == (env.scenario.num_agents > 1)
        assert params.max_steps_in_episode == env.scenario.max_episode_steps(params.inner)
    assert carenv_gymnax.make("intersection")[0].multi_agent and env.scenario.num_agents == MAX_AGENTS


def bad_input_cases():
    """(what is wrong, a call that must fail in one line, the line's type and fragment)."""
    from gymnax.environments.environment import EnvParams

    env, params = carenv_gymnax.make("tracking", **SMALL_BANK)
    discrete, discrete_params = carenv_gymnax.make("tracking_discrete", **SMALL_BANK)
    multi, multi_params = carenv_gymnax.make("intersection")
    road_params = carenv_gymnax.make("country_road", **SMALL_BANK)[1]
    _, state = env.reset(jax.random.PRNGKey(0), params)
    _, discrete_state = discrete.reset(jax.random.PRNGKey(0), discrete_params)
    _, multi_state = multi.reset(jax.random.PRNGKey(0), multi_params)
    key = jax.random.PRNGKey(1)
    return [
        ("a batch of one action", lambda: env.step(key, state, jnp.zeros((1, 3)), params), ValueError,
         "an action has shape (3,), got (1, 3)"),
        ("two discrete actions", lambda: discrete.step(key, discrete_state, jnp.zeros(2, jnp.int32),
         discrete_params), ValueError, "an action has shape (), got (2,)"),
        ("one vehicle's action", lambda: multi.step(key, multi_state, jnp.zeros(3), multi_params), ValueError,
         "an action has shape (8, 3) (8 agent slots), got (3,)"),
        ("gymnax's own EnvParams", lambda: env.reset(key, EnvParams()), TypeError, "got EnvParams"),
        ("the Intersection's params", lambda: env.reset(key, multi_params), ValueError,
         "made for 'Intersection'"),
        ("Country Road's params", lambda: env.step(key, state, jnp.zeros(3), road_params), ValueError,
         "made for 'CountryRoad'"),
        ("the scenario's own params", lambda: env.reset(key, params.inner), TypeError, "got RacingParams"),
        ("a time limit of 0", lambda: carenv_gymnax.make("tracking", max_steps=0, **SMALL_BANK), ValueError,
         "max_steps (the time limit) must be a positive integer, got 0"),
        ("a negative time limit", lambda: carenv_gymnax.make("intersection", episode_steps=-1), ValueError,
         "episode_steps must be a positive int"),
        ("flat_obs as a word", lambda: carenv_gymnax.make("tracking", flat_obs="no"), ValueError,
         "flat_obs must be True or False, got 'no'"),
        ("not an envs Environment", lambda: carenv_gymnax.GymnaxEnv(object(), None), TypeError,
         "adapts an envs.core.Environment, got object"),
    ]  # fmt: skip


def test_bad_input_fails_in_one_line_saying_what_is_wrong():
    for what, call, error, fragment in bad_input_cases():
        with pytest.raises(error) as raised:
            call()
        message = str(raised.value)
        assert fragment in message and "\n" not in message, (what, message)


@pytest.mark.slow  # learns: 65,536 steps of rejax's PPO
@pytest.mark.optimised
def test_a_third_party_trainer_learns_on_tracking():
    """rejax's PPO (written for gymnax's five-value step, hence legacy_step_api) trains on Tracking
    through envs.gymnax. rejax evaluates 128 episodes before training and at every eval_freq; the
    margin is four standard errors of the difference of the two means, from those episodes' spread, so
    an untrained policy passes with probability ~3e-5."""
    rejax = pytest.importorskip("rejax", reason="rejax is not installed (pip install -e '.[gymnax]')")
    env, params = carenv_gymnax.make("tracking", flat_obs=True, track_bank_size=64)
    algo = rejax.PPO.create(
        env=carenv_gymnax.legacy_step_api(env), env_params=params, total_timesteps=65_536, num_envs=16,
        num_steps=128, eval_freq=16_384, num_epochs=4, num_minibatches=4, learning_rate=3e-4, gamma=0.98,
    )  # fmt: skip
    _, (_, returns) = jax.jit(algo.train)(jax.random.PRNGKey(0))
    untrained, trained = np.asarray(returns[0]), np.asarray(returns[-1])
    margin = 4.0 * np.sqrt(untrained.var(ddof=1) / untrained.size + trained.var(ddof=1) / trained.size)
    assert trained.mean() > untrained.mean() + margin, (untrained.mean(), trained.mean(), margin)


def test_the_rejax_comparison_gives_both_ppos_the_same_settings():
    """bench.py rejax compares two PPOs at an equal budget: every setting both have is the same."""
    pytest.importorskip("rejax", reason="rejax is not installed (pip install -e '.[gymnax-tests]')")
    from xrl_jax.benchmarks.third_party import comparison_config, make_rejax_ppo

    cfg = comparison_config(seeds=2, total_steps=8192, num_envs=16, rollout_steps=128, epochs=3,
                            minibatches=4, width=32, depth=2)  # fmt: skip
    algo, a = make_rejax_ppo(cfg), cfg.agent
    assert (algo.total_timesteps, algo.num_envs, algo.num_steps) == (8192, 16, 128)
    assert (algo.num_epochs, algo.num_minibatches) == (a.ppo_epochs, a.ppo_minibatches) == (3, 4)
    shared = {"learning_rate": a.actor_lr, "gamma": a.gamma, "gae_lambda": a.gae_lambda,
              "clip_eps": a.clip_eps, "ent_coef": a.ent_coef, "max_grad_norm": a.clip_norm}  # fmt: skip
    assert {name: float(getattr(algo, name)) for name in shared} == pytest.approx(shared)
    assert a.actor_lr == a.critic_lr and a.lr_decay_updates == 0  # rejax: one constant rate
    assert algo.actor.hidden_layer_sizes == (32, 32) == (a.actor_width,) * a.actor_depth
    assert (a.critic_width, a.critic_depth, a.feature_extractor, a.pe_freqs) == (32, 2, "flat_pe", 0)
    assert a.truncation == "bootstrap"  # ours by default; the ablation takes rejax's reading
    ablation = comparison_config(seeds=2, total_steps=8192, num_envs=16, rollout_steps=128, epochs=3,
                                 minibatches=4, width=32, depth=2,
                                 changes={"truncation": "terminal", "ent_coef": 0.0})  # fmt: skip
    assert ablation.agent.truncation == "terminal" and ablation.agent.ent_coef == 0.0 != a.ent_coef
    assert float(make_rejax_ppo(ablation).ent_coef) == 0.0


def test_the_rejax_ablation_gives_rejax_pieces_of_ours():
    """squash: the env takes unbounded actions and applies tanh (rejax's clip never acts); state_std:
    log σ a head of the features, so σ varies with the observation; observation: our flat encoding,
    the points without their constant present and index columns; global_clip: the gradient's global
    norm clipped at clip_norm, where rejax clips each element. Any of them together."""
    pytest.importorskip("rejax", reason="rejax is not installed (pip install -e '.[gymnax-tests]')")
    from xrl_jax.benchmarks.third_party import comparison_config, make_rejax_ppo

    cfg = comparison_config(seeds=1, total_steps=8192, num_envs=16, rollout_steps=128, epochs=2,
                            minibatches=4, width=32, depth=2)  # fmt: skip
    for wrong in (["tanh"], "squash"):  # an unknown piece; a string, whose letters are no pieces
        with pytest.raises(ValueError, match="rejax_with takes pieces of"):
            make_rejax_ppo(cfg, wrong)
    own, squash = make_rejax_ppo(cfg), make_rejax_ppo(cfg, ["squash"])
    assert type(own.actor).__name__ == type(squash.actor).__name__ == "GaussianPolicy"
    assert np.all(np.asarray(own.env.action_space(own.env_params).high) == 1.0)
    assert np.all(np.isinf(np.asarray(squash.env.action_space(squash.env_params).high)))
    key = jax.random.PRNGKey(0)
    obs, state = squash.env.reset(key, squash.env_params)
    wide = jnp.array([3.0, -0.5, 0.2])  # beyond the box where tanh saturates, and inside it
    stepped = squash.env.step(key, state, wide, squash.env_params)[1]
    expected = own.env.step(key, state, jnp.tanh(wide), own.env_params)[1]
    chex.assert_trees_all_equal(stepped, expected)  # tanh taken eagerly in both: the same input bits

    state_std = make_rejax_ppo(cfg, ["state_std"])
    assert np.all(np.asarray(state_std.env.action_space(state_std.env_params).high) == 1.0)  # no squash
    params = state_std.actor.init(key, obs[None], key)
    other = jax.random.normal(key, obs[None].shape)
    std = [state_std.actor.apply(params, o, method="_action_dist").stddev() for o in (obs[None], other)]
    assert not np.allclose(std[0], std[1])  # rejax's own σ is one parameter vector for every state

    ours = make_rejax_ppo(cfg, ["squash", "state_std", "observation"])
    assert type(ours.actor).__name__ == "StateStdGaussian" and np.isinf(ours.actor.action_range[1])
    flat, _ = ours.env.reset(key, ours.env_params)
    rows = np.asarray(obs[6:]).reshape(25, 4)  # gymnax's flat observation: state, then 25 rows
    expected_flat = np.concatenate([np.asarray(obs[:6]), rows[:, 2:].ravel()])
    np.testing.assert_array_equal(np.asarray(flat), expected_flat)
    assert ours.env.observation_space(ours.env_params).shape == flat.shape == (6 + 25 * 2,)

    for piece in ("squash", "state_std", "observation"):  # each alone builds rejax's networks and optimisers
        observed = make_rejax_ppo(cfg, [piece])
        shape = observed.env.observation_space(observed.env_params).shape
        assert shape == observed.env.reset(key, observed.env_params)[0].shape
        first_layer = observed.init_state(key).actor_ts.params["params"]["features"]["Dense_0"]["kernel"]
        assert first_layer.shape[0] == shape[-1]  # the actor built for the observation the env gives

    # global_clip: a gradient of ones is clipped to norm clip_norm as a whole (each element
    # clip_norm/sqrt(n)), not element by element (each clip_norm); Adam's first moment after one
    # step is (1 - b1) times what the clip let through, in both.
    for pieces, each in (((), lambda n: 0.5), (["global_clip"], lambda n: 0.5 / np.sqrt(n))):
        algo = make_rejax_ppo(cfg, pieces)
        assert float(algo.max_grad_norm) == cfg.agent.clip_norm == 0.5
        assert type(algo.actor).__name__ == "GaussianPolicy"  # nothing else of ours
        for ts in (algo.init_state(key).actor_ts, algo.init_state(key).critic_ts):
            ones = jax.tree_util.tree_map(jnp.ones_like, ts.params)
            n = sum(x.size for x in jax.tree_util.tree_leaves(ones))
            first_moment = ts.apply_gradients(grads=ones).opt_state[1][0].mu
            for leaf in jax.tree_util.tree_leaves(first_moment):  # float32 rounding of 0.1 * 0.5 / sqrt(n)
                np.testing.assert_allclose(leaf, 0.1 * each(n), rtol=1e-5)


@pytest.mark.slow  # two PPOs trained (8,192 steps each) and evaluated on 5 held-out tracks
def test_the_rejax_comparison_reports_both_sides():
    pytest.importorskip("rejax", reason="rejax is not installed (pip install -e '.[gymnax-tests]')")
    from xrl_jax.benchmarks.third_party import ppo_against_rejax

    report = ppo_against_rejax(seeds=2, total_steps=8192, num_envs=16, rollout_steps=128, epochs=2,
                               minibatches=4, width=32, depth=2, eval_episodes=5)  # fmt: skip
    assert report["settings"]["eval_episodes"] == 5
    assert report["settings"]["xrl_jax_truncation"] == "bootstrap"
    for side in ("xrl_jax", "rejax"):
        assert len(report[side]["returns"]) == 2 and np.all(np.isfinite(report[side]["returns"]))
        assert report[side]["env_steps_per_s"] > 0
        low, high = report[side]["ci95"]
        assert low <= report[side]["iqm"] <= high
    assert 0.0 <= report["p_xrl_jax_above_rejax"]["estimate"] <= 1.0 and 0 < report["mann_whitney_p"] <= 1
