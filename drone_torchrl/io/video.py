"""Rendered episodes: frames from ``DroneEnv``'s pygame renderer, saved as MP4 or GIF."""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.io.storage import folder_refuses, writing

VIDEO_DIR = "videos"


@torch.no_grad()
def record_video(
    policy: Any, env_kwargs: dict[str, Any], seed: int, device: str = "cpu", frame_stride: int = 1
) -> np.ndarray:
    """Render one deterministic episode: ``uint8`` frames ``[T, H, W, 3]``, the reset frame first,
    then every ``frame_stride``-th step (drawing is the slow part, so skipped steps are not drawn).

    The episode starts where the first episode of :func:`drone_torchrl.evaluation.evaluate` with the
    same ``seed`` starts."""
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

    part = path.with_name(path.stem + ".part" + path.suffix)  # ffmpeg picks the container by suffix
    with writing(path, part):
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            # ffmpeg quiet: a refused write reaches Python as a broken pipe, diagnosed below in one line.
            imageio.mimsave(part, list(frames), fps=fps, macro_block_size=1, ffmpeg_log_level="quiet")
        except OSError as err:
            raise OSError(folder_refuses(part.parent, frames.nbytes) or err.errno, str(err)) from None
        # ffmpeg may also end "successfully" with a file it could not write (empty, or cut short
        # where the disk filled up): a full or read-only folder after the write means that.
        refused = folder_refuses(part.parent, 1)
        if refused is not None or part.stat().st_size == 0:
            raise OSError(refused or errno.EIO, f"ffmpeg could not write {part}")
        os.replace(part, path)
    return path


def save_gif(frames: np.ndarray, path: Path, fps: int) -> Path:
    """Write frames as an animated GIF (imageio's pillow plugin; duration in milliseconds)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    return path
