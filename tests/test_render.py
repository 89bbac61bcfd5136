"""Bird-view renderer: content, mirroring, overlays and video files (no env needed)."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from envs.render import Pose, render_frame, save_png, save_video

SIZE = {"width": 320, "height": 180}


@pytest.fixture(scope="module")
def oval():
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    centerline = np.stack([60 * np.cos(t), 40 * np.sin(t)], axis=-1)
    cones = np.concatenate([centerline * 1.07, centerline * 0.93])[::6]
    types = np.where(np.arange(len(cones)) < len(cones) // 2, 1, 2)
    return centerline, cones, types


def test_frame_has_road_cones_and_car(oval):
    centerline, cones, types = oval
    frame = render_frame(
        Pose(60.0, 0.0, np.pi / 2, speed=5.0), centerline, cones, types, width=640, height=360
    )
    assert frame.shape == (360, 640, 3) and frame.dtype == np.uint8
    colours = {tuple(c) for c in frame.reshape(-1, 3)}
    assert len(colours) > 10, "frame is blank"
    # Cones are a few pixels wide at this size and anti-aliased: look for their hues, not exact values.
    rgb = frame.astype(int)
    assert np.any(rgb[..., 2] - rgb[..., 0] > 100), "no blue cone drawn"
    assert np.any((rgb[..., 0] > 200) & (rgb[..., 1] > 160) & (rgb[..., 2] < 120)), "no yellow cone drawn"
    # The ego car (yellow-green body) sits at the horizontal centre, 80 % down the image.
    car_pixel = frame[int(0.8 * 360) + 8, 320].astype(int)
    assert abs(car_pixel[0] - 200) < 10 and abs(car_pixel[1] - 211) < 10


def test_mirrored_view_is_the_left_right_flip(oval):
    centerline, cones, types = oval
    pose = Pose(60.0, 0.0, np.pi / 2 + 0.2)
    plain = render_frame(pose, centerline, cones, types, hud=False, **SIZE)
    mirrored = render_frame(pose, centerline, cones, types, hud=False, mirrored=True, **SIZE)
    assert not np.array_equal(plain, mirrored)
    # Anti-aliasing differs by a pixel column at edges; the pictures agree almost everywhere.
    agree = np.mean(np.all(np.abs(plain[:, ::-1].astype(int) - mirrored.astype(int)) < 40, axis=-1))
    assert agree > 0.97


def test_overlay_receives_the_world_to_view_transform(oval):
    centerline, _, _ = oval
    seen = {}

    def overlay(ax, to_view):
        seen["ego"] = to_view(np.array([60.0, 0.0]))
        seen["ahead"] = to_view(np.array([60.0, 10.0]))
        ax.add_patch(
            __import__("matplotlib.patches").patches.Circle(tuple(seen["ahead"]), 3, color="magenta")
        )

    frame = render_frame(Pose(60.0, 0.0, np.pi / 2), centerline, overlay=overlay, **SIZE)
    np.testing.assert_allclose(seen["ego"], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(seen["ahead"], [0.0, 10.0], atol=1e-12)  # heading points up the screen
    magenta = np.all(frame.astype(int) == [255, 0, 255], axis=-1)
    assert magenta.sum() > 20


def test_png_and_gif_files(tmp_path, oval):
    centerline, cones, types = oval
    frames = [
        render_frame(Pose(60.0, 2.0 * k, np.pi / 2, speed=k), centerline, cones, types, **SIZE)
        for k in range(3)
    ]
    png = save_png(frames[0], tmp_path / "frame.png")
    np.testing.assert_array_equal(np.asarray(Image.open(png).convert("RGB")), frames[0])
    gif = save_video(frames, tmp_path / "episode.gif")
    with Image.open(gif) as image:
        assert image.n_frames == 3


def test_bad_video_requests_fail_clearly(tmp_path):
    frame = np.zeros((16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        save_video([frame], tmp_path / "x.avi")
    with pytest.raises(ValueError, match="at least one frame"):
        save_video([], tmp_path / "x.gif")
    with pytest.raises(ValueError, match="at least 16x16"):
        render_frame(Pose(0.0, 0.0, 0.0), width=8, height=8)


def test_renders_a_country_road_episode_from_env_states(tmp_path):
    import jax

    import envs
    from envs.actions import continuous_to_control
    from envs.render import render_racing_episode, render_racing_state

    with np.load(Path(__file__).parent / "data" / "episode_country_road_public.npz") as data:
        pose = data["start_pose"]
        track = envs.track_from_arrays(
            data["track_centerline"], pose[:2], pose[2], data["cone_pos"], data["cone_type"]
        )
        actions = np.asarray(data["actions_raw"][:40], np.float32)
    env, params = envs.make("country_road", track=track)
    _, state = env.reset(jax.random.PRNGKey(0), params)

    def body(state, action):
        state = env.step(jax.random.PRNGKey(0), state, action, params)[1]
        return state, state

    _, states = jax.jit(lambda s, a: jax.lax.scan(body, s, a))(state, actions)
    first = render_racing_state(state, params, **SIZE)
    assert len({tuple(c) for c in first.reshape(-1, 3)}) > 10
    controls = np.asarray(jax.vmap(continuous_to_control)(actions))
    frames = render_racing_episode(jax.tree.map(lambda x: x[::13], states), params, controls[::13], **SIZE)
    assert len(frames) == 4 and all(f.shape == (180, 320, 3) for f in frames)
    assert not np.array_equal(frames[0], frames[-1])  # the car moved
    save_video(frames, tmp_path / "episode.gif")
