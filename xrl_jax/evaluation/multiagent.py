"""Evaluation of the multi-agent Intersection (docs/carenv-intersection.md §8.8): fixed episodes whose
env randomness every evaluation (and every replay of an episode, e.g. the explanation figures) shares."""

from __future__ import annotations

import jax
import jax.numpy as jnp

EVAL_ENV_SEED = 0  # multi-agent evaluation: episode i always replays the env randomness of key (0, i)


def evaluation_episode_keys(episodes) -> tuple[jax.Array, jax.Array]:
    """``(reset_keys, stream_keys)`` of multi-agent evaluation episodes ``episodes`` (int array (E,)).

    Episode i's env randomness is ``fold_in(PRNGKey(EVAL_ENV_SEED), i)`` split into the reset key
    and a stream whose step-t key is ``fold_in(stream_key, t)`` (see :func:`evaluation_step_key`);
    the protocol of :func:`make_evaluate_multiagent`, so a replay of episode i (e.g. the
    explanation figures) sees exactly the evaluation's traffic.
    """
    episodes = jnp.asarray(episodes, jnp.int32)
    base = jax.random.PRNGKey(EVAL_ENV_SEED)
    episode_keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(episodes.reshape(-1))
    reset_keys, stream_keys = jnp.unstack(jax.vmap(jax.random.split)(episode_keys), axis=1)
    return reset_keys.reshape(*episodes.shape, -1), stream_keys.reshape(*episodes.shape, -1)


def evaluation_step_key(stream_key: jax.Array, t) -> jax.Array:
    """The env key of step ``t`` of an evaluation episode from its stream key."""
    return jax.random.fold_in(stream_key, t)


def make_evaluate_multiagent(env, eval_params, agent, num_episodes: int):
    """``evaluate(key, agent_state) -> per-episode arrays`` for the multi-agent Intersection
    (docs/carenv-intersection.md §8.8): ``num_episodes`` episodes of ``eval_params.episode_steps`` steps with
    the evaluation cap of vehicles, every episode's env randomness fixed (episode ``i`` uses the key
    ``fold_in(PRNGKey(0), i)``, the analogue of the reference's ``reset(seed=i)``), the policy's own
    randomness (XSAC samples) from ``key``. Per episode: the return summed over all agents, and the
    env's metrics at the last step (trips completed, vehicles off the road, collided vehicles, mean
    velocity); early terminations = off-road + collided vehicles.
    """
    return make_evaluate_multiagent_policy(
        env, eval_params, lambda key, agent_state, obs: agent.act(key, agent_state, obs, "eval"), num_episodes
    )


def make_evaluate_multiagent_policy(env, eval_params, policy, num_episodes: int):
    """:func:`make_evaluate_multiagent` for any ``policy(key, policy_state, obs) -> actions`` that
    acts for every slot of a batch of episodes (obs leaves ``(episodes, 8, ...)``), e.g. the
    scripted driver; ``evaluate(key, policy_state)``."""
    steps = int(eval_params.episode_steps)
    reset_keys, stream_keys = evaluation_episode_keys(jnp.arange(num_episodes))
    reset_all = jax.vmap(env.reset, in_axes=(0, None))
    step_all = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    metric_keys = ("trips_completed", "come_off_vehicles", "collided_vehicles", "mean_velocity")

    def evaluate(key, policy_state):
        obs, env_state = reset_all(reset_keys, eval_params)
        returns = jnp.zeros((num_episodes,), jnp.result_type(float))

        def body(carry, t):
            obs, env_state, returns, key = carry
            key, act_key = jax.random.split(key)
            action = policy(act_key, policy_state, obs)
            step_keys = jax.vmap(evaluation_step_key, in_axes=(0, None))(stream_keys, t)
            obs, env_state, reward, _, _, info = step_all(step_keys, env_state, action, eval_params)
            returns = returns + jnp.sum(jnp.where(info["acted"], reward, 0.0), axis=-1)
            return (obs, env_state, returns, key), {k: info[k] for k in metric_keys}

        (_, _, returns, _), metrics = jax.lax.scan(
            body, (obs, env_state, returns, key), jnp.arange(steps, dtype=jnp.int32)
        )
        last = {k: v[-1] for k, v in metrics.items()}  # the env's episode metrics after its last step
        return {
            "return": returns,
            **last,
            "early_terminations": last["come_off_vehicles"] + last["collided_vehicles"],
        }

    return evaluate
