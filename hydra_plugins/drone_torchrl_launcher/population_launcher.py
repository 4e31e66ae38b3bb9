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

import importlib
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

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
    # The plan of each batch checked before the sweep folder was written (:meth:`check`), by its jobs.
    _plans: dict[tuple[tuple[str, ...], ...], _Plan]

    def check(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> None:
        """Compose, group and check a batch's jobs as :meth:`launch` will train them, before any folder.

        Raises :class:`~drone_torchrl.checks.ConfigError` (one line) for the first job or group refused:
        a job's values, or what :func:`~drone_torchrl.training.trainer.check_population` refuses
        (learner, budget, memory, a search the budget or the population cannot hold). The hydra/sweeper
        =population sweeper calls it for every batch before it writes the sweep folder; the plan is
        kept for :meth:`launch`.
        """
        from drone_torchrl.training.trainer import check_population

        plan = self._plan(job_overrides, initial_job_idx)
        if plan.refused:
            raise plan.refused[0][1]
        for agents, _ in plan.groups:
            check_population(agents, self.search)
        self._plans = {**getattr(self, "_plans", {}), _jobs(job_overrides): plan}

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.training.trainer import Outcome, train_population

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        log.info(f"Launching {len(job_overrides)} jobs as population runs in {sweep_dir}")
        plan = getattr(self, "_plans", {}).pop(_jobs(job_overrides), None)
        try:  # unless checked before: another sweeper than hydra/sweeper=population
            plan = plan or self._plan(job_overrides, initial_job_idx)
        except ConfigError as err:
            sys.exit(f"drone-train: error: {err}")
        if plan.one_config:
            log.info(
                f"{len(job_overrides)} jobs differ only in per-agent values: one population from one config"
            )
        returns = plan.returns
        outcomes = [None if e is None else Outcome(sweep_dir, error=e) for e in plan.errors]
        refused = [err for _, err in plan.refused]
        for number, (agents, members) in enumerate(plan.groups):
            run_dir = sweep_dir / POPULATION_DIR.format(number)
            names = [" ".join(job_overrides[i]) for i in members]

            def write_record(cfg=agents.cfg, run_dir=run_dir, members=members) -> None:
                record = run_dir / ".hydra"
                record.mkdir(exist_ok=True)
                save_yaml(cfg, record / "config.yaml")
                save_yaml(plan.hydra_record, record / "hydra.yaml")
                # One job a line in YAML's flow style (JSON's strings are YAML's): the block style
                # of save_yaml takes seconds at tens of thousands of jobs.
                lines = "".join(f"- {json.dumps(list(job_overrides[i]))}\n" for i in members)
                write_atomically(record / "overrides.yaml", lines.encode("utf-8"))

            try:
                done = train_population(agents, names, run_dir, write_record, self.search)
            except ConfigError as err:  # refused before training: the other groups go on
                done = [Outcome(run_dir, error=err)] * len(members)
                refused.append(err)
            for i, outcome in zip(members, done, strict=True):
                outcomes[i] = outcome
        for ret, outcome in zip(returns, outcomes, strict=True):
            assert outcome is not None
            if outcome.error is None:
                ret.status, ret.return_value = JobStatus.COMPLETED, outcome.final_return
            else:
                reason = f"{type(outcome.error).__name__}: {outcome.error}"
                ret.status, ret.return_value = JobStatus.FAILED, JobFailed(f"{outcome.run_dir}: {reason}")
        if refused:  # no folder for the sweep's summary to count: a failure all the same, in one line
            others = (
                f" ({len(refused) - 1} other population run(s) not started too)" if len(refused) > 1 else ""
            )
            sys.exit(f"drone-train: error: {refused[0]}{others}")
        return returns

    def _plan(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> _Plan:
        """The batch's jobs composed, checked and grouped: one agent table per population run."""
        returns: list[JobReturn] = [_JobReturn(overrides=list(overrides)) for overrides in job_overrides]
        errors: list[ConfigError | None] = [None] * len(job_overrides)
        one_table = self._one_table(job_overrides, returns)
        hydra_record, groups = one_table or self._tables(job_overrides, returns, errors)
        refused = [
            (i, ConfigError(f"job #{initial_job_idx + i} ({' '.join(job_overrides[i])}): {err}"))
            for i, err in enumerate(errors)
            if err is not None
        ]
        self._check_jobs(job_overrides)
        return _Plan(hydra_record, groups, returns, errors, refused, one_table is not None)

    def _check_jobs(self, job_overrides: Sequence[Sequence[str]]) -> None:
        """What this launcher refuses of the jobs' overrides themselves (:class:`ConfigError`); none here."""

    def _one_table(
        self, job_overrides: Sequence[Sequence[str]], returns: list[JobReturn]
    ) -> tuple[dict, list[tuple[AgentTable, list[int]]]] | None:
        """Jobs that differ only in numbers of the per-agent keys, and whose values all pass: one
        population from one config (:func:`.compose.agent_columns`), no config per job; else None.
        Each job's ``JobReturn.cfg`` is then the group's config (its own values: ``agents.parquet``)."""
        from drone_torchrl import migrations
        from drone_torchrl.config import check_agent_values, per_agent_keys, validate
        from drone_torchrl.training.agents import AgentTable
        from hydra_plugins.drone_torchrl_launcher.compose import agent_columns

        assert self.config is not None and self.hydra_context is not None
        table = agent_columns(self.hydra_context.config_loader, self.config, job_overrides, per_agent_keys())
        if table is None:
            return None
        cfg, hydra, values = table
        try:
            migrations.apply_legacy(cfg)  # old keys mean what they mean in a single run
            validate(cfg)
            check_agent_values(cfg, values)
        except ConfigError:  # the per-job path says which jobs, and trains the others
            return None
        for ret in returns:
            ret.cfg = cfg
        hydra_record = {"hydra": OmegaConf.to_container(hydra, resolve=False, enum_to_str=True)}
        return hydra_record, [(AgentTable(cfg, values), list(range(len(job_overrides))))]

    def _tables(
        self, job_overrides: Sequence[Sequence[str]], returns: list[JobReturn], errors: list
    ) -> tuple[dict | None, list[tuple[AgentTable, list[int]]]]:
        """Each job's config composed and checked (a bad one's error in ``errors``), then grouped as the
        fused launcher groups jobs: one agent table per group."""
        from drone_torchrl import migrations
        from drone_torchrl.config import validate
        from drone_torchrl.training.agents import AgentTable
        from drone_torchrl.training.jobs import group_key
        from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

        assert self.config is not None and self.hydra_context is not None
        groups: dict[str, list[int]] = {}
        hydra_record: dict | None = None
        configs = sweep_configs(self.hydra_context.config_loader, self.config, job_overrides)
        for position, cfg in enumerate(configs):
            with read_write(cfg), open_dict(cfg):
                if hydra_record is None:
                    hydra_record = {
                        "hydra": OmegaConf.to_container(cfg.hydra, resolve=False, enum_to_str=True)
                    }
                del cfg["hydra"]
            returns[position].cfg = cfg
            try:
                migrations.apply_legacy(cfg)  # old keys mean what they mean in a single run
                validate(cfg)
            except ConfigError as err:
                errors[position] = err
                continue
            groups.setdefault(group_key(cfg), []).append(position)
        tables = [(AgentTable.of([returns[i].cfg for i in members]), members) for members in groups.values()]
        return hydra_record, tables


class _Plan(NamedTuple):  # not a dataclass: Hydra's plug-in scan runs this module outside sys.modules
    """A batch as :meth:`PopulationLauncher.launch` trains it: Hydra's record, the groups (an agent table
    and its jobs' positions), each job's ``JobReturn``, each job's refusal (or None), and the refusals
    as ``(position, one-line error naming the job)``; ``one_config``: the jobs differ only in per-agent
    numbers (one config, :func:`.compose.agent_columns`)."""

    hydra_record: dict | None
    groups: list[tuple[AgentTable, list[int]]]
    returns: list[JobReturn]
    errors: list[ConfigError | None]
    refused: list[tuple[int, ConfigError]]
    one_config: bool


def _jobs(job_overrides: Sequence[Sequence[str]]) -> tuple[tuple[str, ...], ...]:
    """A batch's jobs as a key."""
    return tuple(tuple(job) for job in job_overrides)


class _SearchLauncher(PopulationLauncher):
    """A population launcher whose runs search (:mod:`drone_torchrl.training.pbt`): its settings
    class (by name: the plug-in module imports no training code until it runs) reads
    ``hydra.launcher.*``."""

    settings_class = ""
    settings_module = "drone_torchrl.training.pbt"

    def __init__(self, **params: Any) -> None:
        super().__init__()
        try:
            self.search = getattr(importlib.import_module(self.settings_module), self.settings_class).of(
                params
            )
        except ConfigError as err:  # Hydra makes it before any job starts: one line, nothing written
            sys.exit(f"drone-train: error: {err}")


class PBTLauncher(_SearchLauncher):
    """``hydra/launcher=pbt``: each population run trained with population-based training.

    A searched key given as a list moves among the list's values; one given as a range
    (``interval``, drawn per agent by the population sweeper) is multiplied by ``perturb`` and
    clipped to the range.
    """

    settings_class = "PBTSettings"


class PB2Launcher(_SearchLauncher):
    """``hydra/launcher=pb2``: each population run trained with population-based bandits (PBT whose
    explore step is chosen by a Gaussian process, :mod:`drone_torchrl.training.pb2`)."""

    settings_class = "PB2Settings"
    settings_module = "drone_torchrl.training.pb2"


class PBTReplayLauncher(_SearchLauncher):
    """``hydra/launcher=pbt_replay``: each agent trained with the values one agent of a PBT run had,
    at the updates it had them (``hydra.launcher.run``, ``hydra.launcher.agent``): a PBT result
    retrained on fresh seeds."""

    settings_class = "ReplaySettings"

    def _check_jobs(self, job_overrides: Sequence[Sequence[str]]) -> None:
        """Refuse a job that sets a key the replayed schedule sets: its value would never be used."""
        assert self.search is not None
        scheduled = {key for _, values in self.search.schedule for key, _ in values}
        for job in job_overrides:
            for line in job:
                key = line.partition("=")[0].lstrip("+~")
                if key in scheduled:
                    raise ConfigError(
                        f"{line} is not allowed with hydra/launcher=pbt_replay: the replayed schedule sets "
                        f"{', '.join(sorted(scheduled))} (agent {self.search.agent} of {self.search.run}); "
                        f"expected no {key}= (sweep seed= and the keys the schedule leaves)"
                    )


class HalvingLauncher(_SearchLauncher):
    """``hydra/launcher=halving``: each population run trained with successive halving."""

    settings_class = "HalvingSettings"
