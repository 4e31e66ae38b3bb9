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

import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.utils import JobReturn, JobStatus, configure_log, setup_globals
from omegaconf import OmegaConf, open_dict, read_write

from drone_torchrl.checks import ConfigError
from drone_torchrl.io.storage import write_atomically
from drone_torchrl.io.yaml_text import save_yaml
from hydra_plugins.drone_torchrl_launcher.fused_launcher import FusedLauncher, JobFailed, _JobReturn

if TYPE_CHECKING:
    from drone_torchrl.training.agents import AgentTable
    from drone_torchrl.training.pbt import SearchSettings

log = logging.getLogger(__name__)

POPULATION_DIR = "population_{}"


class PopulationLauncher(FusedLauncher):
    search: SearchSettings | None = None

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.training.trainer import Outcome, train_population

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        log.info(f"Launching {len(job_overrides)} jobs as population runs in {sweep_dir}")
        returns: list[JobReturn] = [_JobReturn(overrides=list(overrides)) for overrides in job_overrides]
        outcomes: list[Outcome | None] = [None] * len(job_overrides)
        hydra_record, groups = self._one_table(job_overrides, returns) or self._tables(
            job_overrides, initial_job_idx, returns, outcomes, sweep_dir
        )
        refused = 0
        for number, (agents, members) in enumerate(groups):
            run_dir = sweep_dir / POPULATION_DIR.format(number)
            names = [" ".join(job_overrides[i]) for i in members]

            def write_record(cfg=agents.cfg, run_dir=run_dir, members=members) -> None:
                record = run_dir / ".hydra"
                record.mkdir(exist_ok=True)
                save_yaml(cfg, record / "config.yaml")
                save_yaml(hydra_record, record / "hydra.yaml")
                # One job a line in YAML's flow style (JSON's strings are YAML's): the block style
                # of save_yaml takes seconds at tens of thousands of jobs.
                lines = "".join(f"- {json.dumps(list(job_overrides[i]))}\n" for i in members)
                write_atomically(record / "overrides.yaml", lines.encode("utf-8"))

            try:
                done = train_population(agents, names, run_dir, write_record, self.search)
            except ConfigError as err:  # refused before training: one line, the other groups go on
                print(f"{run_dir}: population not started: {err}")
                done = [Outcome(run_dir, error=err)] * len(members)
                refused += 1
            for i, outcome in zip(members, done, strict=True):
                outcomes[i] = outcome
        for ret, outcome in zip(returns, outcomes, strict=True):
            assert outcome is not None
            if outcome.error is None:
                ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
            else:
                reason = f"{type(outcome.error).__name__}: {outcome.error}"
                ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")
        if refused:  # it has no folder for the sweep's summary to count: a failure all the same
            sys.exit(f"drone-train: {refused} population run(s) not started (the reason is above)")
        return returns

    def _one_table(
        self, job_overrides: Sequence[Sequence[str]], returns: list[JobReturn]
    ) -> tuple[dict, list[tuple[AgentTable, list[int]]]] | None:
        """Jobs that differ only in numbers of the per-agent keys, and whose values all pass: one
        population from one config (:func:`.compose.agent_columns`), no config per job; else None.
        Each job's ``JobReturn.cfg`` is then the group's config (its own values: ``agents.parquet``)."""
        from drone_torchrl.config import check_agent_values, per_agent_keys, validate
        from drone_torchrl.training.agents import AgentTable
        from hydra_plugins.drone_torchrl_launcher.compose import agent_columns

        assert self.config is not None and self.hydra_context is not None
        table = agent_columns(self.hydra_context.config_loader, self.config, job_overrides, per_agent_keys())
        if table is None:
            return None
        cfg, hydra, values = table
        try:
            validate(cfg)
            check_agent_values(cfg, values)
        except ConfigError:  # the per-job path says which jobs, and trains the others
            return None
        log.info(f"{len(job_overrides)} jobs differ only in per-agent values: one population from one config")
        for ret in returns:
            ret.cfg = cfg
        hydra_record = {"hydra": OmegaConf.to_container(hydra, resolve=False, enum_to_str=True)}
        return hydra_record, [(AgentTable(cfg, values), list(range(len(job_overrides))))]

    def _tables(
        self,
        job_overrides: Sequence[Sequence[str]],
        initial_job_idx: int,
        returns: list[JobReturn],
        outcomes: list,
        sweep_dir: Path,
    ) -> tuple[dict | None, list[tuple[AgentTable, list[int]]]]:
        """Each job's config composed and checked (a bad one fails alone), then grouped as the fused
        launcher groups jobs: one agent table per group."""
        from drone_torchrl.config import validate
        from drone_torchrl.training.agents import AgentTable
        from drone_torchrl.training.jobs import group_key
        from drone_torchrl.training.trainer import Outcome
        from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

        assert self.config is not None and self.hydra_context is not None
        groups: dict[str, list[int]] = {}
        hydra_record: dict | None = None
        configs = sweep_configs(self.hydra_context.config_loader, self.config, job_overrides)
        for position, (overrides, cfg) in enumerate(zip(job_overrides, configs, strict=True)):
            with read_write(cfg), open_dict(cfg):
                if hydra_record is None:
                    hydra_record = {
                        "hydra": OmegaConf.to_container(cfg.hydra, resolve=False, enum_to_str=True)
                    }
                del cfg["hydra"]
            returns[position].cfg = cfg
            try:
                validate(cfg)
            except ConfigError as err:  # this job only; the others train
                print(f"job #{initial_job_idx + position} ({' '.join(overrides)}) not started: {err}")
                outcomes[position] = Outcome(sweep_dir, error=err)
                continue
            groups.setdefault(group_key(cfg), []).append(position)
        tables = [(AgentTable.of([returns[i].cfg for i in members]), members) for members in groups.values()]
        return hydra_record, tables


class _SearchLauncher(PopulationLauncher):
    """A population launcher whose runs search (:mod:`drone_torchrl.training.pbt`): its settings
    class (by name: the plug-in module imports no training code until it runs) reads
    ``hydra.launcher.*``."""

    settings_class = ""

    def __init__(self, **params: Any) -> None:
        from drone_torchrl.training import pbt

        super().__init__()
        try:
            self.search = getattr(pbt, self.settings_class).of(params)
        except ConfigError as err:  # Hydra makes it before any job starts: one line, nothing written
            sys.exit(f"drone-train: error: {err}")


class PBTLauncher(_SearchLauncher):
    """``hydra/launcher=pbt``: each population run trained with population-based training.

    A searched key given as a list moves among the list's values; one given as a range
    (``interval``, drawn per agent by the population sweeper) is multiplied by ``perturb`` and
    clipped to the range.
    """

    settings_class = "PBTSettings"


class PBTReplayLauncher(_SearchLauncher):
    """``hydra/launcher=pbt_replay``: each agent trained with the values one agent of a PBT run had,
    at the updates it had them (``hydra.launcher.run``, ``hydra.launcher.agent``): a PBT result
    retrained on fresh seeds."""

    settings_class = "ReplaySettings"


class HalvingLauncher(_SearchLauncher):
    """``hydra/launcher=halving``: each population run trained with successive halving."""

    settings_class = "HalvingSettings"
