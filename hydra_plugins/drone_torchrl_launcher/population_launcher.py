"""The one launcher of a sweep trained as one batch: ``hydra/launcher=population``, ``fused`` and the searches.

Its keys (``conf/hydra/launcher/population.yaml``; each other option there is it with keys preset):

- ``search``: ``none``, ``pbt``, ``pb2``, ``halving`` or ``replay`` (:data:`SEARCHES`); the search's
  own settings are the launcher's other keys (``hydra/launcher=pbt``, ``pb2``, ``halving`` and
  ``pbt_replay`` preset ``search`` and them), read by its settings class in
  :mod:`drone_torchrl.training.pbt` / :mod:`~drone_torchrl.training.pb2`.
- ``folders``: ``population`` (the default): the jobs are grouped as ``fused`` groups them (configs
  equal but for the per-agent keys: ``seed``, ``algo.lr``, ``algo.gamma``, ``algo.weight_decay``);
  each group becomes one population run (:mod:`drone_torchrl.training.population_record`) in
  ``<hydra.sweep.dir>/population_<g>``, with one ``.hydra/`` record (``config.yaml``: the group's
  first job, ``overrides.yaml``: every job's overrides). Running the same command again continues
  each population from its checkpoint (finished ones return at once). ``job``
  (``hydra/launcher=fused``, no search): every job keeps its own folder, lock, ``.hydra/``, CSV,
  logger and checkpoints (:func:`train_populations`, which ``slurm_population`` runs in each of
  its SLURM jobs); at tens of thousands of agents that bookkeeping is most of the work.

Job folders (``folders=job``): Hydra's launchers run one job per process (or one after another).
REINFORCE on this drone is so small that a job spends its time in per-step overhead, not
arithmetic, so :func:`train_populations` gives each job its folder, ``.hydra/`` record
(``config.yaml``, ``hydra.yaml``, ``overrides.yaml``) and log file like the basic launcher, and then
trains all compatible jobs as one population with ``backend=fast``
(:func:`drone_torchrl.training.trainer.train_jobs`; a learner that trains one agent at a time,
PPO's or the reference's, trains them one after another). Each job still ends with its own CSV,
TensorBoard run and checkpoints, so ``drone-report`` and ``resume`` work unchanged. It sets the
folders up itself (``_job_folder()``) instead of through Hydra's ``run_job``: that one deep-copies
the whole config (Hydra's part included) four times and re-configures logging per job, a large
part of a sweep of small jobs; here nothing runs inside a job until training, so it only needs the
files. A job that fails is reported as failed (Hydra then exits non-zero after printing the sweep
summary); the other jobs still train. A job that repeats an earlier one (the same folder, e.g.
``seed=0,0``) is trained once and both report its outcome, as with the basic launcher, whose second
run would find the job finished.

Each job's Hydra return value is its agent's final running-mean return, under any launcher.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import os
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.utils import JobReturn, JobStatus, configure_log, filter_overrides, setup_globals
from hydra.errors import CompactHydraException
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from drone_torchrl.checks import ConfigError, as_override
from drone_torchrl.io.storage import write_atomically
from drone_torchrl.io.yaml_text import save_yaml, to_yaml
from hydra_plugins.drone_torchrl_launcher.compose import Batch, checked_batch, hydra_record, sweep_configs

if TYPE_CHECKING:
    from drone_torchrl.training.agents import AgentTable
    from drone_torchrl.training.pbt import SearchSettings

log = logging.getLogger(__name__)

POPULATION_DIR = "population_{}"
#: Each search's settings class (``module:class``; the plug-in imports no training code until it runs):
#: its fields are the search's ``hydra.launcher`` keys (but those it derives, and its ``unused``).
SEARCHES = {
    "pbt": "drone_torchrl.training.pbt:PBTSettings",
    "pb2": "drone_torchrl.training.pb2:PB2Settings",
    "halving": "drone_torchrl.training.pbt:HalvingSettings",
    "replay": "drone_torchrl.training.pbt:ReplaySettings",
}


class JobFailed(CompactHydraException):
    """A job of a fused sweep that failed: one line (the traceback is in ``<job>/FAILED.txt``)."""


class _JobReturn(JobReturn):
    """A ``JobReturn`` whose ``hydra_cfg`` is built from its plain container when first read: nothing
    here reads it, and building a ``DictConfig`` of Hydra's node took a third of a job's set-up."""

    _hydra_container: dict | None = None
    _hydra_cfg: DictConfig | None = None

    @property  # type: ignore[override]
    def hydra_cfg(self) -> DictConfig | None:
        if self._hydra_cfg is None and self._hydra_container is not None:
            self._hydra_cfg = OmegaConf.create(self._hydra_container)
        return self._hydra_cfg

    @hydra_cfg.setter
    def hydra_cfg(self, value: DictConfig | None) -> None:
        self._hydra_cfg = value


def job_output_dir(cfg: DictConfig, idx: int) -> str:
    """Job number ``idx``'s folder (``hydra.sweep.dir``/``hydra.sweep.subdir``, absolute); sets the
    job's number and id in ``cfg``'s ``hydra`` node first, as the subdir may name them."""
    with read_write(cfg), open_dict(cfg):
        cfg.hydra.job.id = cfg.hydra.job.num = idx
        subdir = str(OmegaConf.select(cfg, "hydra.sweep.subdir"))
    return os.path.abspath(os.path.join(str(cfg.hydra.sweep.dir), subdir))


def _job_folder(hydra_context: HydraContext, cfg: DictConfig, output_dir: Path) -> JobReturn:
    """The job's folder (:func:`job_output_dir`) with what Hydra's ``run_job`` writes before it calls
    the task: ``.hydra/`` and the (empty) job log; returns the job's ``JobReturn``. ``cfg`` (this job's own
    config; its ``hydra`` node may be shared with other jobs) loses its ``hydra`` node: the returned
    ``JobReturn.cfg`` is the job's config. Hydra callbacks' ``on_job_start`` get the job's whole
    config; its ``hydra`` node may be rewritten for the next job afterwards (keep a copy, not it)."""
    with read_write(cfg), open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(output_dir)
        log_file = OmegaConf.select(cfg, "hydra.job_logging.handlers.file.filename", default=None)
        hydra_cfg = hydra_record(cfg.hydra)
        ret = _JobReturn(
            list(cfg.hydra.overrides.task), working_dir=os.getcwd(), task_name=cfg.hydra.job.name
        )
        output_subdir = cfg.hydra.output_subdir
        hydra_context.callbacks.on_job_start(config=cfg, task_function=None)
        del cfg["hydra"]
    ret.cfg, ret._hydra_container = cfg, hydra_cfg
    output_dir.mkdir(parents=True, exist_ok=True)
    if output_subdir is not None:
        _save_record(output_dir / output_subdir, cfg, hydra_cfg, to_yaml(ret.overrides))
    if log_file is not None:
        Path(log_file).touch()
    return ret


def train_populations(
    hydra_context: HydraContext,
    config: DictConfig,
    job_overrides: Sequence[Sequence[str]],
    job_numbers: Sequence[int],
    validated: bool = False,
) -> list[JobReturn]:
    """Set up the jobs' folders and train them, those that can share a population together (in this
    process); one ``JobReturn`` per job. The fused launcher runs it on this machine, the
    ``slurm_population`` launcher inside each of its SLURM jobs. ``job_numbers``: each job's Hydra
    job number (``hydra.job.num``). ``validated``: the sweeper has validated every job's config on
    this machine (then :func:`~drone_torchrl.training.jobs.prepare` does not again)."""
    from drone_torchrl.io import run_lock
    from drone_torchrl.training.jobs import prepare, record_failure
    from drone_torchrl.training.trainer import Outcome, train_jobs

    Path(str(config.hydra.sweep.dir)).mkdir(parents=True, exist_ok=True)
    log.info(f"Launching {len(job_overrides)} jobs as populations")
    # Per job: its prepared Job, its Outcome if it failed before training, or, for a job that repeats
    # an earlier one (seed=0,0: the same folder), the earlier one's position: it trains once.
    jobs: list = []
    folders: dict[Path, int] = {}  # run folder -> the position of the job that owns it
    returns: list[JobReturn] = []
    configs = sweep_configs(hydra_context.config_loader, config, job_overrides)
    for position, (idx, overrides, sweep_config) in enumerate(
        zip(job_numbers, job_overrides, configs, strict=True)
    ):
        log.info(f"\t#{idx} : {' '.join(filter_overrides(overrides))}")
        run_dir = Path(job_output_dir(sweep_config, idx))
        try:
            run_lock.hold(run_dir)  # the job's folder is this process's before anything is written into it
        except (ConfigError, OSError) as err:
            print(f"{run_dir}: job not started: {err}")
            returns.append(_JobReturn(overrides=list(overrides), cfg=sweep_config))
            jobs.append(Outcome(run_dir, error=err))
            continue
        returns.append(ret := _job_folder(hydra_context, sweep_config, run_dir))
        if run_dir in folders:
            first = job_numbers[folders[run_dir]]
            print(f"{run_dir}: job #{idx} is job #{first} again (the same folder); trained once")
            jobs.append(folders[run_dir])
            continue
        folders[run_dir] = position
        # Training comes later, for all jobs at once; here each job is checked and registered.
        try:
            jobs.append(prepare(ret.cfg, run_dir, requested=overrides, validated=validated))
        except Exception as err:  # noqa: BLE001  (recorded; the other jobs go on)
            print(f"{run_dir}: job failed: {record_failure(run_dir, err)}")
            jobs.append(Outcome(run_dir, error=err))
    try:
        trained = iter(train_jobs([j for j in jobs if not isinstance(j, Outcome | int)]))
    finally:
        for run_dir in folders:  # jobs refused before training are let go too
            run_lock.release(run_dir)
    outcomes: list[Outcome] = []
    for ret, job in zip(returns, jobs, strict=True):
        outcomes.append(
            outcomes[job] if isinstance(job, int) else job if isinstance(job, Outcome) else next(trained)
        )
        _report(ret, outcomes[-1])
        hydra_context.callbacks.on_job_end(config=ret.cfg, job_return=ret)
    return returns


def _save_record(record: Path, cfg: DictConfig, hydra: dict, overrides: str) -> None:
    """Hydra's record of a job or population run in ``record`` (its ``.hydra/``): ``config.yaml``,
    ``hydra.yaml`` and ``overrides.yaml`` (``overrides``: its YAML text)."""
    record.mkdir(exist_ok=True)
    save_yaml(cfg, record / "config.yaml")
    save_yaml(hydra, record / "hydra.yaml")
    write_atomically(record / "overrides.yaml", overrides.encode("utf-8"))


def _report(ret: JobReturn, outcome: Any) -> None:
    """Set a job's Hydra status and return value from its :class:`~drone_torchrl.training.trainer.Outcome`."""
    if outcome.error is None:
        ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
    else:
        reason = f"{type(outcome.error).__name__}: {outcome.error}"
        ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")


