"""Evaluation of the racing scenarios on fixed tracks (docs/algorithms.md §6.1).

Protocol: ``n`` episodes, episode ``i`` always on track ``i`` of a fixed evaluation bank, so every
evaluation of every seed sees the same tracks. Each agent acts in its evaluation mode (§3.8: SAC,
DSAC, XDSAC greedy; XSAC stochastic, from a separate key stream). All episodes run in parallel
(a batch of envs without auto-reset) until each has terminated or been truncated; finished
episodes are frozen by masks. Per episode: return, length, how it ended; early termination (ETR)
= terminated with a last reward below −0.5, success (SR) = terminated otherwise; why it ended (the
env's ``done_reason``: left the track, time limit, idling, an invalid action) and how far along the
track (m), so that a report can say where and how an agent's episodes end, not only how often early.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.racing import IDLING, LEFT_TRACK, MAX_TIME, NONFINITE_ACTION
from xrl_jax.agents import check_eval_mode

EARLY_TERMINATION_REWARD = -0.5
EPISODE_FIELDS = ("return", "length", "terminated", "truncated", "last_reward", "track_velocity", "cones_hit",
                  "done_reason", "progress")  # fmt: skip
# The racing envs' done_reason codes (envs.racing.DONE_REASONS) as evaluation-row names: the share of
# episodes that ended so, avg_end_<name>.
END_REASONS = {
    LEFT_TRACK: "left_track", MAX_TIME: "time_limit", IDLING: "idling", NONFINITE_ACTION: "invalid_action"
}  # fmt: skip


# The racing env's info entries an episode's record keeps, by record field (their last value).
_FROM_INFO = {"track_velocity": "avg_track_velocity", "progress": "track_progress", "cones_hit": "cones_hit",
              "done_reason": "done_reason"}  # fmt: skip


def empty_record(num_episodes: int, floats: tuple[str, ...] = (), ints: tuple[str, ...] = ()) -> dict:
    """Each episode's record before its first step: return, length, how it ended and its last reward,
    plus an env's own ``floats`` and ``ints`` (each ``(num_episodes,)``)."""
    zeros = jnp.zeros((num_episodes,), jnp.result_type(float))
    counts, ended = jnp.zeros((num_episodes,), jnp.int32), jnp.zeros((num_episodes,), bool)
    record = {"return": zeros, "length": counts, "terminated": ended, "truncated": ended}
    return record | {"last_reward": zeros} | dict.fromkeys(floats, zeros) | dict.fromkeys(ints, counts)


def record_step(record: dict, done, reward, terminated, truncated, **latest) -> dict:
    """``record`` after one step of every episode: the reward added to the return, one step counted,
    how the step ended and the env's ``latest`` values taken; an episode already ``done`` before the
    step keeps its record (the batch steps on until every episode has ended)."""
    stepped = latest | {"return": record["return"] + reward, "length": record["length"] + 1,
                        "terminated": terminated, "truncated": truncated, "last_reward": reward}  # fmt: skip
    return {name: jnp.where(done, old, stepped[name]).astype(old.dtype) for name, old in record.items()}


def make_evaluate(env, eval_params, agent, num_episodes: int, mode: str = "eval"):
    """``evaluate(key, agent_state) -> per-episode arrays`` (each ``(num_episodes,)``), jittable.

    ``eval_params`` holds a bank of at least ``num_episodes`` tracks; episode ``i`` uses track ``i``.
    ``mode`` is the agent's acting mode: "eval" (the reference's, §3.8), or one of the diagnostics
    outside the paper's protocol, "deterministic" (greedy for every agent, XSAC included) and
    "stochastic" (a policy sample for every agent).
    """
    check_eval_mode(mode)

    def policy(key, agent_state, obs, env_states, per_episode):
        del env_states, per_episode  # an agent sees only its observation
        return agent.act(key, agent_state, obs, mode)

    return make_evaluate_policy(env, eval_params, policy, num_episodes)


