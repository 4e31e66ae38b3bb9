"""``logger=wandb``: each run is a Weights & Biases run (the ``wandb`` extra: ``pip install ".[wandb]"``).

Where: ``logger.project`` (and ``logger.entity``, W&B's default when null), one W&B group per sweep
(``logger.group``, by default the ``sweep_name``), the run named after its folder. ``logger.mode``
is W&B's: ``online``, ``offline`` (files only, in ``<run>/<logger.exp_name>/wandb/``; upload them
later with ``wandb sync``) or ``disabled``; null leaves it to W&B's own settings (``WANDB_MODE``,
``wandb offline``). An online run needs W&B credentials (``wandb login`` or ``WANDB_API_KEY``): a
config without them is refused before any work, as is a W&B that is not installed.

What is logged: every scalar at its step, the resolved config as the run's config, each evaluation
video as a GIF, the final metrics in the run's summary as ``hparam/*``, and how the run ended
(``finish``: exit code 0 when it finished, 1 when it failed; a run stopped by a signal is marked
preempting first, so W&B shows it as resumable rather than failed).

Steps: every value is logged on an ``episodes`` axis (the count of episodes done, declared as the
step metric of every other key), and W&B's own step is that same count, so it only ever grows,
across resumes and offline files synced later.

Resume: the same W&B run continues (its id is kept in ``<run>/<logger.exp_name>/run_id``), and no
step is sent twice: the last step sent is kept beside the id (``sent_through``, rewritten after
every flush), and a continued run skips the steps up to it, those the interrupted process logged
after its checkpoint. REINFORCE retrains those steps exactly, so the skipped values are the ones
it would send; PPO and A2C restart their drones' episodes, so there the values kept are the
interrupted process's (as with ``logger=mlflow``). A process killed between a flush's send and its
record (SIGKILL; SIGTERM checkpoints first) sends that flush's steps again. A run that restarts
from scratch (its folder holds no checkpoint) is a new W&B run.

Several runs of one process (a population, a sweep under ``hydra/launcher=fused``) are W&B runs
side by side (``reinit="create_new"``); each holds a stream to W&B's service process, so keep
``logger=wandb`` to populations of tens of runs, not thousands.
"""

from __future__ import annotations

import contextlib
import os
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drone_torchrl.checks import ConfigError
from drone_torchrl.io.storage import write_atomically, writing
from drone_torchrl.io.video import save_gif
from drone_torchrl.loggers import FAILED, FINISHED, Backend, Logger, RunStatus, register
from drone_torchrl.schema import IF_SET, TensorBoardConf, a_text, one_of, store_plugin
from drone_torchrl.sweep_folder import group_name

RUN_ID_FILE = "run_id"
SENT_FILE = "sent_through"
# The x-axis of every chart: the count of episodes done (also W&B's own step).
STEP_METRIC = "episodes"
MODES = ("online", "offline", "disabled")
# W&B's own rules for project and entity names: at most 128 characters, none of these.
MAX_NAME_CHARS = 128
FORBIDDEN_CHARS = "/\\#?%:"


