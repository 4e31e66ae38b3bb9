"""``logger=csv``: every scalar as a row of one CSV per run, ``<run>/<logger.exp_name>/scalars.csv``.

Long format, ``step,tag,value`` (a pandas ``pivot`` away from one column per tag), so a new tag
never rewrites the file, a run holds one file (TorchRL's ``CSVLogger`` holds one open file per tag
and every value in memory), and the file is open only while a flush appends to it. The final
hyper-parameters and metrics go to ``hparams.csv`` beside it (``key,value``). Videos are not logged
here: the run folder's ``videos/`` has them. ``logger.float_format`` (a ``%`` format such as
``"%.6g"``) shortens the values; by default they are written in full (Python's ``repr``).

Resume: rows after the checkpoint's count of episodes are dropped (the file is rewritten through a
temporary file and an atomic rename), the others kept, so a continued run's file reads as one
uninterrupted run's.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from drone_torchrl.checks import ConfigError
from drone_torchrl.io.episodes_csv import is_text, open_csv
from drone_torchrl.io.storage import write_csv, writing
from drone_torchrl.loggers import Backend, Logger, flatten_config, register
from drone_torchrl.schema import IF_SET, TensorBoardConf, free, store_plugin

SCALARS = "scalars.csv"
HPARAMS = "hparams.csv"
HEADER = ("step", "tag", "value")


class CSVLogger(Logger):
    """Buffered scalars appended to ``<log_dir>/scalars.csv`` (videos are not kept).

    Args:
        log_dir: the folder of ``scalars.csv`` and ``hparams.csv``.
        resumed_at: on resume, the step after which the rows already in ``scalars.csv`` are dropped.
        float_format: a ``%`` format for the values (None: written in full, Python's ``repr``).
    """

    def __init__(self, log_dir: Path, resumed_at: int | None = None, float_format: str | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.float_format = float_format
        self.path = self.log_dir / SCALARS
        self.scalars: list[tuple[str, float, int]] = []
        if resumed_at is not None and self.path.is_file():
            # Only the rows up to resumed_at, dropping torn lines (a kill's) and non-UTF-8 rows.
            with open_csv(self.path) as f:
                rows = list(csv.reader(f))[1:]
            good = (row for row in rows if len(row) == len(HEADER) and is_text(row))
            write_csv(self.path, HEADER, [row for row in good if _step(row[0]) <= resumed_at])

    def log_final_hparams(self, cfg: DictConfig | dict, metrics: dict[str, float]) -> None:
        """Write the flattened config and the final ``metrics`` (as ``hparam/*``) to the hparams file."""
        entries = {**flatten_config(cfg), **{f"hparam/{k}": v for k, v in metrics.items()}}
        write_csv(self.log_dir / HPARAMS, ("key", "value"), entries.items())

    def flush(self) -> None:
        """Append the buffered rows to the scalars CSV (with its header when the file is new)."""
        if not self.scalars:
            return
        with writing(self.path):
            self.log_dir.mkdir(parents=True, exist_ok=True)
        new = not self.path.is_file()
        with writing(self.path), self.path.open("a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(HEADER)
            fmt = self.float_format
            writer.writerows(
                (int(step), tag, repr(float(value)) if fmt is None else fmt % value)
                for tag, value, step in self.scalars
            )
        self.scalars.clear()


def _step(text: str) -> float:
    """A row's step (inf for one that is not an integer: a torn or garbled row)."""
    try:
        return int(text)
    except ValueError:
        return math.inf


def make(cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> CSVLogger:
    """The CSV logger of the run in ``run_dir`` (``resumed_at``: the count it resumes from, or None)."""
    return CSVLogger(run_dir / cfg.logger.exp_name, resumed_at, cfg.logger.float_format)


def validate(cfg: Mapping[str, Any]) -> None:
    """``logger.float_format``: null, or a ``%`` format of one number."""
    fmt = cfg.logger.float_format
    if fmt is None:
        return
    try:
        if not isinstance(fmt, str):  # a number would be taken modulo 0.5 (10**400: an OverflowError)
            raise TypeError
        float(fmt % 0.5)
    except (TypeError, ValueError):
        raise ConfigError.of(
            "logger.float_format", fmt, "null or a %-format of one number, e.g. '%.6g'"
        ) from None


@dataclass
class CSVConf(TensorBoardConf):
    """``logger.*`` of ``logger.backend=csv`` (the %-format is checked by drone_torchrl/loggers/csvfile.py)."""

    float_format: Any = free(on_resume=IF_SET)


store_plugin("logger", "csv", CSVConf)

register(
    Backend(
        "csv",
        make,
        resume_rule="rows logged after the checkpoint are dropped (the file is rewritten), the rest kept",
        validate=validate,
        summary="every scalar as a `step,tag,value` row of `<run>/csv/scalars.csv`; final metrics in `hparams.csv`",
    )
)
