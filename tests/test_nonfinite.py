"""Non-finite and out-of-range actions: every env's step returns, stays finite and ends the episode.

A diverged policy outputs NaN or ±inf. Before the fix such an action sent NaN into the car's state,
and the track projection's ``while_loop`` then never ended, so a jitted step hung. A hang cannot be
caught inside the process, so every check runs in a child process (this file, run as a script) with
a timeout: a hang fails the test instead of blocking the run. Each child compiles one batched step
(``jit`` of ``vmap``, one action per batch row) and writes its outputs to an ``.npz`` for the asserts.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import envs

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data" / "episode_country_road_public.npz"
TIMEOUT_S = 300  # compile + one step takes ~10-30 s on a shared 2-core machine; a hang takes forever
NAN, INF = float("nan"), float("inf")
I32 = np.iinfo(np.int32)

# Batch rows per action kind, and which rows are invalid (must end the episode with reason 4).
CONTINUOUS_ROWS = [
    [NAN] * 3,
    [INF] * 3,
    [-INF] * 3,
    [0.0, NAN, 0.0],
    [0.0, 0.0, -INF],
    [1e30] * 3,  # huge but finite: clipped, so equal to the [1, 1, 1] row
    [-1e30] * 3,  # equal to the [-1, -1, -1] row
    [1.0] * 3,
    [-1.0] * 3,
    [0.0, 1.0, -1.0],
    [0.0, -1.0, -1.0],  # last row: the neutral control (0, 0, 0) that invalid actions are replaced by
]
CONTINUOUS_INVALID = [True] * 5 + [False] * 6
# Discrete indices given as floats (a policy's argmax cast late) and as int32; index 4 is neutral.
DISCRETE_FLOAT_ROWS = [NAN, INF, -INF, 1e30, -1e30, 12.0, -1.0, 6.0, -0.5, 11.9, 4.0]
DISCRETE_FLOAT_INVALID = [True] * 7 + [False] * 4
DISCRETE_INT_ROWS = [-1, 12, I32.max, I32.min, 6, 0, 4]
DISCRETE_INT_INVALID = [True] * 4 + [False] * 3


def _float_leaves(tree):
    import jax
    import jax.numpy as jnp

    return [x for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)]


def _make(name):
    if name.startswith("intersection"):
        env, params = envs.make(name, max_vehicles=4)  # slots 0-3 alive at reset, 4-7 padding
    else:
        with np.load(DATA) as data:
            pose = data["start_pose"]
            track = envs.track_from_arrays(
                data["track_centerline"], pose[:2], pose[2], data["cone_pos"], data["cone_type"]
            )
        env, params = envs.make(name, track=track)
    return env, params


def _step_batch(env, params, actions):
    """One jitted, vmapped step from identical reset states (the same episode), one action per row."""
    import jax
    import jax.numpy as jnp

    batch = actions.shape[0]
    key = jax.random.PRNGKey(0)
    _, state = jax.jit(env.reset)(key, params)
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *jnp.shape(x))), state)
    keys = jnp.broadcast_to(key, (batch, *key.shape))
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    obs, state, reward, terminated, truncated, info = step(keys, state, jnp.asarray(actions), params)
    leaves = _float_leaves((obs, state, info))
    flat = jnp.concatenate([x.reshape(batch, -1).astype(jnp.float32) for x in leaves], axis=1)
    return {
        "flat": flat,  # every float output of the step, per row
        "reward": reward,
        "terminated": terminated,
        "truncated": truncated,
        "done_reason": info["done_reason"],
        "nonfinite_action": info["nonfinite_action"],
    }


def _actions(name, kind):
    """The batch of actions for ``kind`` ("float" or "int"); intersection: in slot 0, NaN in slot 7."""
    discrete = name.endswith("_discrete")
    rows = (DISCRETE_FLOAT_ROWS if kind == "float" else DISCRETE_INT_ROWS) if discrete else CONTINUOUS_ROWS
    rows = np.asarray(rows, np.float32 if kind == "float" else np.int32)
    if not name.startswith("intersection"):
        return rows
    per_slot = np.zeros((rows.shape[0], 8, *rows.shape[1:]), rows.dtype)
    per_slot[:, 0] = rows
    if kind == "float":
        per_slot[:, 7] = NAN  # slot 7 holds no car: its action must be ignored
    return per_slot


def _worker_project(out):
    """``project_point`` at non-finite, huge and ordinary positions of the test track."""
    import jax
    import jax.numpy as jnp
    import track_reference  # tests/ is on the path: this file runs as a script

    from envs import ring_geometry

    with np.load(DATA) as data:
        pose = data["start_pose"]
        track = envs.track_from_arrays(data["track_centerline"], pose[:2], pose[2])
    _, params = envs.make("tracking", track=track)
    tracks = params.tracks
    view = ring_geometry.TrackView(
        params.tables, jnp.int32(0), tracks.length[0], tracks.num_points[0], tracks.cone_type[0]
    )
    x0, y0 = (float(v) for v in pose[:2])
    px = jnp.asarray([NAN, 0.0, INF, -INF, INF, 1e30, -1e30, x0, x0 + 3.0], jnp.float32)
    py = jnp.asarray([0.0, NAN, 0.0, 5.0, -INF, 1e30, 0.0, y0, y0 - 2.0], jnp.float32)
    project = jax.jit(jax.vmap(lambda x, y: ring_geometry.project_point(view, x, y)))
    brute = jax.jit(jax.vmap(lambda x, y: track_reference.project_point_global(view, x, y)))
    s, distance, tangent = project(px, py)
    s_ref, distance_ref, _ = brute(px[-2:], py[-2:])
    np.savez(out, s=s, distance=distance, tangent=tangent, s_ref=s_ref, distance_ref=distance_ref)


def _worker_evaluate(out):
    """``make_evaluate`` (its while_loop) with a policy that only outputs NaN."""
    import jax
    import jax.numpy as jnp

    from xrl_jax.evaluation import make_evaluate

    class NanAgent:
        def act(self, key, state, obs, mode="train"):
            return jnp.full((obs["state"].shape[0], 3), jnp.nan)

    with np.load(DATA) as data:
        pose = data["start_pose"]
        track = envs.track_from_arrays(data["track_centerline"], pose[:2], pose[2])
    env, params = envs.make("tracking", track=envs.stack_tracks([track, track]))
    episodes = jax.jit(make_evaluate(env, params, NanAgent(), 2))(jax.random.PRNGKey(0), None)
    np.savez(out, **episodes)


def _worker(what, out):
    if what == "project_point":
        return _worker_project(out)
    if what == "evaluate":
        return _worker_evaluate(out)
    env, params = _make(what)
    kinds = ("float", "int") if what.endswith("_discrete") else ("float",)
    results = {}
    for kind in kinds:  # one compiled step per action dtype
        result = _step_batch(env, params, _actions(what, kind))
        results.update({f"{kind}/{k}": np.asarray(v) for k, v in result.items()})
    np.savez(out, **results)


def _run(tmp_path_factory, what):
    """Run ``_worker(what)`` in a child process; fail (not hang) if it does not return in time."""
    out = tmp_path_factory.mktemp("nonfinite") / "out.npz"
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    try:
        done = subprocess.run(
            [sys.executable, __file__, what, str(out)],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"{what}: no result within {TIMEOUT_S} s (a while_loop that never ends?)")
    assert done.returncode == 0, f"{what} failed:\n{done.stderr[-4000:]}"
    with np.load(out) as data:
        return {k: data[k] for k in data.files}


# Every scenario and one discrete variant in the default tier; the other discrete variants are marked slow.
SLOW_ENVS = ("country_road_discrete", "intersection_discrete")


@pytest.fixture(
    scope="module",
    params=[pytest.param(env, marks=pytest.mark.slow if env in SLOW_ENVS else ()) for env in envs.ENV_NAMES],
)
def stepped(request, tmp_path_factory):
    """``(name, {kind: outputs})`` of one child process per env name."""
    out = _run(tmp_path_factory, request.param)
    kinds = {key.split("/")[0] for key in out}
    split = {kind: {k.split("/")[1]: v for k, v in out.items() if k.startswith(kind)} for kind in kinds}
    return request.param, split


def _expected_invalid(name, kind):
    if not name.endswith("_discrete"):
        return np.array(CONTINUOUS_INVALID)
    return np.array(DISCRETE_FLOAT_INVALID if kind == "float" else DISCRETE_INT_INVALID)


def test_invalid_actions_end_the_episode_with_their_own_reason(stepped):
    name, outputs = stepped
    assert set(outputs) == ({"float", "int"} if name.endswith("_discrete") else {"float"})
    for kind, out in outputs.items():
        _check_invalid_rows(name, kind, out)
    if not name.endswith("_discrete"):  # (a discrete index has no clipping: huge ones are invalid)
        out = outputs["float"]
        # Huge finite actions are clipped: rows 5/6 (±1e30) give exactly the outputs of rows 7/8 (±1).
        np.testing.assert_array_equal(out["flat"][5], out["flat"][7])
        np.testing.assert_array_equal(out["flat"][6], out["flat"][8])


def _check_invalid_rows(name, kind, out):
    invalid = _expected_invalid(name, kind)
    assert np.isfinite(out["flat"]).all(), "obs, state and info must stay finite"
    # The car drove on with the neutral control: every float output equals the neutral row's (same
    # operations on the same zeros, hence bit for bit).
    for row in np.flatnonzero(invalid):
        np.testing.assert_array_equal(out["flat"][row], out["flat"][-1])
    assert np.isfinite(out["reward"]).all()
    if name.startswith("intersection"):
        # Only slot 0 got the action under test; the padding slot 7's NaN is ignored.
        from envs.intersection import NONFINITE_ACTION

        np.testing.assert_array_equal(out["nonfinite_action"][:, 0], invalid)
        assert not out["nonfinite_action"][:, 1:].any()
        out = {k: v[:, 0] for k, v in out.items() if k != "flat"}
    else:
        from envs.racing import NONFINITE_ACTION

        np.testing.assert_array_equal(out["nonfinite_action"], invalid)
    assert NONFINITE_ACTION == 4
    assert out["terminated"][invalid].all() and not out["truncated"][invalid].any()
    np.testing.assert_array_equal(out["done_reason"][invalid], NONFINITE_ACTION)
    np.testing.assert_array_equal(out["reward"][invalid], -1.0)  # the off-track / off-road value
    assert (out["done_reason"][~invalid] != NONFINITE_ACTION).all()


def test_project_point_returns_for_non_finite_positions(tmp_path_factory):
    out = _run(tmp_path_factory, "project_point")
    far = slice(0, 7)  # NaN, inf and 1e30 coordinates (1e30 squared overflows float32)
    np.testing.assert_array_equal(out["distance"][far], np.inf)
    np.testing.assert_array_equal(out["s"][far], 0.0)
    assert np.isfinite(out["tangent"]).all()
    # Ordinary positions: the exact global answer of the brute force (same formula, same floats).
    np.testing.assert_array_equal(out["s"][7:], out["s_ref"])
    np.testing.assert_array_equal(out["distance"][7:], out["distance_ref"])


def test_evaluation_of_a_nan_policy_ends(tmp_path_factory):
    out = _run(tmp_path_factory, "evaluate")
    np.testing.assert_array_equal(out["length"], [1, 1])
    assert out["terminated"].all() and not out["truncated"].any()
    np.testing.assert_array_equal(out["return"], [-1.0, -1.0])


if __name__ == "__main__":
    _worker(sys.argv[1], sys.argv[2])


@pytest.mark.parametrize(
    "output, algo",
    [
        ("reward", "xdsac"),
        pytest.param("observation", "xdsac", marks=pytest.mark.slow),
        pytest.param("reward", "xdppo", marks=pytest.mark.slow),  # the on-policy chunk's own check
        pytest.param("observation", "xdppo", marks=pytest.mark.slow),
    ],
)
def test_an_env_returning_nan_is_named_not_the_learning_rates(tmp_path, output, algo):
    """Issue 48: an env whose step returns NaN was reported as a loss divergence with advice to lower
    the learning rates (the NaN reward reached the critic once warm-up ended). The chunk's health
    check sees the env's outputs: the run stops at the chunk where the env returned it, naming the
    seed, the step and the output. The check only reads them (training numbers: docs/training.md)."""
    import importlib.util

    import jax.numpy as jnp
    from train_support import prepare_cache

    import xrl_jax
    from xrl_jax.train import DivergenceError, resolve_config, train

    spec = importlib.util.spec_from_file_location(
        "nearest_goal_nan", ROOT / "docs" / "examples" / "nearest_goal.py"
    )
    example = sys.modules["nearest_goal_nan"] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)  # its dataclasses look their module up while it executes

    class NanGoal(example.NearestGoal):  # from its third step on, every step returns NaN
        def step_env(self, key, state, action, params):
            obs, state, reward, terminated, truncated, info = super().step_env(key, state, action, params)
            broken = state.time >= 3
            if output == "reward":
                reward = jnp.where(broken, jnp.nan, reward)
            else:
                obs = {**obs, "state": jnp.where(broken, jnp.nan, obs["state"])}
            return obs, state, reward, terminated, truncated, info

    def make():
        env = NanGoal()
        return env, env.default_params

    prepare_cache(tmp_path / "cache")
    name = f"nan_goal_{output}"
    xrl_jax.register_env(name, make, max_episode_steps=40)
    try:
        cfg = resolve_config(name, algo, "smoke", num_seeds=2)
        with pytest.raises(DivergenceError) as info:
            train(cfg, tmp_path / "run", progress=False, log=lambda *_: None)
    finally:
        xrl_jax.unregister_env(name)
        xrl_jax.unregister_env("nearest_goal")
    message = str(info.value)
    step = 3 * cfg.num_envs  # the end of the third vector step, the first with time >= 3
    assert f"seed 0: the env returned a non-finite {output} at step {step} (1 other too)" in message, message
    assert "fix the env's step" in message and "actor_lr" not in message and "\n" not in message
