"""Loggers as plug-ins: where a run's scalars, final hyper-parameters and videos go (``logger=...``).

The run record (:class:`~drone_torchrl.training.run.RunRecord`) logs through the :class:`Logger`
interface only; ``logger.backend`` (set by each ``conf/logger/<option>.yaml``) picks the
:class:`Backend` that makes one per run. Built in:

- ``logger=tensorboard`` (the default): TensorBoard event files, buffered (:mod:`.tb_logger`).
- ``logger=csv``: one long-format CSV of scalars per run (:mod:`.csvfile`).
- ``logger=mlflow``: an MLflow run per run (:mod:`.mlflow_store`, the ``mlflow`` extra).
- ``logger=wandb``: a Weights & Biases run per run (:mod:`.wandb_run`, the ``wandb`` extra).

Every backend buffers: values are kept in memory between flushes (at every checkpoint, evaluation
and every ``logger.flush_every_s`` seconds) and no file is held open in between, so a population of
1,024 runs holds no files open while it trains.

Resume: every step is a count of episodes done. When a run continues from a checkpoint at count
``E``, the backend is told ``E`` and applies its resume rule (each backend's ``resume_rule`` says
which): the file backends drop what the interrupted process logged after ``E`` and keep the rest.
The backend of a run cannot change when it continues (one line refuses it).

Adding one: a module here (or in another package, named in the ``drone_torchrl.loggers`` entry-point
group) that calls :func:`register`, its keys' schema (a subclass of
:class:`drone_torchrl.schema.TensorBoardConf`, stored with :func:`drone_torchrl.schema.store_plugin`),
and ``conf/logger/<option>.yaml`` with ``defaults: [tensorboard, /schema_logger_<name>@_here_]``
(the shared keys, then its schema), ``backend: <name>`` and its own keys; then
``drone-train logger=<option>``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
from omegaconf import DictConfig, OmegaConf

from drone_torchrl import extras
from drone_torchrl.checks import ConfigError
from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.registry import Registry

# How a run's logging ended (what :meth:`Logger.close` is told): it trained its whole budget; it
# failed (diverged, or an error stopped it); or it stopped to be continued (a signal, Ctrl-C).
RunStatus = Literal["finished", "failed", "stopped"]
FINISHED: RunStatus = "finished"
FAILED: RunStatus = "failed"
STOPPED: RunStatus = "stopped"


class Logger(Protocol):
    """What the run record calls. Steps are counts of episodes done; values are buffered until :meth:`flush`.

    A backend that subclasses it inherits :meth:`log_scalars` (into its ``scalars`` list),
    :meth:`log_metrics`, :meth:`log_frames` and :meth:`close`.
    """

    scalars: list[tuple[str, float, int]]  # what log_scalars buffered, for flush; the backend makes it

    def log_scalars(self, scalars: Iterable[tuple[str, float, int]]) -> None:
        """``(tag, value, step)`` triples, as many as come (kept in ``scalars`` until :meth:`flush`)."""
        self.scalars.extend(scalars)

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        """``{tag: value}`` at one step (as :meth:`log_scalars` triples)."""
        self.log_scalars((tag, value, step) for tag, value in metrics.items())

    def log_frames(self, name: str, frames: np.ndarray, step: int, fps: float) -> None:
        """Log ``[T, H, W, 3]`` uint8 frames of an evaluation video (skipped here).

        A backend may skip them because the run folder always has the MP4.
        """

    def log_final_hparams(self, cfg: DictConfig | dict, metrics: dict[str, float]) -> None:
        """The flattened config with the run's final metrics, once, when it finishes."""

    def flush(self) -> None:
        """Write what is buffered (files are opened only for this)."""

    def close(self, status: RunStatus = FINISHED) -> None:
        """Flush and finish: the run logs nothing more in this process.

        Called once, also when the run failed or was stopped; ``status`` says which, for a backend that
        records it (here: none is held open, so flushing is all).
        """
        self.flush()


