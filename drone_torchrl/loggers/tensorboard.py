"""``logger=tensorboard`` (the default): buffered TensorBoard event files in the run folder.

The logger is :class:`~drone_torchrl.loggers.tb_logger.RunLogger`; the files go to
``<run>/<logger.exp_name>``.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from drone_torchrl.loggers import Backend, register
from drone_torchrl.loggers.tb_logger import RunLogger
from drone_torchrl.schema import TensorBoardConf, store_plugin


def make(cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> RunLogger:
    """The TensorBoard logger of the run in ``run_dir`` (``resumed_at``: the count it resumes from)."""
    # The checkpoint's own last update and evaluation were logged at its count: TensorBoard drops
    # events from count + 1 on, those the interrupted process logged after the checkpoint.
    purge = None if resumed_at is None else resumed_at + 1
    return RunLogger(cfg.logger.exp_name, run_dir, purge_step=purge)


# Its keys are the ones every backend has: drone_torchrl.schema.TensorBoardConf.
store_plugin("logger", "tensorboard", TensorBoardConf)

register(
    Backend(
        "tensorboard",
        make,
        resume_rule="events logged after the checkpoint are dropped (TensorBoard's purge_step), the rest kept",
        summary="TensorBoard event files in `<run>/tensorboard/`: scalars, evaluation videos, hparams (the default)",
    )
)
