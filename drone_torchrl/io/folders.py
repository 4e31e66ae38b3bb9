"""Run folders a command made but did not use, the folders a fork may train in, and their Hydra record."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from drone_torchrl.checks import ConfigError
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST
from drone_torchrl.io.run_lock import LOCK_NAME

#: What a run folder holds before the command's own code runs (Hydra's record and log, and the
#: folder's lock, :mod:`drone_torchrl.io.run_lock`).
HYDRA_ENTRIES = frozenset({".hydra", "train.log", "evaluate.log", "export.log", LOCK_NAME})
#: Hydra's record of how a run was started (``hydra.output_subdir``'s default).
HYDRA_RECORD = ".hydra"


def record_subdir(*, _parent_: Any) -> str | None:
    """``hydra.output_subdir`` of a run or job: :data:`HYDRA_RECORD`, or None for a folder that holds a run.

    The ``drone_torchrl.record_subdir`` resolver (``conf/config.yaml``), read by every launcher once
    the job's folder (``hydra.runtime.output_dir``, in ``_parent_``: Hydra's node) is known. A folder
    whose ``checkpoints/last.pt`` exists keeps the record of how its run was started: a re-run that
    finds it finished, continues it or is refused does not rewrite it (with its original keys, e.g.
    an old ``engine: fused``).
    """
    folder = OmegaConf.select(_parent_, "runtime.output_dir", default=None, throw_on_missing=False)
    if folder is not None and (Path(str(folder)) / CHECKPOINT_DIR / LAST).is_file():
        return None
    return HYDRA_RECORD


def remove_if_untouched(run_dir: Path, root: Path | None = None, also: frozenset[str] = frozenset()) -> None:
    """Delete ``run_dir`` if it holds only what Hydra put there, then its empty parents up to ``root``.

    Entries named in ``also`` count as Hydra's too; ``root`` defaults to the current folder.

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


def check_fork_folder(folder: Path, resume: str, also: frozenset[str] = frozenset({LOCK_NAME})) -> None:
    """Refuse a fork's folder unless it is new or holds only entries named in ``also``.

    A fork (``resume=`` a checkpoint that is not its run's ``last.pt``) trains in a folder of its
    own: ``folder`` must be new, or hold nothing but entries named in ``also`` (a lock left behind;
    inside the Hydra job: what Hydra wrote for it, :data:`HYDRA_ENTRIES`). Anything else is another
    run, which the fork would overwrite: :class:`~.checks.ConfigError` before anything is written.
    """
    try:
        entries = sorted(p.name for p in Path(folder).iterdir() if p.name not in also)
    except (FileNotFoundError, NotADirectoryError):
        return  # new; a file is refused by the folder checks
    if entries:
        raise ConfigError(
            f"hydra.run.dir={folder} is not allowed; expected a new or empty folder: it holds {', '.join(entries[:3])}"
            f"{', ...' if len(entries) > 3 else ''}, and resume={resume} continues as a fork, which would "
            f"overwrite them (to continue the run in that folder: drone-train resume={folder})"
        )
