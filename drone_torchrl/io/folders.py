"""Run folders a command made but did not use."""

from __future__ import annotations

import shutil
from pathlib import Path

from drone_torchrl.io.run_lock import LOCK_NAME

# What a run folder holds before the command's own code runs: Hydra's record and log, and the
# folder's lock (drone_torchrl.io.run_lock).
HYDRA_ENTRIES = frozenset({".hydra", "train.log", "evaluate.log", "export.log", LOCK_NAME})


def remove_if_untouched(run_dir: Path, root: Path | None = None, also: frozenset[str] = frozenset()) -> None:
    """Delete ``run_dir`` if it holds only what Hydra put there (and entries named in ``also``), then
    its parents up to ``root`` (default: the current folder) while they are empty.

    A refused config, or a resume that continued another folder, trains nothing here: the folder
    (``outputs/<date>/<time>/``) would only be clutter among the real runs.
    """
    run_dir = Path(run_dir).resolve()
    root = (Path.cwd() if root is None else Path(root)).resolve()
    if (
        not run_dir.is_dir()
        or run_dir == root
        or not {p.name for p in run_dir.iterdir()} <= HYDRA_ENTRIES | also
    ):
        return
    shutil.rmtree(run_dir, ignore_errors=True)
    for parent in run_dir.parents:
        if parent == root or root not in parent.parents or any(parent.iterdir()):
            break
        parent.rmdir()