class PopulationLauncher(Launcher):
    """A sweep trained as one batch (the module's docstring); ``settings``: the search's keys."""

    config: DictConfig | None = None
    hydra_context: HydraContext | None = None
    task_function: TaskFunction | None = None

    def __init__(self, search: str = "none", folders: str = "population", **settings: Any) -> None:
        self.per_job = folders == "job"
        # Each batch checked before the sweep folder was written (:meth:`check`), by its jobs: its
        # configs and groups (None with folders=job: its jobs' configs are composed again, with folders).
        self._checked: dict[tuple[tuple[str, ...], ...], tuple[Batch, list] | None] = {}
        self.replay = search == "replay"
        self._runs = 0  # population runs of the batches launched so far: the next batch's are numbered on
        try:
            self.search: SearchSettings | None = _settings(search, folders, settings)
        except ConfigError as err:  # Hydra makes it before any job starts: one line, nothing written
            sys.exit(f"drone-train: error: {err}")

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config, self.hydra_context, self.task_function = config, hydra_context, task_function

    def check(self, job_overrides: Sequence[Sequence[str]], batch: Batch) -> None:
        """Group and check a batch's jobs (composed and checked: :func:`.compose.checked_batch`) as
        :meth:`launch` will train them, before any folder.

        Raises :class:`~drone_torchrl.checks.ConfigError` (one line) for the first group refused: what
        :func:`~drone_torchrl.training.trainer.check_population` refuses (learner, budget, memory, a
        search the budget or the population cannot hold). The hydra/sweeper=population sweeper calls
        it for every batch before it writes the sweep folder; :meth:`launch` then trains the groups
        kept here, and jobs in folders of their own (``folders=job``) are not validated again.
        """
        from drone_torchrl.training.trainer import check_population

        groups = None if self.per_job else self._groups(job_overrides, batch)
        for agents, _ in groups or ():
            check_population(agents, self.search)
        self._checked[tuple(map(tuple, job_overrides))] = None if groups is None else (batch, groups)

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.training.jobs import sweep_summary
        from drone_torchrl.training.trainer import Outcome, train_population

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        key = tuple(map(tuple, job_overrides))
        validated, checked = key in self._checked, self._checked.pop(key, None)
        if self.per_job:
            numbers = range(initial_job_idx, initial_job_idx + len(job_overrides))
            returns = train_populations(self.hydra_context, self.config, job_overrides, numbers, validated)
            if not validated and any(ret.status == JobStatus.FAILED for ret in returns):
                # Another sweeper than hydra/sweeper=population (which prints the end-of-sweep
                # summary itself) stops at the first failed job and skips the summary.
                print(sweep_summary(Path(str(self.config.hydra.sweep.dir))))
            return returns
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        log.info(f"Launching {len(job_overrides)} jobs as population runs in {sweep_dir}")
        if checked is None:  # another sweeper than hydra/sweeper=population
            try:
                batch = checked_batch(self.hydra_context.config_loader, self.config, job_overrides)
                checked = batch, self._groups(job_overrides, batch)
            except ConfigError as err:
                sys.exit(f"drone-train: error: {err}")
        batch, groups = checked
        if batch.values is not None:
            log.info(
                f"{len(job_overrides)} jobs differ only in per-agent values: one population from one config"
            )
        returns = [
            JobReturn(overrides=list(o), cfg=c) for o, c in zip(job_overrides, batch.configs, strict=True)
        ]
        refused: list[ConfigError] = []
        first, self._runs = self._runs, self._runs + len(groups)
        for number, (agents, members) in enumerate(groups, start=first):
            run_dir = sweep_dir / POPULATION_DIR.format(number)
            names = [" ".join(job_overrides[i]) for i in members]
            # One job a line in YAML's flow style (JSON's strings are YAML's): the block style of
            # to_yaml takes seconds at tens of thousands of jobs.
            lines = "".join(f"- {json.dumps(list(job_overrides[i]))}\n" for i in members)
            record = partial(_save_record, run_dir / ".hydra", agents.cfg, batch.hydra_record, lines)
            try:
                done = train_population(agents, names, run_dir, record, self.search)
            except ConfigError as err:  # refused before training: the other groups go on
                done = [Outcome(run_dir, error=err)] * len(members)
                refused.append(err)
            for i, outcome in zip(members, done, strict=True):
                _report(returns[i], outcome)
        if refused:  # no folder for the sweep's summary to count: a failure all the same, in one line
            others = (
                f" ({len(refused) - 1} other population run(s) not started too)" if len(refused) > 1 else ""
            )
            sys.exit(f"drone-train: error: {refused[0]}{others}")
        return returns

    def _groups(
        self, job_overrides: Sequence[Sequence[str]], batch: Batch
    ) -> list[tuple[AgentTable, list[int]]]:
        """A checked batch's population runs: each an agent table and its jobs' positions.

        Jobs that differ only in per-agent numbers are one population from one config
        (:func:`.compose.agent_columns`); else the jobs are grouped as the fused launcher groups them
        (:func:`~drone_torchrl.training.jobs.group_key`). A replay refuses a job that sets a key its
        schedule sets.
        """
        from drone_torchrl.training.agents import AgentTable
        from drone_torchrl.training.jobs import group_key

        if self.replay:
            _refuse_scheduled_keys(self.search, job_overrides)
        if batch.values is not None:
            return [(AgentTable(batch.configs[0], batch.values), list(range(len(job_overrides))))]
        members: dict[str, list[int]] = {}
        for position, cfg in enumerate(batch.configs):
            members.setdefault(group_key(cfg), []).append(position)
        return [(AgentTable.of([batch.configs[i] for i in group]), group) for group in members.values()]


