"""``hydra/launcher=fused``: the jobs of a sweep trained side by side by the fused engine.

Hydra's launchers run one job per process (or one after another). REINFORCE on this drone is so
small that a job spends its time in per-step overhead, not arithmetic, so this launcher gives
each job its folder, ``.hydra/`` record and log exactly like the basic launcher, and then trains
all compatible jobs (configs equal but for ``seed``, ``algo.lr``, ``algo.gamma``) as one batch of
agents with :func:`drone_torchrl.fused.train_fused`. Each job still ends with its own CSV,
TensorBoard run and checkpoints, so ``drone-report`` and ``resume`` work unchanged.

On a cluster use ``hydra/launcher=submitit_slurm`` (or ``ray``) instead: they spread the jobs over
machines, each job then training alone.
"""

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus, configure_log, filter_overrides, run_job, setup_globals
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, open_dict

log = logging.getLogger(__name__)


@dataclass
class FusedLauncherConf:
    _target_: str = "hydra_plugins.drone_torchrl_launcher.fused_launcher.FusedLauncher"


ConfigStore.instance().store(
    group="hydra/launcher", name="fused", node=FusedLauncherConf, provider="drone_torchrl"
)


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
        from drone_torchrl.fused import ENGINE, train_fused

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        Path(str(self.config.hydra.sweep.dir)).mkdir(parents=True, exist_ok=True)
        log.info(f"Launching {len(job_overrides)} jobs as one fused batch")
        jobs: list[tuple[DictConfig, Path]] = []

        def register(cfg: DictConfig) -> None:
            # Runs inside Hydra's run_job: the job folder, .hydra/ and log exist; training comes later.
            with open_dict(cfg):
                cfg.engine = ENGINE
            jobs.append((cfg, Path(HydraConfig.get().runtime.output_dir)))

        returns: list[JobReturn] = []
        for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
            log.info(f"\t#{idx} : {' '.join(filter_overrides(overrides))}")
            sweep_config = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
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
        results = train_fused(jobs)
        for ret, value in zip(returns, results, strict=True):
            ret.return_value = value
            ret.status = JobStatus.COMPLETED
        return returns
