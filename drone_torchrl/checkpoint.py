"""Atomic checkpoints: a killed run loses at most the episodes since the last one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_DIR = "checkpoints"
LAST = "last.pt"
BEST = "best.pt"


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` through a temporary file and an atomic rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def resolve_checkpoint(location: str | os.PathLike) -> Path:
    """A checkpoint file, or a run folder holding ``checkpoints/last.pt``; ``FileNotFoundError`` otherwise."""
    path = Path(location).expanduser()
    if path.is_dir():
        path = path / CHECKPOINT_DIR / LAST
    if not path.is_file():
        raise FileNotFoundError(
            f"{location!s} is neither a checkpoint file nor a run folder with {CHECKPOINT_DIR}/{LAST}"
        )
    return path


def load_checkpoint(path: Path) -> dict[str, Any]:
    # Our own files hold numpy RNG states and plain containers besides tensors.
    return torch.load(path, map_location="cpu", weights_only=False)


def run_dir_of(checkpoint: Path) -> Path:
    """The run folder a checkpoint belongs to (``<run>/checkpoints/<file>``)."""
    return checkpoint.resolve().parent.parent
