"""Our PPO beside a third-party one: rejax's PPO (``pip install -e '.[gymnax-tests]'``) trained on
Tracking through :mod:`envs.gymnax` at an equal budget (``bench.py rejax``).

Both sides get the same env steps, vector envs, rollout length, epochs, minibatches, learning rate
(constant), discount, GAE λ, clip range, entropy bonus, gradient-norm clip and ReLU MLPs of the same
widths on the same flat observation (the state, then the 25 centre-line points; ours through the
parameter-free flat encoding with no frequencies). Both run on one XLA device, members vmapped, and
both are evaluated greedily on the same held-out tracks (the trainer's evaluation protocol: rejax's
actor through :func:`xrl_jax.evaluation.make_evaluate_policy`).

What differs is each library's own PPO, which is what the comparison is for: rejax's Gaussian has a
state-independent standard deviation and clips its samples to the action box, ours is SAC's squashed
Gaussian with a state-dependent one; rejax treats a truncated step as terminal, ours bootstraps it
from its ending observation; rejax clips its value loss (the value moves at most ε per rollout), ours
does not. Both train on a fixed bank of 128 tracks (rejax on envs.make's default, ours on its
trainer's bank of that size). ``bench.py rejax --truncation terminal`` and ``--value-clip`` give ours
rejax's readings.

``rejax_with`` gives rejax's side pieces of ours, any of :data:`REJAX_PIECES` (the ablation of
``bench.py rejax --rejax-with``): ``squash`` samples rejax's Gaussian
in the unbounded space and the env applies tanh (the ratio taken there, as ours takes it);
``state_std`` makes log σ a Dense head of the features, clipped to SAC's bounds, as our squashed
Gaussian has it; ``observation`` feeds it our flat encoding (:class:`~xrl_jax.extractors.FlatPEExtractor`
with no frequencies: the points without their constant present and index columns) instead of
gymnax's flat observation; ``global_clip`` clips each gradient's global norm at ``clip_norm``, as
ours does, where rejax clips every element at it (``optax.clip``). The entropy bonus stays rejax's:
the Gaussian's closed form before the squash (``ent_coef=0`` takes it out of both sides).
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax import stats
from xrl_jax.benchmarks import REJAX_PIECES  # any of them together (module docstring); none: its own
from xrl_jax.config import LOG_STD_MAX, SAC_LOG_STD_MIN, TrainConfig, resolve_config


def _our_flat_observation(obs):
    """Our side's input on Tracking: the state, then the points without their meta columns."""
    from xrl_jax.extractors import FlatPEExtractor

    return FlatPEExtractor(num_freqs=0).apply({}, obs)