def _settings(search: Any, folders: Any, settings: dict[str, Any]) -> SearchSettings | None:
    """The search's settings from the launcher's keys, each checked (:class:`ConfigError`, one line)."""
    if folders not in ("population", "job"):
        expected = "population (a folder per population run) or job (a folder per job)"
        raise ConfigError(f"hydra.launcher.folders={_typed(folders)} is not allowed; expected {expected}")
    if search != "none" and (not isinstance(search, str) or search not in SEARCHES or folders == "job"):
        expected = (
            "none with hydra.launcher.folders=job" if folders == "job" else "none, " + ", ".join(SEARCHES)
        )
        raise ConfigError(f"hydra.launcher.search={_typed(search)} is not allowed; expected {expected}")
    module, _, name = SEARCHES.get(search, "").partition(":")
    settings_class = getattr(importlib.import_module(module), name) if module else None
    derived = ("ranges", "schedule", *getattr(settings_class, "unused", ()))
    keys = [f.name for f in dataclasses.fields(settings_class) if f.name not in derived] if module else []
    for key, value in settings.items():
        if key not in keys:
            raise ConfigError(
                f"hydra.launcher.{key}={_typed(value)} is not allowed: hydra.launcher.search={search} has no key "
                f"{key!r}; its keys: {', '.join(sorted(keys)) or 'none'}"
            )
    return settings_class.of(settings) if settings_class else None


def _typed(value: Any) -> str:
    """``value`` as the command line gives it (a string as it is, null as null)."""
    return value if isinstance(value, str) else as_override(value)


def _refuse_scheduled_keys(search: Any, job_overrides: Sequence[Sequence[str]]) -> None:
    """Refuse a job of a replay that sets a key the replayed schedule sets: its value would never be used."""
    scheduled = {key for _, values in search.schedule for key, _ in values}
    for job in job_overrides:
        for line in job:
            key = line.partition("=")[0].lstrip("+~")
            if key in scheduled:
                raise ConfigError(
                    f"{line} is not allowed with hydra/launcher=pbt_replay: the replayed schedule sets "
                    f"{', '.join(sorted(scheduled))} (agent {search.agent} of {search.run}); "
                    f"expected no {key}= (sweep seed= and the keys the schedule leaves)"
                )
