"""Per-episode metrics of a batch of rollouts, and the CSV file the reports read."""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

import torch
from tensordict import TensorDictBase

from drone_torchrl.envs.dynamics import TerminationCause, in_target_zone
from drone_torchrl.objectives.reinforce import valid_steps

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


def episode_stats(rollout: TensorDictBase) -> dict[str, torch.Tensor]:
    """Metrics of each row of a ``[E, T]`` rollout that holds one episode per row.

    ``return``, ``length``; ``time_in_zone``: fraction of the episode's steps that ended inside the
    target zone; ``negative_thrust_fraction``: fraction of motor commands below zero (the paper's
    exploit); ``termination_cause``: the code on the episode's last step (0 when truncated).
    """
    done = rollout.get(("next", "done"))
    valid = valid_steps(done).squeeze(-1)
    length = valid.sum(-1)
    reward = rollout.get(("next", "reward")).squeeze(-1)
    terminated = rollout.get(("next", "terminated")).squeeze(-1)
    zone = in_target_zone(rollout.get(("next", "observation"))) & valid & ~terminated
    negative = (rollout.get("action") < 0) & valid.unsqueeze(-1)
    last = (length - 1).clamp_min(0).unsqueeze(-1)
    cause = rollout.get(("next", "termination_cause")).squeeze(-1).gather(-1, last).squeeze(-1)
    steps = length.clamp_min(1).to(reward.dtype)
    return {
        "return": torch.where(valid, reward, 0.0).sum(-1),
        "length": length,
        "time_in_zone": zone.sum(-1) / steps,
        "negative_thrust_fraction": negative.sum((-1, -2)) / (steps * negative.shape[-1]),
        "termination_cause": cause,
    }


def cause_counts(causes: torch.Tensor) -> dict[str, int]:
    """How many episodes ended with each :class:`TerminationCause` (``NONE`` = truncated)."""
    return {cause.name: int((causes == cause).sum()) for cause in TerminationCause}


class EpisodeCSV:
    """Appends one row per episode to ``episodes.csv``; on resume, drops rows past the checkpoint."""

    def __init__(self, path: Path, keep_episodes: int | None = None) -> None:
        self.path = path
        rows: list[dict[str, str]] = []
        if keep_episodes is not None and path.exists():
            with path.open(newline="") as f:
                rows = [row for row in csv.DictReader(f) if int(row["episode"]) < keep_episodes]
        self._file = path.open("w", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=CSV_COLUMNS)
        self._writer.writeheader()
        self._writer.writerows(rows)
        self._file.flush()

    def write(self, rows: Iterable[dict[str, object]]) -> None:
        self._writer.writerows(rows)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_episode_csv(path: Path) -> dict[str, list]:
    """Read ``episodes.csv`` back as columns (numbers as floats, the cause as its name)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {
        col: [row[col] if col == "termination_cause" else float(row[col]) for row in rows]
        for col in CSV_COLUMNS
    }