@dataclass(frozen=True)
class Backend:
    """One logger backend.

    Attributes:
        name: its ``logger.backend``.
        make: ``make(cfg, run_dir, resumed_at)`` -> the run's :class:`Logger`; ``resumed_at`` is the
            checkpoint's count of episodes when the run continues (None for a new run).
        resume_rule: one line saying what happens to values logged after the checkpoint.
        validate: checks of its own ``logger.*`` keys that its schema's bounds and choices do not
            cover (one-line ``ConfigError``).
        summary: one line saying what it writes where.
        extra: the package extra it needs (``pip install "drone_torchrl[<extra>]"``), named as the
            module it imports, or None; without it a config is refused before any work
            (:func:`check_backend`), naming the extra.
    """

    name: str
    make: Callable[[DictConfig, Path, int | None], Logger]
    resume_rule: str
    validate: Callable[[Mapping[str, Any]], None] = lambda cfg: None
    summary: str = ""
    extra: str | None = None

    @property
    def needs(self) -> extras.Needs | None:
        """What it needs installed (:mod:`drone_torchrl.extras`): the module its :attr:`extra` installs."""
        return None if self.extra is None else extras.Needs(self.extra, self.extra)

    @property
    def installed(self) -> bool:
        """Whether the module its :attr:`extra` installs can be imported."""
        return self.needs is None or self.needs.installed


BACKENDS: Registry[Backend] = Registry("logger.backend", __name__, "drone_torchrl.loggers")


def register(backend: Backend) -> Backend:
    """Add ``backend`` (its module calls this when imported)."""
    return BACKENDS.register(backend.name, backend)


#: The backend named ``name``; a one-line :class:`~drone_torchrl.checks.ConfigError` otherwise.
get = BACKENDS.get


def check_backend(cfg: Mapping[str, Any]) -> None:
    """Refuse, in one line, a backend whose extra is not installed, then run its own checks.

    The backend's own checks may import it.
    """
    backend = get(cfg.logger.backend)
    if not backend.installed:
        raise ConfigError(extras.missing(f"logger={backend.name}", backend.needs))
    backend.validate(cfg)


def make_logger(cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> Logger:
    """The run's logger, from ``cfg.logger.backend``."""
    return get(cfg.logger.backend).make(cfg, Path(run_dir), resumed_at)


def flatten_config(cfg: DictConfig | dict, prefix: str = "") -> dict[str, Any]:
    """``{"algo.lr": 1e-4, ...}`` with values every backend accepts (lists and None as strings)."""
    container = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    flat: dict[str, Any] = {}
    for key, value in container.items():
        if isinstance(value, dict):
            flat.update(flatten_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value if isinstance(value, bool | int | float | str) else str(value)
    return flat


EPISODE_SCALARS = ("return", "length", "time_in_zone", "negative_thrust_fraction")
# Tags made once: log_update runs per agent per update.
_EPISODE_TAGS = tuple((k, f"episode/{k}") for k in EPISODE_SCALARS)
_CAUSE_TAGS = tuple((cause.name, f"episode/termination_cause/{cause.name}") for cause in TerminationCause)


def log_update(
    logger: Logger, rows: list[dict[str, Any]], train_metrics: dict[str, float], step: int
) -> None:
    """Log one update's scalars: each episode's metrics, the termination causes and training metrics.

    The causes are the number of episodes that ended with each. Every step is a count of episodes
    done: an episode's own metrics at its number counted from 1 (the CSV's ``episode`` + 1), the
    update's at ``step``, the count after its last episode; so a resume from a checkpoint at count
    ``E`` purges from ``E + 1`` and keeps everything the checkpoint includes.
    """
    for row in rows:
        count = row["episode"] + 1
        logger.log_scalars((tag, row[k], count) for k, tag in _EPISODE_TAGS)
    causes = [row["termination_cause"] for row in rows]
    logger.log_scalars((tag, causes.count(name), step) for name, tag in _CAUSE_TAGS)
    logger.log_metrics(train_metrics, step=step)
