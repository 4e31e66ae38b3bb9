"""TensorBoard through TorchRL's logger, with the two things it lacks here: resume and hparams."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import TensorboardLogger

from drone_torchrl.envs.dynamics import TerminationCause


class RunLogger(TensorboardLogger):
    """``TensorboardLogger`` writing into ``<run>/<exp_name>``.

    ``purge_step``: on resume, TensorBoard drops the events logged at or after this step by the
    interrupted process, so the curves do not fold back on themselves. TorchRL's logger does not
    expose it, hence this subclass.
    """

    def __init__(self, exp_name: str, log_dir: str | Path, purge_step: int | None = None) -> None:
        self._purge_step = purge_step
        super().__init__(exp_name=exp_name, log_dir=str(log_dir))
        self._video_ok = True

    def _create_experiment(self):
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(log_dir=str(Path(self.log_dir) / self.exp_name), purge_step=self._purge_step)

    def log_frames(self, name: str, frames: np.ndarray, step: int, fps: float) -> None:
        """Log ``[T, H, W, 3]`` uint8 frames as a TensorBoard video (needs ``moviepy<2``)."""
        if not self._video_ok:
            return
        video = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).unsqueeze(0)
        # moviepy 1.x imports pygame, which opens an audio device unless told not to.
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
        try:
            import moviepy.editor  # noqa: F401  (torch's add_video needs the 1.x module)
        except ImportError:
            warnings.warn(
                "TensorBoard videos need moviepy<2 (pip install 'moviepy<2'); GIFs are still written",
                stacklevel=2,
            )
            self._video_ok = False
            return
        self.log_video(name, video, step=step, fps=fps)

    def log_final_hparams(self, cfg: DictConfig, metrics: dict[str, float]) -> None:
        """Flattened config + final metrics, so TensorBoard's HPARAMS tab compares the runs of a sweep."""
        self.experiment.add_hparams(
            flatten_config(cfg), {f"hparam/{k}": v for k, v in metrics.items()}, run_name="."
        )
        self.experiment.flush()


EPISODE_SCALARS = ("return", "length", "time_in_zone", "negative_thrust_fraction")


def log_update(
    logger: RunLogger, rows: list[dict[str, Any]], train_metrics: dict[str, float], step: int
) -> None:
    """One update's TensorBoard scalars: each episode's metrics (x axis: its episode index), the
    number of episodes that ended with each termination cause, and the update's training metrics."""
    for row in rows:
        logger.log_metrics({f"episode/{k}": row[k] for k in EPISODE_SCALARS}, step=row["episode"])
    for cause in TerminationCause:
        count = sum(1 for row in rows if row["termination_cause"] == cause.name)
        logger.log_scalar(f"episode/termination_cause/{cause.name}", count, step=step)
    logger.log_metrics(train_metrics, step=step)


def flatten_config(cfg: DictConfig | dict) -> dict[str, Any]:
    """``{"algo.lr": 1e-4, ...}`` with values TensorBoard accepts (lists and None as strings)."""
    container = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(f"{prefix}.{key}" if prefix else str(key), value)
        elif isinstance(node, bool | int | float | str):
            flat[prefix] = node
        else:
            flat[prefix] = str(node)

    walk("", container)
    return flat
