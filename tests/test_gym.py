"""Gymnasium adaptors: env checker, numpy I/O, action validation, vector env auto-reset."""

from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs.gym import GymEnv, GymVectorEnv

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def track():
    with np.load(DATA / "episode_country_road_public.npz") as data:
        pose = data["start_pose"]
        return envs.track_from_arrays(
            data["track_centerline"], pose[:2], pose[2], data["cone_pos"], data["cone_type"]
        )


@pytest.mark.filterwarnings("ignore:.*infinity")
@pytest.mark.parametrize("name", ["tracking", "country_road_discrete"])
def test_check_env_passes(name, track):
    env = GymEnv(name, track=track)
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert info == {} and all(v.dtype == np.float32 for v in obs.values())
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    assert env.observation_space.contains(obs)
    assert int(info["done_reason"]) == 0 and info["avg_track_velocity"].shape == ()


def test_single_env_rejects_bad_actions(track):
    env = GymEnv("country_road", track=track)
    env.reset(seed=0)
    for bad in ([0.0, 1.5, 0.0], [0.0, np.nan, 0.0], [0.0, 0.0], "fast"):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    discrete = GymEnv(envs.CountryRoad(discrete=True), params=env.params)
    discrete.reset(seed=0)
    for bad in (12, -1, 2.0, [1, 2]):
        with pytest.raises(ValueError, match="action"):
            discrete.step(bad)
    with pytest.raises(ValueError, match="params"):
        GymEnv(envs.CountryRoad())


def test_vector_env_steps_and_auto_resets(track):
    vec = GymVectorEnv("tracking", num_envs=3, track=track, max_steps=2)
    obs, _ = vec.reset(seed=1)
    assert obs["trajectory_set"].shape == (3, 25, 4) and obs["state"].shape == (3, 6)
    actions = np.tile(np.array([0.0, 1.0, -1.0], np.float32), (3, 1))
    _, reward, terminated, truncated, info = vec.step(actions)
    assert reward.shape == (3,) and not (terminated | truncated).any() and not info["_final_obs"].any()
    obs2, reward, terminated, truncated, info = vec.step(actions)
    assert truncated.all() and not terminated.any() and info["_final_obs"].all()
    np.testing.assert_array_equal(obs2["state"], 0.0)  # first observation of the next episode
    assert (info["final_obs"]["state"][:, 0] > 0).all()  # the cars were moving when it ended
    assert np.all(info["done_reason"] == envs.MAX_TIME)
    with pytest.raises(ValueError, match="action"):
        vec.step(np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match="action"):
        vec.step(np.full((3, 3), 2.0, np.float32))
