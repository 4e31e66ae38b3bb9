"""Checkpoints: tensors and plain data only, versioned, written atomically, loaded without pickle code.

A checkpoint is a dict of tensors, numbers, strings, lists and dicts (the config as plain data,
RNG states as uint8 tensors), so ``torch.load(weights_only=True)`` reads it and a crafted file
cannot run code. ``format_version`` says which layout it has; older layouts are migrated when
loaded (:func:`migrate`), anything else is refused with a one-line :class:`CheckpointError`.

Layout (``format_version`` 4), one for every run record: a run's (``kind`` "run") and a population
run's (``kind`` "population", drone_torchrl.training.population_record)::

    format_version  4
    kind            "run" | "population"
    backend         "fast" | "reference": the backend that wrote it (a run continues with it)
    <learner's>     a run's: actor (ProbabilisticActor state_dict, make_actor's layout), optimizer
                    (its Adam's), rng ({"torch", "env", "agent"}: uint8 tensors for the TorchRL
                    collector; all None for the vectorised one, whose counter-based noise needs only
                    the update count) and what its algorithm adds (algo=ppo and a2c: ``critic``, and
                    with eval.rollback_drop ``rollback``; see drone_torchrl.algorithms); a
                    population's: state, every agent's tensors stacked ``[N, ...]``
    config          the run's resolved config (plain dict; a population's: agent 0's values)
    episodes_done, updates_done, wall_clock_s, best_eval_return, stopped_at_return,
    recent_returns, recent_lengths (the running-mean windows),
    final (None while training; the final metrics once finished), failure (None, or why it diverged)
                    the counters of each agent (:data:`COUNTERS`): a run's as they are, a
                    population's a list over its agents, the windows ``[N, window]`` float64,
                    zero-padded, with ``recent_count`` [N]
    agents, parts, population_updates, search
                    a population's only: each agent's name and per-agent values, the episode parts
                    its counters cover, its updates, its search's record
    tensor_sha256   {"actor/<key>": sha256 of that tensor's dtype, shape and bytes, ...}: every
                    tensor above, written by :func:`save_checkpoint`

Older layouts are upgraded when read (:func:`migrate`): version 3 (a run's without ``kind``,
``failure`` and perhaps ``stopped_at_return``; a population's with one ``wall_clock_s`` for all its
agents and no ``stopped_at_return``), version 2 (``engine`` instead of ``backend``), version 1 (no
``format_version``; RNG states under ``torch_rng``, ``env_rng``, ``agent_rng``; no ``final``).

What is loaded is checked (:func:`load_checkpoint`), since ``torch.load`` reads damaged bytes
without noticing: each tensor against its digest, every record of the file against the CRC-32
its zip archive keeps, the counters (``episodes_done``, ``updates_done``: integers >= 0) and every
floating-point tensor (finite: a run never saves diverged weights). Checkpoints written before the
digest existed have none and still load; their zip CRCs are checked all the same. Tensors whose
shapes the run's config does not make are refused when they are loaded into its networks
(:func:`check_weights`).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import warnings
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch

from drone_torchrl import migrations
from drone_torchrl.checks import ConfigError, check_number
from drone_torchrl.io.storage import name_too_long, write_atomically

CHECKPOINT_DIR = "checkpoints"
LAST = "last.pt"
BEST = "best.pt"
#: The checkpoint format written; older ones are upgraded to it when read.
FORMAT_VERSION = 4
# The two kinds of run record (``kind``).
RUN, POPULATION = "run", "population"
#: Each agent's counters, as :meth:`~drone_torchrl.training.run.AgentBook.counters` gives them.
COUNTERS = (
    *("episodes_done", "updates_done", "wall_clock_s", "best_eval_return", "recent_returns"),
    *("recent_lengths", "stopped_at_return", "final", "failure"),
)
# The running-mean windows among them: a population's are zero-padded tensors.
WINDOWS = ("recent_returns", "recent_lengths")
# The keys a reader needs of each kind, a run's and a population's (the counters added since format
# 3 are filled in first: :func:`migrate`).
REQUIRED_KEYS = ("format_version", "backend", "actor", "optimizer", "rng", "config", *COUNTERS)
POPULATION_KEYS = ("format_version", "backend", "state", "config", "agents", "parts", "episodes_done")
POPULATION_KEYS += ("updates_done", "final", "failure")
# The digest of every tensor of a checkpoint (see the layout above).
DIGEST_KEY = "tensor_sha256"
# Counters a checkpoint carries on (integers >= 0).
WHOLE_COUNTERS = ("episodes_done", "updates_done")
# What a damaged checkpoint's message suggests.
OTHER_CHECKPOINT = "use another checkpoint (the run's best.pt or last.pt, or a copy)"
# Bytes read at a time when checking the zip's CRC-32s.
CRC_CHUNK = 1 << 20


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: one line naming the file and why."""


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write ``state`` and its tensors' digest to ``path`` atomically (temporary file, then rename).

    Written through :func:`~drone_torchrl.io.storage.write_atomically`, so a reader, or a process
    killed meanwhile, sees the old checkpoint or the whole new one.
    """
    state = {key: value for key, value in state.items() if key != DIGEST_KEY}
    state[DIGEST_KEY] = tensor_digests(state)
    # Serialised in memory and written at once: torch.save's zip writer makes a small write per
    # record (half of the time for a file of this size).
    buffer = io.BytesIO()
    torch.save(state, buffer)
    # A full disk leaves the previous checkpoint whole and no .tmp behind.
    write_atomically(path, buffer.getbuffer())


def record_state(
    kind: str, backend: str, learner: dict, config: dict, counters: list[dict], window: int = 0
) -> dict:
    """A run record's checkpoint (the layout above): ``learner``'s entries, then its agents' ``counters``.

    A run's one agent's as they are; a population's a list per key, the windows zero-padded to ``window``.
    """
    if kind == RUN:
        (stacked,) = counters
    else:
        stacked = {key: [c[key] for c in counters] for key in COUNTERS if key not in WINDOWS}
        for key in WINDOWS:  # each agent's window, zero-padded to [N, window]
            stacked[key] = torch.tensor(
                [c[key] + [0.0] * (window - len(c[key])) for c in counters], dtype=torch.float64
            )
        stacked["recent_count"] = torch.tensor([len(c["recent_returns"]) for c in counters])
    head = {"format_version": FORMAT_VERSION, "kind": kind, "backend": backend}
    return {**head, **learner, "config": config, **stacked}


def agent_counters(state: dict[str, Any], agent: int = 0) -> dict[str, Any]:
    """Agent ``agent``'s counters in a checkpoint (:data:`COUNTERS`; a run's are its one agent's)."""
    if not is_population(state):
        return {key: state[key] for key in COUNTERS}
    count = int(state["recent_count"][agent])
    return {
        key: state[key][agent, :count].tolist() if key in WINDOWS else state[key][agent] for key in COUNTERS
    }


