"""``hydra/launcher=population``: each group of a sweep's jobs trained as ONE population run, in ONE folder.

The fused launcher gives every job its folder (lock, ``.hydra/``, CSV, logger, checkpoints); at
tens of thousands of agents that bookkeeping is most of the work. Here the jobs are grouped as the
fused launcher groups them (configs equal but for the per-agent keys: ``seed``, ``algo.lr``,
``algo.gamma``, ``algo.weight_decay``); each group becomes one population run
(:mod:`drone_torchrl.training.population_record`) in ``<hydra.sweep.dir>/population_<g>``, with one
``.hydra/`` record (``config.yaml``: the group's first job, ``overrides.yaml``: every job's
overrides). Running the same command again continues each population from its checkpoint
(finished ones return at once). Each job's Hydra return value is its agent's final running-mean
return, as under the other launchers.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from hydra.core.utils import JobReturn, JobStatus, configure_log, setup_globals
from omegaconf import OmegaConf, open_dict, read_write

from drone_torchrl.io.yaml_text import save_yaml
from hydra_plugins.drone_torchrl_launcher.fused_launcher import FusedLauncher, JobFailed, _JobReturn

log = logging.getLogger(__name__)

POPULATION_DIR = "population_{}"


class PopulationLauncher(FusedLauncher):
    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.config import ConfigError, validate
        from drone_torchrl.training.jobs import group_key
        from drone_torchrl.training.trainer import Outcome, train_population
        from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        log.info(f"Launching {len(job_overrides)} jobs as population runs in {sweep_dir}")
        returns: list[JobReturn] = []
        outcomes: list[Outcome | None] = []
        groups: dict[str, list[int]] = {}
        hydra_record: dict | None = None
        for position, (overrides, cfg) in enumerate(
            zip(
                job_overrides,
                sweep_configs(self.hydra_context.config_loader, self.config, job_overrides),
                strict=True,
            )
        ):
            with read_write(cfg), open_dict(cfg):
                if hydra_record is None:
                    hydra_record = {
                        "hydra": OmegaConf.to_container(cfg.hydra, resolve=False, enum_to_str=True)
                    }
                del cfg["hydra"]
            ret = _JobReturn(overrides=list(overrides))
            ret.cfg = cfg
            returns.append(ret)
            outcomes.append(None)
            try:
                validate(cfg)
            except ConfigError as err:  # this job only; the others train
                print(f"job #{initial_job_idx + position} ({' '.join(overrides)}) not started: {err}")
                outcomes[position] = Outcome(sweep_dir, error=err)
                continue
            groups.setdefault(group_key(cfg), []).append(position)
        for number, members in enumerate(groups.values()):
            run_dir = sweep_dir / POPULATION_DIR.format(number)
            cfgs = [returns[i].cfg for i in members]
            names = [" ".join(job_overrides[i]) for i in members]

            def write_record(cfgs=cfgs, run_dir=run_dir, members=members) -> None:
                record = run_dir / ".hydra"
                record.mkdir(exist_ok=True)
                save_yaml(cfgs[0], record / "config.yaml")
                save_yaml(hydra_record, record / "hydra.yaml")
                save_yaml([list(job_overrides[i]) for i in members], record / "overrides.yaml")

            try:
                done = train_population(cfgs, names, run_dir, write_record)
            except ConfigError as err:  # refused before training: one line, the other groups go on
                print(f"{run_dir}: population not started: {err}")
                done = [Outcome(run_dir, error=err)] * len(members)
            for i, outcome in zip(members, done, strict=True):
                outcomes[i] = outcome
        for ret, outcome in zip(returns, outcomes, strict=True):
            assert outcome is not None
            if outcome.error is None:
                ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
            else:
                reason = f"{type(outcome.error).__name__}: {outcome.error}"
                ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")
        return returns
