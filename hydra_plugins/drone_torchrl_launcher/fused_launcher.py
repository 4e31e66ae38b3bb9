"""The jobs of a sweep trained as populations, each job keeping its own folder (``hydra/launcher=fused``).

What :class:`.population_launcher.PopulationLauncher` does with ``folders=job`` (the ``fused``
option), and ``slurm_population`` in each of its SLURM jobs. Hydra's launchers run one job per
process (or one after another). REINFORCE on this drone is so small that a job spends its time in
per-step overhead, not arithmetic, so :func:`train_populations` gives
each job its folder, ``.hydra/`` record (``config.yaml``, ``hydra.yaml``, ``overrides.yaml``) and
log file like the basic launcher, and then trains all compatible jobs (configs equal but for
``seed``, ``algo.lr``, ``algo.gamma``, ``algo.weight_decay``) as one population with
``backend=fast`` (:func:`drone_torchrl.training.trainer.train_jobs`; a learner that trains one agent
at a time, PPO's or the reference's, trains them one after another). Each job still ends with its
own CSV, TensorBoard run and checkpoints, so ``drone-report`` and ``resume`` work unchanged.

It sets the folders up itself (``_job_folder()``) instead of through Hydra's ``run_job``: that
one deep-copies the whole config (Hydra's part included) four times and re-configures logging per
job, a large part of a sweep of small jobs; here nothing runs inside a
job until training, so it only needs the files.

A job that fails is reported as failed (Hydra then exits non-zero after printing the sweep summary);
the other jobs still train. A job that repeats an earlier one (the same folder, e.g. ``seed=0,0``)
is trained once and both report its outcome, as with the basic launcher, whose second run would
find the job finished.

On a cluster use ``hydra/launcher=submitit_slurm`` (or ``ray``) instead: they spread the jobs over
machines, each job then training alone.
"""

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus, filter_overrides
from hydra.errors import CompactHydraException
from hydra.types import HydraContext
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from drone_torchrl.io.yaml_text import save_yaml

log = logging.getLogger(__name__)


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


def _job_folder(hydra_context: HydraContext, cfg: DictConfig, idx: int) -> tuple[JobReturn, Path]:
    """The job's folder with what Hydra's ``run_job`` writes before it calls the task: ``.hydra/``
    and the (empty) job log; returns the job's ``JobReturn`` and folder. ``cfg`` (this job's own
    config; its ``hydra`` node may be shared with other jobs) loses its ``hydra`` node: the returned
    ``JobReturn.cfg`` is the job's config. Hydra callbacks' ``on_job_start`` get the job's whole
    config; its ``hydra`` node may be rewritten for the next job afterwards (keep a copy, not it)."""
    with read_write(cfg), open_dict(cfg):
        output_dir = job_output_dir(cfg, idx)
        cfg.hydra.runtime.output_dir = output_dir
        log_file = OmegaConf.select(cfg, "hydra.job_logging.handlers.file.filename", default=None)
        hydra_cfg = {"hydra": OmegaConf.to_container(cfg.hydra, resolve=False, enum_to_str=True)}
        ret = _JobReturn(overrides=list(cfg.hydra.overrides.task), working_dir=os.getcwd())
        ret.task_name = cfg.hydra.job.name
        output_subdir = cfg.hydra.output_subdir
        hydra_context.callbacks.on_job_start(config=cfg, task_function=None)
        del cfg["hydra"]
    ret.cfg, ret._hydra_container = cfg, hydra_cfg
    Path(output_dir).mkdir(parents=True, exist_ok=True)
    if output_subdir is not None:
        record = Path(output_dir) / output_subdir
        record.mkdir(exist_ok=True)
        save_yaml(cfg, record / "config.yaml")
        save_yaml(hydra_cfg, record / "hydra.yaml")
        save_yaml(ret.overrides, record / "overrides.yaml")
    if log_file is not None:
        Path(log_file).touch()
    return ret, Path(output_dir)


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
    from drone_torchrl.config import ConfigError
    from drone_torchrl.io import run_lock
    from drone_torchrl.training.jobs import prepare, record_failure
    from drone_torchrl.training.trainer import Outcome, train_jobs
    from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

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
        folder = job_output_dir(sweep_config, idx)
        try:
            run_lock.hold(folder)  # the job's folder is this process's before anything is written into it
        except (ConfigError, OSError) as err:
            print(f"{folder}: job not started: {err}")
            ret = _JobReturn(overrides=list(overrides))
            ret.cfg = sweep_config
            returns.append(ret)
            jobs.append(Outcome(Path(folder), error=err))
            continue
        ret, run_dir = _job_folder(hydra_context, sweep_config, idx)
        returns.append(ret)
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
    for job in jobs:
        outcomes.append(
            outcomes[job] if isinstance(job, int) else job if isinstance(job, Outcome) else next(trained)
        )
    for ret, outcome in zip(returns, outcomes, strict=True):
        report(ret, outcome)
        hydra_context.callbacks.on_job_end(config=ret.cfg, job_return=ret)
    return returns


def report(ret: JobReturn, outcome: Any) -> None:
    """Set a job's Hydra status and return value from its :class:`~drone_torchrl.training.trainer.Outcome`."""
    if outcome.error is None:
        ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
    else:
        reason = f"{type(outcome.error).__name__}: {outcome.error}"
        ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")
