"""``episodes.csv``: one row per finished episode. The one writer and the one reader."""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

import numpy as np

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


class EpisodeCSV:
    """One row per episode in ``path``, buffered: rows are appended when :meth:`flush` is called, and
    no file stays open in between (a population of runs holds no file descriptor per run).

    ``keep_episodes``: on resume, keep the rows of episodes ``< keep_episodes`` read from ``source``
    (default: ``path`` itself; a fork copies its parent run's rows) and drop the rest, which the
    interrupted process wrote after its last checkpoint.
    """

    def __init__(self, path: Path, keep_episodes: int = 0, source: Path | None = None) -> None:
        self.path = Path(path)
        source = self.path if source is None else Path(source)
        rows: list[dict[str, str]] = []
        if keep_episodes and source.exists():
            with source.open(newline="") as f:
                rows = [row for row in csv.DictReader(f) if int(row["episode"]) < keep_episodes]
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
        self._rows: list[dict[str, object]] = []

    def write(self, rows: Iterable[dict[str, object]]) -> None:
        self._rows.extend(rows)

    def flush(self) -> None:
        if not self._rows:
            return
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=CSV_COLUMNS).writerows(self._rows)
        self._rows.clear()

    def close(self) -> None:
        self.flush()


class EpisodeCSVError(ValueError):
    """An ``episodes.csv`` that cannot be read: one line naming the file."""


def read_episodes(path: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read ``episodes.csv`` as columns ordered by episode, and notes about what was left out.

    Numbers come back as float64 arrays, ``termination_cause`` as an array of names. Tolerant of
    a run still writing: reading stops at the first row that does not parse (a line being
    appended). Duplicate episode indices keep their last row; the rows stop at the first gap in
    the episode indices (noted).
    """
    path = Path(path)
    notes: list[str] = []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in CSV_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise EpisodeCSVError(f"{path} lacks the column(s) {', '.join(missing)}")
        by_episode: dict[int, dict[str, object]] = {}
        for row in reader:
            try:
                parsed = {c: row[c] if c in TEXT_COLUMNS else float(row[c]) for c in CSV_COLUMNS}
            except (TypeError, ValueError):
                break
            if any(parsed[c] is None for c in TEXT_COLUMNS):
                break
            by_episode[int(parsed["episode"])] = parsed
    ordered = sorted(by_episode)
    contiguous = 0
    while contiguous < len(ordered) and ordered[contiguous] == contiguous:
        contiguous += 1
    if contiguous < len(ordered):
        notes.append(f"{path}: episode indices have a gap; using episodes 0-{contiguous - 1}")
    rows = [by_episode[e] for e in ordered[:contiguous]]
    columns = {
        c: np.array([r[c] for r in rows], dtype=object if c in TEXT_COLUMNS else np.float64)
        for c in CSV_COLUMNS
    }
    return columns, notes