def comparison_config(seeds: int, total_steps: int, num_envs: int, rollout_steps: int, epochs: int,
                      minibatches: int, width: int, depth: int, eval_episodes: int = 100,
                      changes: Mapping[str, Any] | None = None) -> TrainConfig:  # fmt: skip
    """Our side: plain PPO on continuous Tracking with the shared settings, trained on a fixed bank of
    as many tracks as rejax's env holds (fresh tracks would cost ours the generator), in chunks of up
    to 16 rollouts (at least two chunks), one evaluation at the end."""
    from envs.racing_params import DEFAULT_BANK_SIZE

    rollout = num_envs * rollout_steps
    rollouts = total_steps // rollout
    # At least two chunks: the first, which compiles, is not timed.
    chunk = max(n for n in range(1, min(16, max(rollouts // 2, 1)) + 1) if rollouts % n == 0) * rollout
    overrides = {
        "num_envs": num_envs, "rollout_steps": rollout_steps, "ppo_epochs": epochs,
        "ppo_minibatches": minibatches, "actor_width": width, "critic_width": width, "actor_depth": depth,
        "critic_depth": depth, "feature_extractor": "flat_pe", "pe_freqs": 0, "lr_decay_updates": 0,
        "train_tracks": DEFAULT_BANK_SIZE, "log_interval": chunk, "eval_interval": total_steps,
        "checkpoint_interval": total_steps, "num_devices": 1, "eval_episodes": eval_episodes,
        "truncation": "bootstrap", **(changes or {}),
    }  # fmt: skip
    cfg = resolve_config("tracking", "ppo", "quick", num_seeds=seeds, total_steps=total_steps,
                         overrides={k: str(v) for k, v in overrides.items()})  # fmt: skip
    return cfg


def _train_ours(cfg: TrainConfig, folder: Path) -> tuple[np.ndarray, float]:
    """Final greedy evaluation returns per seed, and env steps per second of the timed chunks."""
    from xrl_jax.train import train

    summary = train(cfg, folder, progress=False, log=lambda *_: None)
    returns = np.array([summary["per_seed"][str(seed)]["avg_return"] for seed in range(cfg.num_seeds)])
    timings = (folder / "timing.jsonl").read_text().splitlines()
    seconds = [json.loads(line)["seconds"] for line in timings][1:]  # the first chunk compiles
    if not seconds:
        raise ValueError("the run had one chunk, which compiled: give --steps several rollouts more")
    steps = cfg.log_interval * cfg.num_seeds * len(seconds)
    return returns, steps / sum(seconds)


def _rejax_env(rejax_with: Collection[str]):
    """Tracking for rejax (gymnax's older step API), with ``rejax_with``'s pieces of ours: ``squash``
    takes unbounded actions and applies tanh to them (rejax's clip to the box then never acts);
    ``observation`` gives our flat encoding instead of gymnax's flat observation."""
    from gymnax.environments import spaces

    from envs import gymnax as carenv_gymnax

    squash, ours = "squash" in rejax_with, "observation" in rejax_with
    env, params = carenv_gymnax.make("tracking", flat_obs=not ours)
    if not (squash or ours):
        return carenv_gymnax.legacy_step_api(env), params
    observe = _our_flat_observation if ours else lambda obs: obs
    example = observe(env.reset(jax.random.PRNGKey(0), params)[0]) if ours else None  # its shape

    class WithOurs(carenv_gymnax.LegacyStepAPI):
        def observation_space(self, params=None):
            return (
                spaces.Box(-jnp.inf, jnp.inf, example.shape, example.dtype)
                if ours
                else self._env.observation_space(params)  # the wrapper delegates by __getattr__ only
            )

        def action_space(self, params=None):
            box = self._env.action_space(params)
            return spaces.Box(-jnp.inf, jnp.inf, box.shape, box.dtype) if squash else box

        def reset(self, key, params=None):
            obs, state = super().reset(key, params)
            return observe(obs), state

        def step(self, key, state, action, params=None):
            obs, state, reward, done, info = super().step(
                key, state, jnp.tanh(action) if squash else action, params
            )
            return observe(obs), state, reward, done, info

    return WithOurs(env), params


def _state_std_actor(actor):
    """rejax's Gaussian ``actor`` with log σ a Dense head of its features, clipped to SAC's bounds."""
    import distrax
    import flax.linen as nn
    from rejax.networks import MLP, GaussianPolicy

    class StateStdGaussian(GaussianPolicy):
        def setup(self):
            self.features = MLP(self.hidden_layer_sizes, self.activation)
            self.action_mean = nn.Dense(self.action_dim)
            self.action_log_std = nn.Dense(self.action_dim)

        def _action_dist(self, obs):
            features = self.features(obs)
            log_std = jnp.clip(self.action_log_std(features), SAC_LOG_STD_MIN, LOG_STD_MAX)
            return distrax.MultivariateNormalDiag(loc=self.action_mean(features), scale_diag=jnp.exp(log_std))

    return StateStdGaussian(actor.action_dim, actor.action_range, actor.hidden_layer_sizes, actor.activation)


def _with_global_norm_clip(algo):
    """``algo`` whose actor and critic optimisers clip the gradient's global norm at its
    ``max_grad_norm`` (ours) instead of every element at it (rejax's ``optax.clip``)."""
    import dataclasses

    import optax
    from rejax.algos.algorithm import register_init

    class GlobalClipPPO(type(algo)):
        @register_init
        def initialize_network_params(self, rng):
            states = super().initialize_network_params(rng)
            tx = optax.chain(optax.clip_by_global_norm(self.max_grad_norm), optax.adam(self.learning_rate))
            return {name: ts.replace(tx=tx, opt_state=tx.init(ts.params)) for name, ts in states.items()}

    return GlobalClipPPO(**{field.name: getattr(algo, field.name) for field in dataclasses.fields(algo)})


def make_rejax_ppo(cfg: TrainConfig, rejax_with: Collection[str] = ()):
    """rejax's PPO with ``cfg``'s shared settings on Tracking through :mod:`envs.gymnax`, evaluating
    nothing while it trains (ours evaluates outside its timed chunks too); ``rejax_with``: pieces of
    ours it is given (:data:`REJAX_PIECES`)."""
    unknown = [piece for piece in rejax_with if piece not in REJAX_PIECES]
    if isinstance(rejax_with, str) or unknown:
        raise ValueError(f"rejax_with takes pieces of {', '.join(REJAX_PIECES)}, got {rejax_with!r}")
    try:
        import rejax
    except ImportError:
        raise ImportError("bench.py rejax needs rejax: pip install -e '.[gymnax-tests]'") from None

    a = cfg.agent
    env, params = _rejax_env(rejax_with)
    algo = rejax.PPO.create(
        env=env, env_params=params, total_timesteps=cfg.total_steps,
        num_envs=cfg.num_envs, num_steps=a.rollout_steps, num_epochs=a.ppo_epochs,
        num_minibatches=a.ppo_minibatches, learning_rate=a.actor_lr, gamma=a.gamma,
        gae_lambda=a.gae_lambda, clip_eps=a.clip_eps, ent_coef=a.ent_coef, max_grad_norm=a.clip_norm,
        eval_freq=cfg.total_steps, skip_initial_evaluation=True,
        agent_kwargs={"hidden_layer_sizes": (a.actor_width,) * a.actor_depth, "activation": "relu"},
    )  # fmt: skip
    algo = algo.replace(eval_callback=lambda algo, ts, rng: jnp.zeros(()))
    if "state_std" in rejax_with:
        algo = algo.replace(actor=_state_std_actor(algo.actor))
    if "global_clip" in rejax_with:
        algo = _with_global_norm_clip(algo)
    return algo


def _train_rejax(cfg: TrainConfig, seed: int, rejax_with: Collection[str]) -> tuple[Any, Any, float]:
    """(algorithm, trained actor params per member, env steps per second of the compiled training,
    compilation excluded)."""
    algo = make_rejax_ppo(cfg, rejax_with)
    keys = jax.random.split(jax.random.PRNGKey(seed), cfg.num_seeds)
    compiled = jax.jit(jax.vmap(algo.train)).lower(keys).compile()
    start = time.perf_counter()
    train_state, _ = compiled(keys)
    jax.block_until_ready(train_state)
    rate = cfg.total_steps * cfg.num_seeds / (time.perf_counter() - start)
    return algo, train_state.actor_ts.params, rate


def _evaluate_rejax(cfg: TrainConfig, algo, actor_params, rejax_with: Collection[str]) -> np.ndarray:
    """Greedy returns (the mean action, clipped or squashed as it trained, on the observation it
    trained on) per member on the trainer's held-out tracks."""
    from envs.gymnax import flatten_observation
    from xrl_jax.evaluation import make_evaluate_policy
    from xrl_jax.train.kinds import make_envs

    env, _, eval_params = make_envs(cfg)

    def greedy(key, params, obs, env_states, per_episode):
        del key, env_states, per_episode
        observe = _our_flat_observation if "observation" in rejax_with else flatten_observation
        mean = algo.actor.apply(params, observe(obs), method="_action_dist").mean()
        return jnp.tanh(mean) if "squash" in rejax_with else jnp.clip(mean, -1.0, 1.0)

    evaluate = make_evaluate_policy(env, eval_params, greedy, cfg.eval_episodes)
    keys = jax.random.split(jax.random.PRNGKey(cfg.eval_track_seed), cfg.num_seeds)
    per_episode = jax.jit(jax.vmap(evaluate))(keys, actor_params)
    return np.asarray(per_episode["return"]).mean(axis=1)


def ppo_against_rejax(seeds: int = 8, total_steps: int = 1_048_576, num_envs: int = 16,
                      rollout_steps: int = 128, epochs: int = 4, minibatches: int = 8, width: int = 64,
                      depth: int = 2, folder: str | None = None, eval_episodes: int = 100,
                      rejax_with: Collection[str] = (),
                      changes: Mapping[str, Any] | None = None) -> dict[str, Any]:  # fmt: skip
    """Both PPOs at the settings given, ``seeds`` members each: final greedy returns per seed (over
    ``eval_episodes`` held-out tracks) with their IQM and 95 % interval, P(ours > rejax) with the
    Mann-Whitney test, and env steps per second. ``rejax_with``: pieces of ours rejax's PPO is given
    (:data:`REJAX_PIECES`; none: its own); ``changes``: settings of the config changed for an
    ablation, read by both sides where rejax has them (``ent_coef``), else by ours alone
    (``truncation="terminal"``, ``value_clip_eps``: rejax's readings of the time limit and the value
    loss)."""
    cfg = comparison_config(seeds, total_steps, num_envs, rollout_steps, epochs, minibatches, width, depth,
                            eval_episodes, changes)  # fmt: skip
    with tempfile.TemporaryDirectory() as scratch:
        ours, ours_rate = _train_ours(cfg, Path(folder or scratch) / "ours")
    algo, actor_params, rejax_rate = _train_rejax(cfg, cfg.seed, rejax_with)
    theirs = _evaluate_rejax(cfg, algo, actor_params, rejax_with)

    def side(returns, rate):
        interval = stats.stratified_bootstrap_ci(returns)
        return {"returns": [round(float(r), 3) for r in returns], "iqm": interval.estimate,
                "ci95": [interval.low, interval.high], "env_steps_per_s": round(rate, 1)}  # fmt: skip

    improvement = stats.probability_of_improvement_ci(ours, theirs)
    a = cfg.agent
    settings = {
        "env": "tracking (continuous)", "seeds": seeds, "total_steps": total_steps, "num_envs": num_envs,
        "rollout_steps": rollout_steps, "epochs": epochs, "minibatches": minibatches, "mlp": [width] * depth,
        "lr": a.actor_lr, "gamma": a.gamma, "gae_lambda": a.gae_lambda, "clip_eps": a.clip_eps,
        "ent_coef": a.ent_coef, "clip_norm": a.clip_norm, "eval_episodes": cfg.eval_episodes,
        "xrl_jax_truncation": a.truncation, "xrl_jax_value_clip_eps": a.value_clip_eps,
        "rejax_with": [piece for piece in REJAX_PIECES if piece in rejax_with],
    }  # fmt: skip
    return {
        "settings": settings,
        "xrl_jax": side(ours, ours_rate),
        "rejax": side(theirs, rejax_rate),
        "p_xrl_jax_above_rejax": improvement.as_dict(),
        "mann_whitney_p": stats.improvement_test(ours, theirs),
    }