class WandbLogger(Logger):
    """One drone_torchrl run as one W&B run, buffered.

    Args:
        cfg: the run's config (``logger.*`` and the config W&B records).
        run_dir: the run folder (the W&B run's name; its files go in ``<run_dir>/<logger.exp_name>``).
        resumed_at: on resume, the W&B run is continued and the steps it has already are skipped.
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> None:
        import wandb

        run_dir = Path(run_dir)
        self.folder = folder = run_dir / cfg.logger.exp_name
        id_file, self._sent_file = folder / RUN_ID_FILE, folder / SENT_FILE
        resuming = resumed_at is not None and id_file.is_file()
        run_id = id_file.read_text().strip() if resuming else None  # None: W&B names a new run
        self._sent = 0  # steps up to this one are in W&B already (sent by the interrupted process)
        if resuming:
            with contextlib.suppress(OSError, ValueError):  # absent or torn: nothing known to be sent
                self._sent = int(self._sent_file.read_text().strip())
        with writing(folder):
            folder.mkdir(parents=True, exist_ok=True)
        self.run = wandb.init(
            project=cfg.logger.project,
            entity=cfg.logger.entity,
            group=cfg.logger.group or group_name(cfg.sweep_name, run_dir),
            name=run_dir.name,
            id=run_id,
            resume="allow",
            dir=str(folder),
            mode=cfg.logger.mode,
            config=OmegaConf.to_container(cfg, resolve=True),
            settings=wandb.Settings(reinit="create_new", console="off"),
        )
        if not resuming:
            write_atomically(self._sent_file, f"{self._sent}\n".encode())
            write_atomically(id_file, f"{self.run.id}\n".encode())
        self.run.define_metric(STEP_METRIC)
        self.run.define_metric("*", step_metric=STEP_METRIC)
        self._steps: dict[int, dict[str, Any]] = defaultdict(dict)
        self._media: list[Path] = []  # GIFs handed to W&B, removed once it has its copy

    def log_scalars(self, scalars: Iterable[tuple[str, float, int]]) -> None:
        """Buffer ``(tag, value, step)`` triples, grouped by step."""
        steps = self._steps
        for tag, value, step in scalars:
            steps[int(step)][tag] = float(value)

    def log_frames(self, name: str, frames: np.ndarray, step: int, fps: float) -> None:
        """Log ``[T, H, W, 3]`` uint8 frames as a W&B video (an animated GIF at ``fps``)."""
        import wandb

        # wandb.Video encodes arrays with moviepy, which the package does not need: hand it a GIF,
        # which W&B copies into its run files when logged (then this one is removed).
        path = save_gif(frames, self.folder / f"{name.replace('/', '_')}_{step:06d}.gif", fps)
        self._steps[int(step)][name] = wandb.Video(str(path), format="gif")
        self._media.append(path)

    def log_final_hparams(self, cfg: DictConfig | dict, metrics: dict[str, float]) -> None:
        # The config is the run's already; the final metrics go where W&B keeps a run's last word.
        """Put the final ``metrics`` (as ``hparam/*``) in the W&B run's summary."""
        self.run.summary.update({f"hparam/{k}": v for k, v in metrics.items()})

    def flush(self) -> None:
        """Send the buffered steps W&B has not had yet, in step order."""
        if not self._steps:
            return
        sent = self._sent
        for step in sorted(self._steps):
            if step > sent:  # a continued run's steps the interrupted process sent already are skipped
                self.run.log({STEP_METRIC: step, **self._steps[step]}, step=step)
        self._sent = max(sent, max(self._steps))
        self._steps.clear()
        for path in self._media:
            path.unlink(missing_ok=True)
        self._media.clear()
        if self._sent != sent:
            write_atomically(self._sent_file, f"{self._sent}\n".encode())

    def close(self, status: RunStatus) -> None:
        """Flush and finish the W&B run (marked preempting when stopped, exit code 1 when failed)."""
        self.flush()
        if status not in (FINISHED, FAILED):
            self.run.mark_preempting()
        self.run.finish(exit_code=1 if status == FAILED else 0)


def validate(cfg: Mapping[str, Any]) -> None:
    """Check names W&B accepts, and credentials for an online run, before any work.

    W&B is installed by then: :func:`drone_torchrl.loggers.check_backend` checks the extra first.
    """
    logger = cfg.logger
    for key, optional in (("project", False), ("entity", True), ("group", True)):
        value = logger[key]
        if (value is not None or not optional) and (
            not isinstance(value, str)
            or not value.strip()
            or len(value) > MAX_NAME_CHARS
            or any(c in value for c in FORBIDDEN_CHARS)
        ):
            expected = f"a W&B name of 1 to {MAX_NAME_CHARS} characters without any of {FORBIDDEN_CHARS!r}"
            raise ConfigError.of(f"logger.{key}", value, f"null or {expected}" if optional else expected)
    mode = logger.mode
    if mode is None:
        mode = os.environ.get("WANDB_MODE", "online")
        # W&B refuses any other value with a long validation error when the run starts.
        if mode not in (*MODES, "dryrun", "run"):
            raise ConfigError.of("WANDB_MODE", mode, f"one of {list(MODES)} (W&B's environment variable)")
    if mode in ("online", "run"):
        import wandb

        if not wandb.login(prompt=False, verify=False):
            raise ConfigError(
                "logger=wandb in online mode needs W&B credentials: run `wandb login` or set WANDB_API_KEY, "
                "or use logger.mode=offline (and `wandb sync` later)"
            )


@dataclass
class WandbConf(TensorBoardConf):
    """``logger.*`` of ``logger.backend=wandb`` (names and credentials checked by this module's ``validate``)."""

    # A W&B run id lives in one project and entity: a continued run keeps them (and its run).
    project: Any = a_text()
    entity: Any = a_text(optional=True)
    group: Any = a_text(optional=True, on_resume=IF_SET)
    mode: Any = one_of(MODES, optional=True, on_resume=IF_SET)


store_plugin("logger", "wandb", WandbConf)

register(
    Backend(
        "wandb",
        WandbLogger,
        resume_rule="continues the same W&B run and sends no step twice (those sent after the checkpoint are skipped)",
        validate=validate,
        summary="a Weights & Biases run per run, online or offline: config, scalars, videos, final metrics",
        extra="wandb",
    )
)