def make_evaluate_policy(env, eval_params, policy, num_episodes: int):
    """:func:`make_evaluate` for any ``policy(key, policy_state, obs, env_states, per_episode)``
    returning the batch of actions; ``evaluate(key, policy_state)``.

    A policy that reads the env state (the hand controller reads the centre line) gets it batched
    over episodes, with ``per_episode(fn)``: ``fn(env_state, params)`` vmapped over the episodes,
    each with its own track's params.
    """
    bank_size = int(eval_params.tracks.num_points.shape[0])
    if bank_size < num_episodes:
        raise ValueError(f"the evaluation bank has {bank_size} tracks, fewer than {num_episodes} episodes")
    tracks = jax.tree.map(lambda leaf: leaf[:num_episodes, None], eval_params.tracks)
    tables = getattr(eval_params, "tables", None)
    tables = None if tables is None else jax.tree.map(lambda leaf: leaf[:num_episodes, None], tables)
    max_steps = int(eval_params.max_steps)

    def own_params(track, table):
        changes = {"tracks": track} if table is None else {"tracks": track, "tables": table}
        return eval_params.replace(**changes)

    def reset_one(key, track, table):
        return env.reset_env(key, own_params(track, table))

    def step_one(key, state, action, track, table):
        return env.step_env(key, state, action, own_params(track, table))

    table_axis = 0 if tables is not None else None
    reset_all = jax.vmap(reset_one, in_axes=(0, 0, table_axis))
    step_all = jax.vmap(step_one, in_axes=(0, 0, 0, 0, table_axis))

    def per_episode(fn):
        def on_all(env_states):
            one = lambda state, track, table: fn(state, own_params(track, table))
            return jax.vmap(one, in_axes=(0, 0, table_axis))(env_states, tracks, tables)

        return on_all

    def evaluate(key, policy_state):
        reset_key, key = jax.random.split(key)
        obs, env_state = reset_all(jax.random.split(reset_key, num_episodes), tracks, tables)
        record = empty_record(
            num_episodes, floats=("track_velocity", "progress"), ints=("cones_hit", "done_reason")
        )

        def running(carry):
            # At most max_steps + 1 rounds, whatever the policy outputs. The env truncates every episode
            # at max_steps (and terminates it at once on a NaN action), so the count never cuts one short.
            _, _, done, _, _, t = carry
            return ~jnp.all(done) & (t < max_steps + 1)

        def body(carry):
            obs, env_state, done, record, key, t = carry
            key, act_key, step_key = jax.random.split(key, 3)
            action = policy(act_key, policy_state, obs, env_state, per_episode)
            obs, env_state, reward, terminated, truncated, info = step_all(
                jax.random.split(step_key, num_episodes), env_state, action, tracks, tables
            )
            latest = {name: info[key] for name, key in _FROM_INFO.items()}
            record = record_step(record, done, reward, terminated, truncated, **latest)
            return obs, env_state, done | terminated | truncated, record, key, t + 1

        not_done = jnp.zeros((num_episodes,), bool)
        carry = (obs, env_state, not_done, record, key, jnp.zeros((), jnp.int32))
        return jax.lax.while_loop(running, body, carry)[3]

    return evaluate


def summarize_episodes(episodes: dict[str, Any]) -> dict[str, Any]:
    """The §6.1 averages of one seed's evaluation, plus the per-episode returns (host side); a user's
    env reports return, episode length and the share of episodes its env terminated."""
    if "trips_completed" in episodes:  # multi-agent: the env's metrics (docs/carenv-intersection.md §8.8)
        out = {f"avg_{k}": float(np.mean(v)) for k, v in episodes.items() if k != "return"}
        returns = np.asarray(episodes["return"], np.float64)
        return {
            "avg_return": float(returns.mean()),
            **out,
            "episode_returns": [round(float(r), 6) for r in returns],
        }
    returns = np.asarray(episodes["return"], np.float64)
    terminated = np.asarray(episodes["terminated"], bool)
    if "track_velocity" not in episodes:  # a user's env (xrl_jax.evaluation.resets)
        return {
            "avg_return": float(returns.mean()),
            "avg_episode_length": float(np.mean(episodes["length"])),
            "avg_terminated": float(terminated.mean()),
            "episode_returns": [round(float(r), 6) for r in returns],
        }
    early = terminated & (np.asarray(episodes["last_reward"]) < EARLY_TERMINATION_REWARD)
    out = {
        "avg_return": float(returns.mean()),
        "avg_episode_length": float(np.mean(episodes["length"])),
        "avg_etr": float(early.mean()),
        "avg_sr": float((terminated & ~early).mean()),
        "avg_track_velocity": float(np.mean(episodes["track_velocity"])),
        "avg_cones_hit": float(np.mean(episodes["cones_hit"])),
    }
    if "done_reason" in episodes:  # evaluations before the ending reasons were recorded lack them
        reasons = np.asarray(episodes["done_reason"])
        out |= {f"avg_end_{name}": float(np.mean(reasons == code)) for code, name in END_REASONS.items()}
        out["avg_end_progress_m"] = float(np.mean(episodes["progress"]))
    return {**out, "episode_returns": [round(float(r), 6) for r in returns]}
