"""Where a multirun goes: ``multirun/<sweep_name>``, or for an ad-hoc sweep a folder named by its command.

Every job is idempotent in a fixed sweep folder (:mod:`drone_torchrl.training.jobs`): the same
command run again skips its finished jobs and resumes the others. An ad-hoc sweep (no
``sweep_name``) gets a folder of its own, :func:`sweep_folder`: a readable prefix (the swept keys)
and a short hash of every override that defines the search, so the same command finds its folder
again and another command never shares it (its summary and ``drone-report`` see its jobs only).

Hydra resolves ``hydra.sweep.dir`` in the sweep's config, whose ``hydra.overrides.task`` holds the
command line's lists (``seed=0,1``), and again in each job's config, whose overrides are the job's
own (``seed=1``). The resolver is cached (``use_cache``) as Hydra's ``${now:...}`` is: Hydra copies
the sweep's cache into each job's config (``load_sweep_config``), so every job, in any process or
on any launcher, gets the sweep's folder.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

#: What marks a folder as a sweep's root (Hydra writes it there when the sweep starts).
SWEEP_RECORD = "multirun.yaml"
#: The folder every ad-hoc sweep shared before they were named by their overrides.
OLD_ADHOC = "adhoc"
#: Hex digits of the hash in an ad-hoc sweep's folder name.
HASH_DIGITS = 8
# Keeps the readable prefix well inside a file system's 255-byte names.
_PREFIX_CHARS = 60
#: The launchers that change what a sweep is, with one population run per group (``population_<g>/``,
#: not a folder per job) or a search (PBT, successive halving, a PBT agent replayed). The others (basic,
#: fused, local_parallel, slurm, ...) train the same jobs into the same job folders, so the same grid
#: run by another of them continues in its folder; their keys (cores, partition) are no matter either.
#: Without ``-m`` Hydra ignores a launcher, so a single run naming one of these would train something
#: else than asked: ``drone-train`` refuses it (:func:`drone_torchrl.command_line.check_single_run`).
SEARCH_LAUNCHERS = frozenset({"population", "pbt", "pb2", "halving", "pbt_replay"})
_LAUNCHER = "hydra/launcher"
# Hydra overrides that pick the jobs (the sweeper and its params); the others (hydra.verbose,
# hydra.job_logging, hydra.mode, ...) change how the sweep is logged, not what it is.
_SWEEPER = ("hydra/sweeper", "hydra.sweeper.")


def _key(override: str) -> str:
    """The key of an override as typed (``+algo.lr=1`` -> ``algo.lr``, ``~logger`` -> ``logger``)."""
    return override.partition("=")[0].lstrip("+~")


def search_overrides(task: Iterable[str], hydra: Iterable[str] = ()) -> list[str]:
    """The overrides that name an ad-hoc sweep's folder, sorted (their order on the line is no matter).

    Every task override but the process-only ones (budgets included: ``algo.episodes=2`` and
    ``algo.episodes=6000`` are different sweeps), the sweeper's overrides, and a
    :data:`SEARCH_LAUNCHERS` launcher with its keys (a PBT search and a plain grid over the same
    values differ; a grid run by ``fused`` or ``slurm`` is the grid run by ``basic``).
    """
    from drone_torchrl import schema

    # Keys that only say where and how this process runs (the schema's PROCESS keys: device, threads,
    # progress...; no plug-in has one) do not enter the hash, nor sweep_name (an ad-hoc sweep has none).
    process = (k for k, rule in schema.fields(schema.TrainConfig, {}) if rule.on_resume == schema.PROCESS)
    skip = {"sweep_name", *process}
    chosen = [str(o) for o in task if _key(str(o)) not in skip]
    hydra = [str(o) for o in hydra]
    launcher = next((o.partition("=")[2] for o in reversed(hydra) if _key(o) == _LAUNCHER), None)
    search = (_SWEEPER + (_LAUNCHER, "hydra.launcher.")) if launcher in SEARCH_LAUNCHERS else _SWEEPER
    chosen += [o for o in hydra if _key(o).startswith(search)]
    return sorted(chosen)


def sweep_folder(sweep_name: str | None, task: Iterable[str], hydra: Iterable[str] = ()) -> str:
    """The sweep folder's name under ``multirun/``: ``sweep_name``, or for an ad-hoc sweep (null) its own.

    The ``drone_torchrl.sweep_folder`` resolver of ``hydra.sweep.dir`` (``conf/config.yaml``),
    given ``sweep_name``, ``hydra.overrides.task`` and ``hydra.overrides.hydra``. An ad-hoc sweep's
    name is ``<swept keys>-<hash>``, e.g. ``algo.lr,seed-1c9a4f0e``: the keys given several values
    (``adhoc`` when none is), and a hash of :func:`search_overrides`.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if sweep_name is not None:
        return str(sweep_name)
    overrides = search_overrides(task, hydra)
    digest = hashlib.sha256("\n".join(overrides).encode()).hexdigest()[:HASH_DIGITS]
    parsed = OverridesParser.create().parse_overrides([o for o in overrides if not o.startswith("hydra")])
    swept = sorted({o.key_or_group.replace("/", ".") for o in parsed if o.is_sweep_override()})
    prefix = ",".join(swept)[:_PREFIX_CHARS] or OLD_ADHOC
    return f"{prefix}-{digest}"


def group_name(sweep_name: str | None, run_dir: Path) -> str:
    """The name a logger groups a run under (W&B's group, MLflow's experiment) when none is given.

    ``sweep_name``; for a job of an ad-hoc sweep its sweep folder's name (the folder holds the
    sweep's ``multirun.yaml``), so each sweep is one group; for a single run :data:`OLD_ADHOC`.
    """
    if sweep_name is not None:
        return str(sweep_name)
    sweep = Path(run_dir).resolve().parent
    return sweep.name if (sweep / SWEEP_RECORD).is_file() else OLD_ADHOC