def is_population(checkpoint: Any) -> bool:
    """Whether ``checkpoint`` is a population run's checkpoint (``kind``)."""
    return isinstance(checkpoint, dict) and checkpoint.get("kind") == POPULATION


def tensors(state: Any, prefix: str = "") -> Iterator[tuple[str, torch.Tensor]]:
    """Every tensor of a checkpoint's nested dicts and lists, with its path, in storage order.

    A path reads like ``actor/<key>`` or ``optimizer/state/0/exp_avg``.
    """
    if isinstance(state, torch.Tensor):
        yield prefix, state
    elif isinstance(state, Mapping | list | tuple):
        for key, value in state.items() if isinstance(state, Mapping) else enumerate(state):
            yield from tensors(value, f"{prefix}/{key}" if prefix else str(key))


def tensor_digests(state: Mapping[str, Any]) -> dict[str, str]:
    """sha256 of each tensor's dtype, shape and bytes, by its path (:func:`tensors`)."""
    digests = {}
    for where, tensor in tensors(state):
        data = tensor.detach().to("cpu").contiguous().reshape(-1)
        digest = hashlib.sha256(f"{data.dtype} {list(tensor.shape)}".encode())
        digest.update(data.view(torch.uint8).numpy().data if data.numel() else b"")
        digests[where] = digest.hexdigest()
    return digests


