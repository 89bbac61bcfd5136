"""Evaluation of a user's env (:func:`xrl_jax.custom_envs.register_env`) from its own reset: episode
``i`` always starts from, and steps with, the env randomness of ``fold_in(PRNGKey(seed), i)``, so
every evaluation of every seed meets the same episodes, as the racing evaluation meets the same
tracks. An episode ends when the env terminates or truncates it, or at ``max_steps`` (then it counts
as truncated)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from xrl_jax.agents import check_eval_mode
from xrl_jax.evaluation.protocol import empty_record, record_step


def reset_episode_keys(seed: int, num_episodes: int) -> tuple[jax.Array, jax.Array]:
    """``(reset_keys, stream_keys)``, each ``(num_episodes, key)``: episode ``i``'s reset key and the
    stream whose step-``t`` key is ``fold_in(stream_key, t)``."""
    base = jax.random.PRNGKey(seed)
    keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(base, i)))(jnp.arange(num_episodes))
    return keys[:, 0], keys[:, 1]


def make_evaluate_resets(
    env, params, agent, num_episodes: int, max_steps: int, seed: int, mode: str = "eval"
):
    """``evaluate(key, agent_state) -> per-episode arrays`` (return, length, terminated, truncated,
    last_reward; each ``(num_episodes,)``), jittable; ``key`` drives only the policy's own sampling
    (XSAC acts stochastically in its evaluation mode, docs/algorithms.md §3.8)."""
    check_eval_mode(mode)
    if int(max_steps) < 1 or int(num_episodes) < 1:
        raise ValueError(f"max_steps ({max_steps}) and num_episodes ({num_episodes}) must be positive")
    reset_keys, stream_keys = reset_episode_keys(seed, num_episodes)
    reset_all = jax.vmap(env.reset_env, in_axes=(0, None))
    step_all = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))

    def evaluate(key, agent_state):
        obs, env_state = reset_all(reset_keys, params)
        record = empty_record(num_episodes)

        def running(carry):  # ends after max_steps rounds whatever the env and the policy output
            done, t = carry[2], carry[5]
            return ~jnp.all(done) & (t < max_steps)

        def body(carry):
            obs, env_state, done, record, key, t = carry
            key, act_key = jax.random.split(key)
            action = agent.act(act_key, agent_state, obs, mode)
            step_keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(stream_keys, t)
            obs, env_state, reward, terminated, truncated, _ = step_all(step_keys, env_state, action, params)
            truncated = truncated | (t + 1 >= max_steps)
            record = record_step(record, done, reward, terminated, truncated & ~terminated)
            return obs, env_state, done | terminated | truncated, record, key, t + 1

        not_done = jnp.zeros((num_episodes,), bool)
        carry = (obs, env_state, not_done, record, key, jnp.zeros((), jnp.int32))
        return jax.lax.while_loop(running, body, carry)[3]

    return evaluate
