"""Gymnasium adaptors: env checker, numpy I/O, action validation, vector env auto-reset."""

from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs.gym import GymEnv, GymVectorEnv, ResetNeeded

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


def test_masked_actions_are_rejected(track):
    """np.asarray of a masked array keeps the masked entries' values: the env would act on them."""
    env = GymEnv("country_road", track=track)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="masked array"):
        env.step(np.ma.masked_array([0.0, 0.9, 0.0], mask=[False, True, False]))
    vec = GymVectorEnv("country_road", num_envs=2, track=track)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="masked array"):
        vec.step(np.ma.masked_array(np.zeros((2, 3)), mask=np.eye(2, 3, dtype=bool)))


def test_a_multi_agent_env_is_refused_in_one_line():
    """The Intersection's observations carry 8 agent slots that the per-agent Gymnasium spaces lack:
    the adaptor took it and failed at the first step, or returned observations outside its space."""
    for adaptor in (GymEnv, GymVectorEnv):
        with pytest.raises(ValueError, match="single-agent envs; Intersection is multi-agent") as error:
            adaptor("intersection")
        assert "\n" not in str(error.value)


def test_complex_actions_are_rejected(track):
    # The cast to float32 would drop the imaginary part with only a ComplexWarning.
    env = GymEnv("country_road", track=track)
    env.reset(seed=0)
    for bad in (np.array([0.0, 0.5 + 0.1j, 0.0]), np.zeros(3, np.complex64), [0j, 1 + 0j, 0j]):
        with pytest.raises(ValueError, match="real"):
            env.step(bad)
    discrete = GymEnv(envs.CountryRoad(discrete=True), params=env.params)
    discrete.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        discrete.step(np.complex64(3))
    vec = GymVectorEnv("country_road", num_envs=2, track=track)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="real"):
        vec.step(np.zeros((2, 3), np.complex128))


@pytest.mark.parametrize(
    ("overrides", "action", "ended"),
    [
        ({"max_steps": 1}, [0.0, -1.0, -1.0], "truncated"),
        ({"track_width": 0.0}, [1.0, 1.0, -1.0], "terminated"),  # any distance > 0 leaves the track
    ],
)
def test_stepping_an_ended_episode_needs_reset(track, overrides, action, ended):
    env = GymEnv("tracking", track=track, **overrides)
    with pytest.raises(ResetNeeded, match="reset"):
        env.step(action)
    env.reset(seed=0)
    *_, terminated, truncated, _ = env.step(action)
    assert {"terminated": terminated, "truncated": truncated}[ended]
    for error in (ResetNeeded, gymnasium.error.ResetNeeded, RuntimeError):  # Gymnasium's, and as before
        with pytest.raises(error, match="call reset"):
            env.step(action)
    env.reset()
    env.step(action)  # a new episode steps again


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
    # The vector env needs no reset after an ending: the rows already run their next episode.
    _, _, terminated, truncated, info = vec.step(actions)
    assert not (terminated | truncated).any() and not info["_final_obs"].any()
    _, _, terminated, truncated, info = vec.step(actions)
    assert truncated.all() and info["_final_obs"].all()


def test_vector_env_needs_a_first_reset(track):
    vec = GymVectorEnv("tracking", num_envs=2, track=track)
    with pytest.raises(ResetNeeded, match="reset"):
        vec.step(np.zeros((2, 3), np.float32))
