"""``hydra/launcher=fused``: the jobs of a sweep trained as populations, each job keeping its own folder.

Hydra's launchers run one job per process (or one after another). REINFORCE on this drone is so
small that a job spends its time in per-step overhead, not arithmetic, so this launcher gives
each job its folder, ``.hydra/`` record and log exactly like the basic launcher, and then trains
all compatible jobs (configs equal but for ``seed``, ``algo.lr``, ``algo.gamma``) as one population
with ``engine=fused`` (:func:`drone_torchrl.training.trainer.train_jobs`). Each job still ends with
its own CSV, TensorBoard run and checkpoints, so ``drone-report`` and ``resume`` work unchanged.

A job that fails is reported as failed (Hydra then exits non-zero after printing the sweep summary);
the other jobs still train.

On a cluster use ``hydra/launcher=submitit_slurm`` (or ``ray``) instead: they spread the jobs over
machines, each job then training alone.
"""

import logging
from collections.abc import Sequence
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus, configure_log, filter_overrides, run_job, setup_globals
from hydra.errors import CompactHydraException
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, open_dict

from hydra_plugins.drone_torchrl_launcher import schemas  # noqa: F401  (registers hydra/launcher=fused)

log = logging.getLogger(__name__)
ENGINE = "fused"


class JobFailed(CompactHydraException):
    """A job of a fused sweep that failed: one line (the traceback is in ``<job>/FAILED.txt``)."""


class FusedLauncher(Launcher):
    def __init__(self) -> None:
        super().__init__()
        self.config: DictConfig | None = None
        self.hydra_context: HydraContext | None = None
        self.task_function: TaskFunction | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.hydra_context = hydra_context
        self.task_function = task_function

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.config import ConfigError
        from drone_torchrl.training.jobs import prepare, record_failure, sweep_summary
        from drone_torchrl.training.trainer import Outcome, train_jobs
        from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        log.info(f"Launching {len(job_overrides)} jobs as populations (engine={ENGINE})")
        jobs: list = []
        folders: list[Path] = []

        def register(cfg: DictConfig) -> None:
            # Runs inside Hydra's run_job: the job folder, .hydra/ and log exist, and the job's
            # command line is known (prepare reads it); training comes later, for all jobs at once.
            run_dir = Path(HydraConfig.get().runtime.output_dir)
            try:
                if run_dir in folders:  # e.g. seed=0,0: two agents would write one folder
                    raise ConfigError(
                        f"{run_dir} is also job #{folders.index(run_dir)}'s folder: a duplicate job"
                    )
                folders.append(run_dir)
                jobs.append(prepare(cfg, run_dir if cfg.resume is None else None, engine=ENGINE))
            except Exception as err:  # noqa: BLE001  (recorded; the other jobs go on)
                print(f"{run_dir}: job failed: {record_failure(run_dir, err)}")
                jobs.append(Outcome(run_dir, error=err))

        returns: list[JobReturn] = []
        configs = sweep_configs(self.hydra_context.config_loader, self.config, job_overrides)
        for idx, (overrides, sweep_config) in enumerate(
            zip(job_overrides, configs, strict=True), initial_job_idx
        ):
            # Back to Hydra's own logging between jobs (run_job switched to the last job's log file).
            configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
            log.info(f"\t#{idx} : {' '.join(filter_overrides(overrides))}")
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = idx
                sweep_config.hydra.job.num = idx
            returns.append(
                run_job(
                    hydra_context=self.hydra_context,
                    task_function=register,
                    config=sweep_config,
                    job_dir_key="hydra.sweep.dir",
                    job_subdir_key="hydra.sweep.subdir",
                )
            )
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        prepared = [j for j in jobs if not isinstance(j, Outcome)]
        trained = iter(train_jobs(prepared))
        outcomes = [j if isinstance(j, Outcome) else next(trained) for j in jobs]
        failed = False
        for ret, outcome in zip(returns, outcomes, strict=True):
            if outcome.error is None:
                ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
            else:
                failed = True
                reason = f"{type(outcome.error).__name__}: {outcome.error}"
                ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")
        if failed and not str(self.config.hydra.sweeper._target_).endswith("PopulationSweeper"):
            # Another sweeper stops at the first failed job and skips the end-of-sweep summary.
            print(sweep_summary(sweep_dir))
        return returns