def resolve_checkpoint(location: str | os.PathLike) -> Path:
    """A checkpoint file, or a run folder holding ``checkpoints/last.pt``; ``FileNotFoundError`` otherwise."""
    path = Path(location).expanduser()
    too_long = name_too_long(path)
    if too_long is not None:  # is_dir() would raise ENAMETOOLONG
        raise FileNotFoundError(f"{location!s} cannot name a file: {too_long}")
    if path.is_dir():
        path = path / CHECKPOINT_DIR / LAST
    if not path.is_file():
        raise FileNotFoundError(
            f"{location!s} is neither a checkpoint file nor a run folder with {CHECKPOINT_DIR}/{LAST}"
        )
    return path


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``, check it and migrate it to :data:`FORMAT_VERSION`.

    Raises :class:`CheckpointError` (one line, naming the file) for a file that is not a
    checkpoint, holds Python objects other than tensors and plain data, has an unknown version,
    is damaged (a tensor that does not match its digest, a record that does not match its zip
    CRC-32), or holds counters or weights no run saves (see the module's docstring).
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
    if isinstance(state, dict):
        _check_digest(state, path)
    _check_archive(path)
    return migrate(state, path)


def _check_digest(state: dict[str, Any], path: Path) -> None:
    """Each tensor against the digest :func:`save_checkpoint` wrote with it (none in older files)."""
    saved = state.pop(DIGEST_KEY, None)
    if saved is None:
        return
    if not isinstance(saved, dict):
        raise CheckpointError(f"{path}: its {DIGEST_KEY} is not a digest of each tensor: a damaged file")
    digests = tensor_digests(state)
    for where in [*digests, *(w for w in saved if w not in digests)]:
        if digests.get(where) == saved.get(where):
            continue
        what = "does not match the digest written with it" if where in saved else "has no digest"
        what = what if where in digests else "is missing"
        raise CheckpointError(f"{path}: the tensor {where} {what}: a damaged file; {OTHER_CHECKPOINT}")


def _check_archive(path: Path) -> None:
    """Check every record of the zip archive against the CRC-32 stored with it.

    ``torch.load`` does not check them. A record stored without one (CRC 0:
    ``torch.serialization.config.save.compute_crc32`` off) and files in torch's legacy format, which
    are not zip archives, are not checked.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError):
        return
    with archive:
        for info in archive.infolist():
            if info.CRC == 0:
                continue
            try:
                with archive.open(info) as record:
                    while record.read(CRC_CHUNK):
                        pass
            except (zipfile.BadZipFile, OSError, EOFError):
                raise CheckpointError(
                    f"{path}: its record {info.filename} does not match the checksum stored with it: a damaged "
                    f"file; {OTHER_CHECKPOINT}"
                ) from None


def migrate(state: Any, path: Path) -> dict[str, Any]:
    """Bring a loaded checkpoint of any format to the current layout (see the module's docstring), or refuse it.

    Versions 1 and 2 named the implementation ``engine`` (and PPO's ``algo.collector`` in the
    config), which ``backend`` replaced (:mod:`drone_torchrl.migrations`).
    """
    config = state.get("config") if isinstance(state, dict) else None
    if not isinstance(config, dict) or not ("actor" in state or is_population(state)):
        raise CheckpointError(f"{path} is not a drone_torchrl checkpoint (no actor or config)")
    version = state.get("format_version", 1)
    if version == 1:
        state["rng"] = {key: state.pop(f"{key}_rng", None) for key in ("torch", "env", "agent")}
        state.setdefault("final", None)
    if version in (1, 2):
        algo = config.get("algo") if isinstance(config.get("algo"), dict) else {}
        state["backend"] = migrations.backend_of(state.pop("engine", None), algo.get("collector"))
        version = 3
    elif version not in (3, FORMAT_VERSION):
        raise CheckpointError(
            f"{path} has format_version={version!r}; this version of drone_torchrl reads 1 to {FORMAT_VERSION}"
        )
    state["format_version"] = FORMAT_VERSION
    if not is_population(state):  # format 3 had no kind and no failure (never saved after one)
        state.update(kind=RUN, failure=state.get("failure"), stopped_at_return=state.get("stopped_at_return"))
    keys = POPULATION_KEYS if is_population(state) else REQUIRED_KEYS
    if missing := [key for key in keys if key not in state]:
        raise CheckpointError(f"{path} lacks {', '.join(missing)}: a damaged or foreign checkpoint")
    for key in WHOLE_COUNTERS:
        try:
            for value in state[key] if is_population(state) else [state[key]]:
                check_number(key, value, low=0, integer=True)
        except (ConfigError, TypeError) as err:
            raise CheckpointError(f"{path}: {err}; a damaged or hand-edited checkpoint") from None
    if is_population(state):  # format 3 kept one wall clock for all the agents and no stop_return
        agents = len(state["episodes_done"])
        if not isinstance(state.get("wall_clock_s"), list):
            state["wall_clock_s"] = [state.get("wall_clock_s")] * agents
        state.setdefault("stopped_at_return", [None] * agents)
    for where, tensor in tensors(state):
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(
                f"{path}: the tensor {where} holds NaN or infinite values (a run never saves diverged "
                "weights): a damaged or hand-edited checkpoint"
            )
    return state


def check_weights(module: torch.nn.Module, weights: Any, path: Path, entry: str) -> None:
    """Check that ``weights`` holds exactly the tensors ``module`` has, of their shapes.

    ``weights`` is the checkpoint's ``entry``; exactly those tensors is what
    ``module.load_state_dict(weights)`` needs. :class:`CheckpointError` naming the file and the
    first tensor that differs otherwise (``load_state_dict`` lists them all, over many lines).
    ``module`` may live on the meta device: only its shapes are read.
    """
    expected = module.state_dict()
    if not isinstance(weights, Mapping):
        raise CheckpointError(f"{path}: its {entry} is not a state dict: a damaged or foreign checkpoint")
    for key, tensor in expected.items():
        saved = weights.get(key)
        if not isinstance(saved, torch.Tensor):
            raise CheckpointError(
                f"{path}: {entry} lacks the tensor {key} that its config's networks have: a damaged or foreign checkpoint"
            )
        if saved.shape != tensor.shape:
            raise CheckpointError(
                f"{path}: the tensor {entry}/{key} has shape {list(saved.shape)}, but the networks its config "
                f"describes (model.*, algo.*) need {list(tensor.shape)}: a checkpoint of another model, or a hand-edited config"
            )
    unknown = [key for key in weights if key not in expected]
    if unknown:
        raise CheckpointError(
            f"{path}: {entry} holds the tensor {unknown[0]}, which its config's networks do not have: a "
            "damaged or foreign checkpoint"
        )


def run_dir_of(checkpoint: Path) -> Path:
    """The run folder a checkpoint belongs to (``<run>/checkpoints/<file>``)."""
    return Path(checkpoint).resolve().parent.parent


def is_last_of_its_run(checkpoint: Path) -> bool:
    """Whether ``checkpoint`` is its run's ``checkpoints/last.pt`` (resuming from it continues the run)."""
    checkpoint = Path(checkpoint).resolve()
    return checkpoint == run_dir_of(checkpoint) / CHECKPOINT_DIR / LAST
