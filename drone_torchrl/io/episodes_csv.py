"""``episodes.csv``: one row per finished episode. The one writer and the one reader."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from drone_torchrl.io.storage import write_csv, writing

CSV_NAME = "episodes.csv"
CSV_COLUMNS = (
    "episode",
    "update",
    "return",
    "length",
    "time_in_zone",
    "negative_thrust_fraction",
    "termination_cause",
    "wall_clock_s",
)
TEXT_COLUMNS = ("termination_cause",)


def open_csv(path: Path) -> TextIO:
    """Open ``path`` for :mod:`csv` to read as UTF-8, a byte that is not UTF-8 kept as a lone surrogate.

    A damaged file does not raise: one bad row costs that row (:func:`is_text`).
    """
    return Path(path).open(newline="", encoding="utf-8", errors="surrogateescape")


def is_text(fields: Iterable[Any]) -> bool:
    """Whether a row read through :func:`open_csv` was UTF-8 text.

    It checks the fields, lists of extra fields and ``None`` for missing ones.
    """
    for field in fields:
        for value in field if isinstance(field, list) else [field]:
            try:
                (value or "").encode("utf-8")
            except UnicodeEncodeError:
                return False
    return True


def _read_rows(path: Path) -> tuple[list[tuple[dict[str, object], dict[str, str]]], list[str]]:
    """The parsable rows of ``path`` (parsed, and as written), and a note for each line left out.

    A line is left out when torn, garbled, or not UTF-8. A row is kept as numbers (and the cause's
    name): each finite, the cause named, and no more fields than columns (two rows run together).
    """
    notes: list[str] = []
    rows = []
    with open_csv(path) as f:
        reader = csv.DictReader(f)
        missing = [c for c in CSV_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise EpisodeCSVError(f"{path} lacks the column(s) {', '.join(missing)}")
        for row in reader:
            try:
                parsed = {c: row[c] if c in TEXT_COLUMNS else float(row[c]) for c in CSV_COLUMNS}  # type: ignore[arg-type]
            except (TypeError, ValueError):
                parsed = None
            if not is_text(row.values()):
                notes.append(f"{path}: line {reader.line_num} is not UTF-8 text; skipped")
            elif (
                parsed is None
                or None in row
                or not all(v if c in TEXT_COLUMNS else math.isfinite(v) for c, v in parsed.items())
            ):
                notes.append(f"{path}: line {reader.line_num} is not a complete row; skipped")
            else:
                rows.append((parsed, row))
    return rows, notes


class EpisodeCSV:
    """One row per episode in ``path``, buffered until :meth:`~EpisodeCSV.flush`.

    No file stays open between flushes (a population of runs holds no file descriptor per run).

    Args:
        path: the CSV file written (rewritten at once with its header and the rows kept).
        keep_episodes: on resume, keep the rows of episodes ``< keep_episodes`` read from
            ``source`` and drop the rest, which the interrupted process wrote after its last
            checkpoint. A row torn by the interruption is dropped too; ``notes`` says which lines were.
        source: the file those rows are read from (default: ``path`` itself; a fork copies its
            parent run's rows).
    """

    def __init__(self, path: Path, keep_episodes: int = 0, source: Path | None = None) -> None:
        self.path = Path(path)
        source = self.path if source is None else Path(source)
        rows: list[dict[str, str]] = []
        self.notes: list[str] = []
        self.dropped = 0  # rows of episodes at or after keep_episodes (trained again after a resume)
        if keep_episodes and source.exists():
            read, self.notes = _read_rows(source)
            rows = [raw for parsed, raw in read if parsed["episode"] < keep_episodes]
            self.dropped = sum(parsed["episode"] >= keep_episodes for parsed, _ in read)
        # Atomically: a kill leaves the old file whole.
        write_csv(self.path, CSV_COLUMNS, ([row[c] for c in CSV_COLUMNS] for row in rows))
        self._rows: list[dict[str, object]] = []

    def write(self, rows: Iterable[dict[str, object]]) -> None:
        """Buffer episode rows (column name to value) until the next :meth:`flush`."""
        self._rows.extend(rows)

    def flush(self) -> None:
        """Append the buffered rows to the file (kept buffered if the disk refuses them)."""
        if not self._rows:
            return
        # A refused append may leave a torn last row: the rows stay buffered, and a resume drops
        # what follows the checkpoint (the torn row with it).
        with writing(self.path), self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=CSV_COLUMNS).writerows(self._rows)
        self._rows.clear()


class EpisodeCSVError(ValueError):
    """An ``episodes.csv`` that cannot be read: one line naming the file."""


def read_episodes(path: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read ``episodes.csv`` as columns ordered by episode, and notes about what was left out.

    Numbers come back as float64 arrays, ``termination_cause`` as an array of names. A row that
    does not parse (torn by a kill, a line still being appended, garbage, ``nan``, bytes that are
    not UTF-8) is skipped with a note, and the rows after it are read; duplicate episode indices keep their last row, and
    missing episode indices are noted.
    """
    path = Path(path)
    rows, notes = _read_rows(path)
    by_episode = {int(parsed["episode"]): parsed for parsed, _ in rows}
    if len(by_episode) < len(rows):
        notes.append(
            f"{path}: {len(rows) - len(by_episode)} episode(s) have more than one row; using the last"
        )
    ordered = sorted(by_episode)
    missing = sorted(set(range(ordered[-1] + 1)) - set(ordered)) if ordered else []
    if missing:
        shown = ", ".join(str(e) for e in missing[:5]) + (", ..." if len(missing) > 5 else "")
        notes.append(f"{path}: {len(missing)} episode(s) have no row ({shown})")
    columns = {
        c: np.array([by_episode[e][c] for e in ordered], dtype=object if c in TEXT_COLUMNS else np.float64)
        for c in CSV_COLUMNS
    }
    return columns, notes
