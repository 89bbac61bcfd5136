"""Environment throughput: steps per second of batched envs under random actions inside one
``lax.scan`` (racing scenarios with auto-reset, the Intersection restarting itself), and the cost of
the fresh-track feed beside a fixed bank."""

from __future__ import annotations

import jax
import jax.numpy as jnp

import envs
from envs.core import VmapWrapper, vmap_env
from envs.racing import with_bank
from envs.track_feed import init_feed, refill_feed, reset_with_feed, step_with_feed
from envs.track_generator import generate_track, make_track_bank
from xrl_jax.benchmarks.timing import compiled_flops, seconds_of, timed, timed_alternately
from xrl_jax.tracks import cached_track_bank


def _compile_rollout(reset, rollout, key):
    """First calls of a jitted ``reset(key)`` and ``rollout(key, state)``: returns the reset state,
    the rollout's output and the two first-call times (compilation plus one run each)."""
    (_, state), reset_compile = seconds_of(lambda: reset(key))
    output, rollout_compile = seconds_of(lambda: rollout(key, state))
    return state, output, {"reset": reset_compile, "rollout": rollout_compile}


def bench_env(scenario: str, batch: int, steps: int, repeats: int) -> dict:
    """Env-steps/s of ``batch`` auto-resetting envs driven by random actions inside one ``lax.scan``."""
    env, params = envs.make(scenario)
    venv = vmap_env(env, batch)

    @jax.jit
    def reset(key):
        return venv.reset(key, params)

    @jax.jit
    def rollout(key, state):
        def body(state, key):
            key_act, key_step = jax.random.split(key)
            action = venv.sample_actions(key_act, params)
            _, state, reward, *_ = venv.step(key_step, state, action, params)
            return state, reward.sum()

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    key = jax.random.PRNGKey(0)
    state, _, compile_s = _compile_rollout(reset, rollout, key)
    reset_seconds = timed(lambda: reset(key), repeats)
    rollout_seconds = timed(lambda: rollout(key, state), repeats)
    return {
        "scenario": scenario,
        "batch": batch,
        "steps_per_call": steps,
        "env_steps_per_s": batch * steps / rollout_seconds,
        "reset_us_per_env": 1e6 * reset_seconds / batch,
        "compile_s": compile_s,
    }


def bench_intersection(max_vehicles: int, batch: int, steps: int, repeats: int, discrete: bool) -> dict:
    """Env-steps/s and agent-steps/s of ``batch`` intersection envs (fixed ``max_vehicles``), random
    actions for all 8 slots, inside one jitted ``lax.scan``. The env restarts itself every 600 steps,
    so no auto-reset wrapper is needed; agent-steps count the slots that acted (``info["acted"]``)."""
    name = "intersection_discrete" if discrete else "intersection"
    env, params = envs.make(name, max_vehicles=max_vehicles)
    venv = VmapWrapper(env, batch)

    @jax.jit
    def reset(key):
        return venv.reset(key, params)

    @jax.jit
    def rollout(key, state):
        def body(carry, key):
            state, agent_steps = carry
            key_act, key_step = jax.random.split(key)
            action = jax.vmap(env.sample_actions, in_axes=(0, None))(jax.random.split(key_act, batch), params)
            _, state, reward, _, _, info = venv.step(key_step, state, action, params)
            return (state, agent_steps + jnp.sum(info["acted"], dtype=jnp.int32)), reward.sum()

        (state, agent_steps), rewards = jax.lax.scan(
            body, (state, jnp.zeros((), jnp.int32)), jax.random.split(key, steps)
        )
        return state, agent_steps, rewards

    key = jax.random.PRNGKey(0)
    state, (_, agent_steps, _), compile_s = _compile_rollout(reset, rollout, key)
    rollout_seconds = timed(lambda: rollout(key, state), repeats)
    return {
        "scenario": name,
        "max_vehicles": max_vehicles,
        "batch": batch,
        "steps_per_call": steps,
        "env_steps_per_s": batch * steps / rollout_seconds,
        "agent_steps_per_s": int(agent_steps) / rollout_seconds,
        "mean_alive_agents": int(agent_steps) / (batch * steps),
        "compile_s": compile_s,
    }


def bench_tracks(seeds: int, count: int, repeats: int) -> dict:
    """Fresh-track cost: a refill of ``count`` tracks into each of ``seeds`` feeds (generation, ring
    tables, reset observations, the slot writes), as the training chunk runs it; and XLA's FLOP count
    of one track, which counts every loop body once (a lower bound: the generator's pairwise checks
    loop over ~50 blocks for a typical track)."""
    bank = cached_track_bank(1, 1)
    env, template = envs.make("tracking", track=jax.tree.map(lambda leaf: leaf[0], bank))
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    feeds = jax.jit(jax.vmap(lambda key: init_feed(env, template, key, 2 * count, 4)))(keys)
    feeds = feeds.replace(issued=feeds.generated, driving=jnp.full_like(feeds.driving, -1))  # all slots free
    refill = jax.jit(lambda feed: refill_feed(env, feed, count))
    _, compile_s = seconds_of(lambda: refill(feeds))
    seconds = timed(lambda: refill(feeds), repeats)
    step_us = _vector_step_costs(env, template, repeats)
    params = feeds.params
    bank_leaves = (params.tracks, params.tables, params.start_s, params.reset_obs)
    return {
        "seeds": seeds,
        "tracks_per_refill": seeds * count,
        "ms_per_track": 1e3 * seconds / (seeds * count),
        "refill_s": seconds,
        "compile_s": compile_s,
        "xla_flops_per_track_loop_bodies_once": compiled_flops(generate_track, jax.random.PRNGKey(0)),
        "bytes_per_track_in_feed": sum(x.nbytes for x in jax.tree.leaves(bank_leaves)) // (seeds * 2 * count),
        "vector_step_us_4_envs": step_us,
    }


def _vector_step_costs(env, template, repeats: int, steps: int = 2000) -> dict:
    """Microseconds per step of 4 auto-resetting envs (a training seed's vector step) under random
    actions: on a fixed bank of 128 (the auto-reset wrapper) and on a fresh-track feed of 128, so the
    feed's per-step overhead is measured apart from the (much larger) agent update."""
    space = env.action_space(template)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (steps, 4, *space.shape), minval=-1, maxval=1)
    bank_params = env.prepare(with_bank(template, make_track_bank(jax.random.PRNGKey(0), 128)))
    venv = vmap_env(env, 4)

    @jax.jit
    def on_bank(key):
        _, states = venv.reset(key, bank_params)

        def body(states, inputs):
            key, action = inputs
            return venv.step(key, states, action, bank_params)[1], None

        return jax.lax.scan(body, states, (jax.random.split(key, steps), actions))[0]

    @jax.jit
    def on_feed(key, states, feed):
        def body(carry, inputs):
            key, action = inputs
            states, feed = carry
            out = step_with_feed(env, key, states, action, feed)
            return (out[1], out[-1]), None

        return jax.lax.scan(body, (states, feed), (jax.random.split(key, steps), actions))[0]

    key = jax.random.PRNGKey(2)
    _, states, feed = reset_with_feed(env, jax.jit(lambda k: init_feed(env, template, k, 128, 4))(key))
    jax.block_until_ready((on_bank(key), on_feed(key, states, feed)))
    calls = {"bank": lambda: on_bank(key), "feed": lambda: on_feed(key, states, feed)}
    seconds = timed_alternately(calls, repeats)
    return {name: 1e6 * value / steps for name, value in seconds.items()}
