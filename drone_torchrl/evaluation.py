"""Deterministic evaluation episodes and videos, shared by ``drone-train`` and ``drone-eval``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.metrics import episode_stats


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
def record_video(policy: Any, env_kwargs: dict[str, Any], seed: int, device: str = "cpu") -> np.ndarray:
    """Render one deterministic episode: ``uint8`` frames ``[T + 1, H, W, 3]`` (reset frame first)."""
    env = DroneEnv(batch_size=[], device=device, render_mode="rgb_array", **env_kwargs)
    env.set_seed(seed)
    frames = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        frames.append(env.render())
        env.rollout(
            env.max_steps,
            policy,
            tensordict=td,
            auto_reset=False,
            callback=lambda env_, _td: frames.append(env_.render()),
        )
    env.close()
    return np.stack(frames)


def save_gif(frames: np.ndarray, path: Path, fps: int) -> Path:
    """Write frames as an animated GIF (imageio's pillow plugin; duration in milliseconds)."""
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    return path
