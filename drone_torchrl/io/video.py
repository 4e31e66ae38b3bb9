"""Rendered episodes: frames from ``DroneEnv``'s pygame renderer, saved as MP4 or GIF."""

from __future__ import annotations

import errno
import io
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.io.storage import folder_refuses, write_atomically, writing

VIDEO_DIR = "videos"


@torch.no_grad()
def record_video(
    policy: Any, env_kwargs: dict[str, Any], seed: int, device: str = "cpu", frame_stride: int = 1
) -> np.ndarray:
    """Render one deterministic episode as ``uint8`` frames ``[T, H, W, 3]``, the reset frame first.

    After the reset frame comes every ``frame_stride``-th step (drawing is the slow part, so
    skipped steps are not drawn).

    The episode starts where the first episode of :func:`drone_torchrl.evaluation.evaluate` with the
    same ``seed`` starts.
    """
    env = DroneEnv(batch_size=[], device=device, render_mode="rgb_array", **env_kwargs)
    env.set_seed(seed)
    count = 1

    def draw(env_: DroneEnv, td: TensorDictBase) -> None:
        nonlocal count
        if int(td.get(("next", "step_count"), td.get("step_count"))) % frame_stride == 0:
            frames[count] = env_.render()
            count += 1

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        first = env.render()
        # Each frame is copied once into one array sized for the longest episode (a list stacked at the
        # end holds every frame twice: a training video is 160 MB, and its page faults cost seconds here).
        frames = np.empty((env.max_steps // frame_stride + 1, *first.shape), dtype=first.dtype)
        frames[0] = first
        env.rollout(env.max_steps, policy, tensordict=td, auto_reset=False, callback=draw)
    env.close()
    return frames[:count]


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


# Frames sampled across a clip to choose its GIF palette when it has more colours than a GIF holds.
PALETTE_SAMPLE_FRAMES = 8
GIF_COLOURS = 256
_RGB_CODES = 1 << 24


def _rgb_codes(frame: np.ndarray) -> np.ndarray:
    """Each pixel's colour as one integer ``0xRRGGBB``."""
    frame = frame.astype(np.uint32)
    return (frame[..., 0] << 16) | (frame[..., 1] << 8) | frame[..., 2]


def _palette_images(frames: np.ndarray) -> list:
    """The frames as palette images with one palette for the whole clip.

    Exactly their colours if there are at most 256 (the renderer draws fewer: 214 in a training video), else a
    median cut of a sample of frames. A fixed palette costs a lookup per pixel; choosing one per frame, as
    moviepy (TensorBoard's ``add_video``) does, took about ten times as long for a training video.
    """
    from PIL import Image

    seen = np.zeros(_RGB_CODES, dtype=bool)
    for frame in frames:
        seen[_rgb_codes(frame)] = True
    colours = np.flatnonzero(seen)
    if len(colours) > GIF_COLOURS:
        picks = np.linspace(0, len(frames) - 1, min(len(frames), PALETTE_SAMPLE_FRAMES)).astype(int)
        sample = Image.fromarray(np.concatenate([frames[i] for i in picks], axis=0))
        palette = sample.quantize(colors=GIF_COLOURS, method=Image.Quantize.MEDIANCUT)
        return [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    index = np.zeros(_RGB_CODES, dtype=np.uint8)
    index[colours] = np.arange(len(colours))
    rgb = np.stack([colours >> 16, (colours >> 8) & 0xFF, colours & 0xFF], axis=-1).astype(np.uint8)
    images = []
    for frame in frames:
        image = Image.fromarray(index[_rgb_codes(frame)], mode="P")
        image.putpalette(rgb.tobytes())
        images.append(image)
    return images


def gif_bytes(frames: np.ndarray, fps: float) -> bytes:
    """Encode ``[T, H, W, 3]`` uint8 frames as a looping animated GIF at ``fps``.

    Pillow encodes it, with one palette for the whole clip.
    """
    images = _palette_images(frames)
    out = io.BytesIO()
    images[0].save(out, format="GIF", save_all=True, append_images=images[1:], duration=1000.0 / fps, loop=0)
    return out.getvalue()


def save_gif(frames: np.ndarray, path: Path, fps: float) -> Path:
    """Write frames as an animated GIF (:func:`gif_bytes`), atomically."""
    return write_atomically(path, gif_bytes(frames, fps))
