"""pygame frames of both envs: shape, content, thrust arrows, tilt direction."""

import gymnasium as gym
import numpy as np
import pytest
import torch

import drone_torchrl  # noqa: F401  (registers Drone2D-v0)
from drone_torchrl.envs import DroneEnv
from drone_torchrl.envs import rendering as R

pytest.importorskip("pygame")


def _count(frame: np.ndarray, colour) -> int:
    return int((frame == np.array(colour, dtype=np.uint8)).all(-1).sum())


def _zone_pixels(frame: np.ndarray) -> int:
    """Pixels showing the translucent zone fill over the white domain (pygame rounds the blend)."""
    alpha = R.ZONE_ALPHA / 255
    blend = (1 - alpha) * np.array(R.DOMAIN_COLOUR) + alpha * np.array(R.ZONE_COLOUR)
    return int((np.abs(frame.astype(float) - blend) <= 2).all(-1).sum())


def _zone_area_px(params=None) -> float:
    p = params or DroneEnv().params
    left, top = R.Layout(p).to_pixel(-p.zone_x_limit, p.zone_z_max)
    right, bottom = R.Layout(p).to_pixel(p.zone_x_limit, p.zone_z_min)
    return (right - left) * (bottom - top)


def _frame(state, action, batch=None):
    env = DroneEnv(batch_size=batch, render_mode="rgb_array", reset_mode="air")
    env.reset()
    env._state = torch.tensor(state, dtype=torch.float32).expand_as(env._state).clone()
    env._last_action = torch.tensor(action, dtype=torch.float32).expand_as(env._last_action).clone()
    frame = env.render()
    env.close()
    return frame


def test_native_frame_shape_and_content():
    env = DroneEnv(render_mode="rgb_array")
    env.set_seed(0)
    env.reset()
    env.rollout(5, lambda td: td.set("action", torch.full((2,), 0.6)))
    frame = env.render()
    env.close()
    assert frame.shape == (R.FRAME_HEIGHT, R.FRAME_WIDTH, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 20  # grid, zone, text, drone: not blank
    assert _count(frame, R.MOTOR_LEFT_COLOUR) > 0 and _count(frame, R.MOTOR_RIGHT_COLOUR) > 0
    assert _zone_pixels(frame) > 0.5 * _zone_area_px()  # the drone is on the floor, the zone is clear


def test_the_frame_draws_the_envs_own_zone_and_domain():
    """A wider domain and a smaller, lower zone: the zone fill covers that zone's area in the frame
    scaled to the domain (not the paper's), and the default frame's is larger."""
    arena = {"x_limit": 3.0, "zone_x_limit": 0.4, "zone_z_min": 1.0, "zone_z_max": 1.5}
    env = DroneEnv(render_mode="rgb_array", **arena)
    env.set_seed(0)
    env.reset()
    frame = env.render()
    env.close()
    area, paper_area = _zone_area_px(env.params), _zone_area_px()
    assert area < 0.25 * paper_area
    assert 0.5 * area < _zone_pixels(frame) <= 1.05 * area
    left, _ = R.Layout(env.params).to_pixel(-3.0, 0.0)
    right, _ = R.Layout(env.params).to_pixel(3.0, 0.0)
    assert left >= R.MARGIN_LEFT and right <= R.FRAME_WIDTH - R.MARGIN_RIGHT  # the domain fits


def test_gym_frame():
    env = gym.make("Drone2D-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    env.close()
    assert frame.shape == (R.FRAME_HEIGHT, R.FRAME_WIDTH, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 20
    assert _zone_pixels(frame) > 0.5 * _zone_area_px()


@pytest.mark.filterwarnings("ignore::UserWarning:gymnasium.utils.env_checker")  # unbounded Box spaces (SPEC)
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_gym_env_checker_passes(render_mode):
    from gymnasium.utils.env_checker import check_env

    env = gym.make("Drone2D-v0", render_mode=render_mode).unwrapped
    check_env(env)  # calls render() in "rgb_array" mode
    env.close()


def test_human_mode_draws_headless_and_closes():
    renderer = R.DroneRenderer("human", DroneEnv().params, fps=1000)
    state = np.array([0.0, 0.0, 2.7, 0.0, 0.1, 0.0], np.float32)
    for step in range(2):
        assert renderer.draw(state, np.array([0.5, -0.2]), step, 10.0 * step, R.TerminationCause.NONE) is None
    renderer.close()
    renderer.close()  # a second close is harmless


def test_render_index_picks_the_sub_env():
    env = DroneEnv(batch_size=[2], render_mode="rgb_array", reset_mode="air")
    env.reset()
    env._state[1, 0] = 1.2  # sub-env 1 flies to the right
    left, right = env.render(0), env.render(1)
    env.close()
    assert not np.array_equal(left, right)


def test_negative_thrust_has_its_own_colour():
    hover = [0.0, 0.0, 2.7, 0.0, 0.0, 0.0]
    positive = _frame(hover, [0.8, 0.8])
    negative = _frame(hover, [-0.8, 0.8])
    assert _count(positive, R.THRUST_POSITIVE_COLOUR) > 0
    assert _count(positive, R.THRUST_NEGATIVE_COLOUR) == 0
    assert _count(negative, R.THRUST_NEGATIVE_COLOUR) > 0


def test_positive_alpha_raises_the_right_motor():
    """alpha is counter-clockwise from the vertical: with alpha > 0 the right motor is higher."""
    frame = _frame([0.0, 0.0, 2.0, 0.0, 0.4, 0.0], [0.0, 0.0])
    rows_left = np.nonzero((frame == np.array(R.MOTOR_LEFT_COLOUR, np.uint8)).all(-1))[0]
    rows_right = np.nonzero((frame == np.array(R.MOTOR_RIGHT_COLOUR, np.uint8)).all(-1))[0]
    assert rows_right.mean() < rows_left.mean()  # screen rows grow downwards


def test_render_without_mode_is_a_clear_error():
    with pytest.raises(ValueError, match="render_mode"):
        DroneEnv().render()


def test_a_gif_holds_every_frame_exactly_at_the_clip_s_rate(tmp_path):
    from PIL import Image, ImageSequence

    from drone_torchrl.io.video import gif_bytes, save_gif

    # Twelve frames of a drone flying fixed, uneven commands: fewer colours than a GIF palette holds,
    # so the palette must give back every pixel of every frame.
    env = DroneEnv(render_mode="rgb_array", reset_mode="air")
    env.set_seed(3)
    td = env.reset()
    frames = [env.render()]
    for i in range(11):
        td = env.step(td.set("action", torch.tensor([0.4 + 0.03 * i, 0.6])))["next"]
        frames.append(env.render())
    env.close()
    frames = np.stack(frames)
    assert all(not np.array_equal(a, b) for a, b in zip(frames[:-1], frames[1:], strict=True))  # it moves
    codes = (frames[..., 0].astype(np.int64) << 16) | (frames[..., 1].astype(np.int64) << 8) | frames[..., 2]
    assert len(np.unique(codes)) <= 256
    path = save_gif(frames, tmp_path / "clip.gif", fps=25)
    assert path.read_bytes() == gif_bytes(frames, 25)
    with Image.open(path) as gif:
        assert gif.info["loop"] == 0
        decoded = []
        for frame in ImageSequence.Iterator(gif):
            assert frame.info["duration"] == 40  # ms: 25 frames a second
            decoded.append(np.asarray(frame.convert("RGB")))
    assert len(decoded) == len(frames)
    for got, want in zip(decoded, frames, strict=True):
        np.testing.assert_array_equal(got, want)
