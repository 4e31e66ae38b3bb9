"""Deterministic evaluation episodes and videos, shared by ``drone-train`` and ``drone-eval``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.metrics import episode_stats

VIDEO_DIR = "videos"


@torch.no_grad()
def evaluate(
    policy: Any, env_kwargs: dict[str, Any], episodes: int, seed: int, device: str = "cpu"
) -> tuple[dict[str, torch.Tensor], TensorDictBase]:
    """Fly ``episodes`` seeded episodes side by side with the policy's deterministic action.

    The same ``seed`` gives the same start states to every policy, so returns are comparable.
    Returns the per-episode stats (see :func:`~drone_torchrl.metrics.episode_stats`) and the rollout.
    """
    env = DroneEnv(batch_size=[episodes], device=device, **env_kwargs)
    env.set_seed(seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(env.max_steps, policy, break_when_all_done=True)
    env.close()
    return episode_stats(rollout), rollout


@torch.no_grad()
def record_video(
    policy: Any, env_kwargs: dict[str, Any], seed: int, device: str = "cpu", frame_stride: int = 1
) -> np.ndarray:
    """Render one deterministic episode: ``uint8`` frames ``[T, H, W, 3]``, the reset frame first,
    then every ``frame_stride``-th step (drawing is the slow part, so skipped steps are not drawn)."""
    env = DroneEnv(batch_size=[], device=device, render_mode="rgb_array", **env_kwargs)
    env.set_seed(seed)
    frames = []

    def draw(env_: DroneEnv, td: TensorDictBase) -> None:
        if int(td.get(("next", "step_count"), td.get("step_count"))) % frame_stride == 0:
            frames.append(env_.render())

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        frames.append(env.render())
        env.rollout(env.max_steps, policy, tensordict=td, auto_reset=False, callback=draw)
    env.close()
    return np.stack(frames)


def save_mp4(frames: np.ndarray, path: Path, fps: float) -> Path:
    """Write frames as an H.264 MP4 (imageio-ffmpeg; about 5x faster to write than a GIF)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), fps=fps, macro_block_size=1)
    return path


def write_eval_video(policy: Any, cfg: Any, run_dir: Path, step: int, logger: Any) -> Path:
    """One evaluation video of a training run: ``<run>/videos/episode_<step>.mp4`` and TensorBoard.

    ``logger.video_stride`` thins the frames (the playback rate is divided alike, so it stays real
    time) and, for TensorBoard only, the pixels: TensorBoard's GIF encoding is the slow part.
    """
    stride = cfg.logger.video_stride
    frames = record_video(policy, env_kwargs(cfg), cfg.eval.seed, cfg.device, frame_stride=stride)
    fps = cfg.logger.video_fps / stride
    path = save_mp4(frames, run_dir / VIDEO_DIR / f"episode_{step:06d}.mp4", fps)
    logger.log_frames("eval/video", frames[:, ::stride, ::stride], step=step, fps=fps)
    return path


def save_gif(frames: np.ndarray, path: Path, fps: int) -> Path:
    """Write frames as an animated GIF (imageio's pillow plugin; duration in milliseconds)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    return path
