"""``hydra/launcher=slurm`` and ``slurm_population``: sweeps on a SLURM cluster, waiting for every job.

- ``slurm``: one SLURM job per sweep job (Hydra's submitit launcher, see below).
- ``slurm_population``: the sweep cut into populations of ``agents_per_job`` jobs, one SLURM job each, which
  trains its jobs as one population with the fast engine (:func:`~.population_launcher.train_populations`, as
  ``hydra/launcher=fused`` does on one machine; on the node's GPU with ``device=cuda``). A 256-agent landscape
  is then 8 cluster jobs of 32 agents instead of 256 jobs of a few seconds of work each. Every job folder is
  the one it would have alone. Jobs that share a folder (``seed=0,0``, or values of keys left out of folder
  names such as ``threads``) go into the same SLURM job, which trains that folder once
  (:func:`population_groups`): two SLURM jobs never write one folder at the same time.

Both are one launcher (:class:`SlurmLauncher`; ``slurm_population``'s schema adds ``agents_per_job``):
one job array, one array task per group of sweep jobs (a single job under ``slurm``, run by Hydra's
submitit launcher's own ``__call__``; a population under ``slurm_population``), its executor built
as that launcher builds it. That launcher ends with ``[job.results()[0] for job in jobs]``: the
first job that did not finish (cancelled with ``scancel``, out of memory, a node failure) raises
while the other jobs are still running, so the sweep stops with a traceback and its summary is
never printed. This one waits for every array task and reports each sweep job of one that did not
finish as FAILED: SLURM's state (e.g. ``CANCELLED``) goes into the job's ``FAILED.txt`` (the folder
found at submission, :func:`~.population_launcher.job_output_dir`), the end-of-sweep summary lists
it, and running the same command again continues it from its checkpoint (finished jobs return at
once).

A job that reaches its time limit is requeued by submitit (``max_num_timeout`` times; the signal
comes ``signal_delay_s`` before the limit) and continues from ``<job>/checkpoints/last.pt``.

Needs the ``submitit`` extra; without it this module defines nothing (Hydra imports every module
of ``hydra_plugins`` when it looks for plugins).
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, JobStatus, filter_overrides, setup_globals
from omegaconf import OmegaConf

from drone_torchrl.compat import submitit_cluster, submitit_params
from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs
from hydra_plugins.drone_torchrl_launcher.population_launcher import JobFailed, job_output_dir

try:
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher as _SubmititSlurm
except ImportError:  # the submitit extra is not installed
    _SubmititSlurm = None

log = logging.getLogger(__name__)
# How often to ask SLURM (through submitit's sacct watcher) whether the jobs are done.
POLL_S = 2.0


def population_groups(folders: Sequence[str], per_job: int) -> list[list[int]]:
    """The sweep's jobs (by position) cut into SLURM jobs of up to ``per_job`` distinct folders, in
    order; a job whose folder an earlier job has goes with that job (which trains the folder once)."""
    groups: dict[int, list[int]] = {}
    owner: dict[str, int] = {}  # folder -> its group: the n-th distinct folder goes to group n // per_job
    for position, folder in enumerate(folders):
        groups.setdefault(owner.setdefault(folder, len(owner) // per_job), []).append(position)
    return list(groups.values())


if _SubmititSlurm is not None:

    class SlurmLauncher(_SubmititSlurm):
        """Hydra's submitit SLURM launcher that waits for every job and reports unfinished ones as FAILED.

        Each SLURM array task gets a group of sweep jobs: one job, run as Hydra's launcher runs it
        (``slurm``), or, with ``agents_per_job`` (``slurm_population``'s schema has it), a population.
        """

        def __init__(self, **params: Any) -> None:
            super().__init__(**params)
            self.per_job = per_job = params.get("agents_per_job")  # slurm_population's key; slurm has none
            if "agents_per_job" in params and (type(per_job) is not int or per_job < 1):
                # Hydra instantiates the launcher before any job starts: one line, nothing written.
                sys.exit(
                    f"drone-train: error: hydra.launcher.agents_per_job={per_job} is not allowed; "
                    "expected an integer >= 1"
                )

        def _executor(self):
            """The submitit executor with this launcher's parameters (as Hydra's launcher builds it)."""
            import submitit

            cluster, params = submitit_cluster(self), submitit_params(self)
            executor = submitit.AutoExecutor(
                cluster=cluster,
                folder=params["submitit_folder"],
                **{f"{cluster}_max_num_timeout": params["max_num_timeout"]},
            )
            base = set(OmegaConf.structured(BaseQueueConf).keys())
            executor.update_parameters(
                **{
                    key if key in base else f"{cluster}_{key}": value
                    for key, value in params.items()
                    if key not in {"submitit_folder", "max_num_timeout", "agents_per_job"}
                }
            )
            return executor

        def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
            from submitit.core.utils import UncompletedJobError

            from drone_torchrl.training.jobs import record_failure

            assert self.config is not None and self.hydra_context is not None
            sweep_dir = Path(str(self.config.hydra.sweep.dir))
            sweep_dir.mkdir(parents=True, exist_ok=True)
            numbers = range(initial_job_idx, initial_job_idx + len(job_overrides))
            configs = sweep_configs(self.hydra_context.config_loader, self.config, job_overrides)
            folders = [job_output_dir(cfg, idx) for idx, cfg in zip(numbers, configs, strict=True)]
            if self.per_job is None:  # one array task per sweep job
                groups = [[position] for position in range(len(job_overrides))]
                log.info(f"Submitit 'slurm' sweep output dir : {sweep_dir}")
                for idx, overrides in zip(numbers, job_overrides, strict=True):
                    log.info(f"\t#{idx} : {' '.join(filter_overrides(overrides))}")
            else:  # populations of up to agents_per_job folders, a folder's jobs in one
                groups = population_groups(folders, self.per_job)
                log.info(
                    f"Submitit 'slurm' sweep output dir : {sweep_dir}: {len(job_overrides)} jobs as "
                    f"{len(groups)} SLURM job(s) of up to {self.per_job} agents"
                )
            jobs = self._executor().map_array(  # one array task per group
                self,
                [[list(job_overrides[i]) for i in group] for group in groups],
                [[numbers[i] for i in group] for group in groups],
                [Singleton.get_state()] * len(groups),
            )
            log.info(
                f"Submitted SLURM job(s) {', '.join(sorted({job.job_id.split('_')[0] for job in jobs}))}"
            )
            while not all(job.done() for job in jobs):
                time.sleep(POLL_S)
            returns: dict[int, JobReturn] = {}  # by the job's position in the sweep
            for job, group in zip(jobs, groups, strict=True):
                try:
                    returns.update(zip(group, job.results()[0], strict=True))
                except UncompletedJobError:  # each of its jobs FAILED, with FAILED.txt
                    error = JobFailed(
                        f"SLURM job {job.job_id} ended {job.state} before the run finished; "
                        "run the same command again to continue it from its checkpoint"
                    )
                    for i in group:
                        print(f"{folders[i]}: job failed: {record_failure(Path(folders[i]), error)}")
                        returns[i] = JobReturn(
                            list(job_overrides[i]), status=JobStatus.FAILED, _return_value=error
                        )
            return [returns[position] for position in range(len(job_overrides))]

        def __call__(self, group: list[list[str]], numbers: list[int], singleton_state) -> list[JobReturn]:
            """Inside the array task: its job as Hydra's launcher runs it, or its jobs as one population
            (:func:`~.population_launcher.train_populations`); ``checkpoint`` requeues it."""
            from hydra_plugins.drone_torchrl_launcher.population_launcher import train_populations

            if self.per_job is None:
                return [super().__call__(group[0], "hydra.sweep.dir", numbers[0], "", singleton_state)]
            Singleton.set_state(singleton_state)
            setup_globals()
            return train_populations(self.hydra_context, self.config, group, numbers)

    class SlurmPopulationLauncher(SlurmLauncher):
        """``slurm_population``'s target: :class:`SlurmLauncher` (its ``agents_per_job`` makes the populations)."""


# The launchers this module defines, for drone-train to register: none without the submitit extra.
PLUGINS: tuple[type, ...] = () if _SubmititSlurm is None else (SlurmLauncher, SlurmPopulationLauncher)
