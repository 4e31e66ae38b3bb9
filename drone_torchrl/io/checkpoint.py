"""Checkpoints: tensors and plain data only, versioned, written atomically, loaded without pickle code.

A checkpoint is a dict of tensors, numbers, strings, lists and dicts (the config as plain data,
RNG states as uint8 tensors), so ``torch.load(weights_only=True)`` reads it and a crafted file
cannot run code. ``format_version`` says which layout it has; older layouts are migrated when
loaded (:func:`migrate`), anything else is refused with a one-line :class:`CheckpointError`.

Layout (``format_version`` 3)::

    format_version  3
    backend         "fast" | "reference": the backend that wrote it (a run continues with it)
    actor           state_dict of the ProbabilisticActor (make_actor's layout)
    optimizer       state_dict of the agent's Adam
    episodes_done, updates_done, wall_clock_s, best_eval_return
    recent_returns, recent_lengths   the running-mean windows (lists of floats)
    rng             {"torch": global RNG, "env": DroneEnv generator, "agent": None}: uint8 tensors
                    for the TorchRL collector; all None for the vectorised one, whose counter-based
                    noise needs only the update count (older files may hold a generator state
                    under "agent"; it is not used)
    config          the run's resolved config (plain dict)
    final           None while the run goes on; its final metrics once it finished
    <algorithm's>   what its learner adds (algo=ppo and a2c: ``critic``; see drone_torchrl.algorithms)
"""

from __future__ import annotations

import io
import os
import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from drone_torchrl import migrations
from drone_torchrl.io.storage import writing

CHECKPOINT_DIR = "checkpoints"
LAST = "last.pt"
BEST = "best.pt"
FORMAT_VERSION = 3
# Keys every checkpoint of the current format holds.
REQUIRED_KEYS = (
    "format_version",
    "backend",
    "actor",
    "optimizer",
    "episodes_done",
    "updates_done",
    "wall_clock_s",
    "best_eval_return",
    "recent_returns",
    "recent_lengths",
    "rng",
    "config",
    "final",
)


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: one line naming the file and why."""


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` through a temporary file and an atomic rename."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    # Serialised in memory and written at once: torch.save's zip writer makes a small write per
    # record (half of the time for a file of this size).
    buffer = io.BytesIO()
    torch.save(state, buffer)
    with writing(path, tmp):  # a full disk leaves the previous checkpoint whole and no .tmp behind
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(buffer.getbuffer())
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


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True`` and migrate it to :data:`FORMAT_VERSION`.

    Raises :class:`CheckpointError` (one line, naming the file) for a file that is not a
    checkpoint, holds Python objects other than tensors and plain data, or has an unknown version.
    """
    path = Path(path)
    try:
        with warnings.catch_warnings():  # torch warns before refusing a pickle it will not run
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        if "Unsupported global" not in str(err):  # not a pickle we could read at all
            raise CheckpointError(
                f"{path} is not a readable checkpoint (damaged or not a torch file)"
            ) from None
        raise CheckpointError(
            f"{path} holds Python objects other than tensors and plain data; refusing to unpickle it"
        ) from None
    except Exception:  # noqa: BLE001  (torch.load raises many kinds for a damaged file)
        raise CheckpointError(
            f"{path} is not a readable checkpoint (empty, truncated, or not a file torch.save wrote)"
        ) from None
    return migrate(state, path)


def migrate(state: Any, path: Path) -> dict[str, Any]:
    """Bring a loaded checkpoint to the current layout, or refuse it.

    Version 1 (no ``format_version`` key; written before it existed) kept the RNG states as
    ``torch_rng`` / ``env_rng`` / ``agent_rng`` and had no ``final`` key while unfinished. Versions
    1 and 2 named the implementation ``engine`` (and PPO's ``algo.collector`` in the config), which
    ``backend`` replaced (:mod:`drone_torchrl.migrations`).
    """
    if not isinstance(state, dict) or "actor" not in state or "config" not in state:
        raise CheckpointError(f"{path} is not a drone_torchrl checkpoint (no actor or config)")
    version = state.get("format_version", 1)
    if version == 1:
        state = dict(state)
        state["rng"] = {
            "torch": state.pop("torch_rng", None),
            "env": state.pop("env_rng", None),
            "agent": state.pop("agent_rng", None),
        }
        state.setdefault("final", None)
        version = 2
    if version == 2:
        state = dict(state)
        config = state["config"] if isinstance(state["config"], dict) else {}
        algo = config.get("algo") if isinstance(config.get("algo"), dict) else {}
        state["backend"] = migrations.backend_of(state.pop("engine", None), algo.get("collector"))
        state["format_version"] = version = FORMAT_VERSION
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has format_version={version!r}; this version of drone_torchrl reads 1 to {FORMAT_VERSION}"
        )
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CheckpointError(f"{path} lacks {', '.join(missing)}: a damaged or foreign checkpoint")
    return state


def run_dir_of(checkpoint: Path) -> Path:
    """The run folder a checkpoint belongs to (``<run>/checkpoints/<file>``)."""
    return Path(checkpoint).resolve().parent.parent


def is_last_of_its_run(checkpoint: Path) -> bool:
    """Whether ``checkpoint`` is its run's ``checkpoints/last.pt`` (resuming from it continues the run)."""
    checkpoint = Path(checkpoint).resolve()
    return checkpoint == run_dir_of(checkpoint) / CHECKPOINT_DIR / LAST
