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
  logger and checkpoints (:func:`.fused_launcher.train_populations`, which ``slurm_population``
  runs on each node); at tens of thousands of agents that bookkeeping is most of the work.

Each job's Hydra return value is its agent's final running-mean return, under any launcher.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from hydra.core.utils import JobReturn, JobStatus, configure_log, setup_globals
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from drone_torchrl.checks import ConfigError, as_override
from drone_torchrl.io.storage import write_atomically
from drone_torchrl.io.yaml_text import save_yaml
from hydra_plugins.drone_torchrl_launcher.fused_launcher import _JobReturn, report, train_populations

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


class PopulationLauncher(Launcher):
    """A sweep trained as one batch (the module's docstring); ``settings``: the search's keys."""

    config: DictConfig | None = None
    hydra_context: HydraContext | None = None
    task_function: TaskFunction | None = None

    def __init__(self, search: str = "none", folders: str = "population", **settings: Any) -> None:
        self.per_job = folders == "job"
        # The plan of each batch checked before the sweep folder was written (:meth:`check`), by its jobs.
        self._plans: dict[tuple[tuple[str, ...], ...], _Plan] = {}
        self.replay = search == "replay"
        try:
            self.search: SearchSettings | None = _settings(search, folders, settings)
        except ConfigError as err:  # Hydra makes it before any job starts: one line, nothing written
            sys.exit(f"drone-train: error: {err}")

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config, self.hydra_context, self.task_function = config, hydra_context, task_function

    def check(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> None:
        """Compose, group and check a batch's jobs as :meth:`launch` will train them, before any folder.

        Raises :class:`~drone_torchrl.checks.ConfigError` (one line) for the first job or group refused:
        a job's values, or what :func:`~drone_torchrl.training.trainer.check_population` refuses
        (learner, budget, memory, a search the budget or the population cannot hold). The hydra/sweeper
        =population sweeper calls it for every batch before it writes the sweep folder; the plan is
        kept for :meth:`launch`. Jobs in folders of their own (``folders=job``) are each checked by the sweeper.
        """
        from drone_torchrl.training.trainer import check_population

        if self.per_job:
            return
        plan = self._plan(job_overrides, initial_job_idx)
        if plan.refused:
            raise plan.refused[0]
        for agents, _ in plan.groups:
            check_population(agents, self.search)
        self._plans[_jobs(job_overrides)] = plan

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        from drone_torchrl.training.jobs import sweep_summary
        from drone_torchrl.training.trainer import Outcome, train_population

        setup_globals()
        assert self.config is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        if self.per_job:
            # hydra/sweeper=population validates every job's config before launching its batch, and
            # prints the end-of-sweep summary itself.
            validated = str(self.config.hydra.sweeper._target_).endswith("PopulationSweeper")
            numbers = range(initial_job_idx, initial_job_idx + len(job_overrides))
            returns = train_populations(self.hydra_context, self.config, job_overrides, numbers, validated)
            if not validated and any(ret.status == JobStatus.FAILED for ret in returns):
                # Another sweeper stops at the first failed job and skips the end-of-sweep summary.
                print(sweep_summary(Path(str(self.config.hydra.sweep.dir))))
            return returns
        sweep_dir = Path(str(self.config.hydra.sweep.dir)).absolute()
        log.info(f"Launching {len(job_overrides)} jobs as population runs in {sweep_dir}")
        plan = self._plans.pop(_jobs(job_overrides), None)
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
        refused = list(plan.refused)
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
            report(ret, outcome)
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
            ConfigError(f"job #{initial_job_idx + i} ({' '.join(job_overrides[i])}): {err}")
            for i, err in enumerate(errors)
            if err is not None
        ]
        if self.replay:
            _refuse_scheduled_keys(self.search, job_overrides)
        return _Plan(hydra_record, groups, returns, errors, refused, one_table is not None)

    def _one_table(
        self, job_overrides: Sequence[Sequence[str]], returns: list[JobReturn]
    ) -> tuple[dict, list[tuple[AgentTable, list[int]]]] | None:
        """Jobs that differ only in numbers of the per-agent keys, and whose values all pass: one
        population from one config (:func:`.compose.agent_columns`), no config per job; else None.
        Each job's ``JobReturn.cfg`` is then the group's config (its own values: ``agents.parquet``)."""
        from drone_torchrl.config import per_agent_keys
        from drone_torchrl.training.agents import AgentTable
        from hydra_plugins.drone_torchrl_launcher.compose import agent_columns, checked

        assert self.config is not None and self.hydra_context is not None
        table = agent_columns(self.hydra_context.config_loader, self.config, job_overrides, per_agent_keys())
        if table is None:
            return None
        cfg, hydra, values = table
        try:
            checked(cfg, values)
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
        from drone_torchrl.training.agents import AgentTable
        from drone_torchrl.training.jobs import group_key
        from hydra_plugins.drone_torchrl_launcher.compose import checked, sweep_configs

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
                checked(cfg)
            except ConfigError as err:
                errors[position] = err
                continue
            groups.setdefault(group_key(cfg), []).append(position)
        tables = [(AgentTable.of([returns[i].cfg for i in members]), members) for members in groups.values()]
        return hydra_record, tables


class _Plan(NamedTuple):  # not a dataclass: Hydra's plug-in scan runs this module outside sys.modules
    """A batch as :meth:`PopulationLauncher.launch` trains it: Hydra's record, the groups (an agent table
    and its jobs' positions), each job's ``JobReturn``, each job's refusal (or None), and the refusals
    as one-line errors naming their jobs; ``one_config``: the jobs differ only in per-agent
    numbers (one config, :func:`.compose.agent_columns`)."""

    hydra_record: dict | None
    groups: list[tuple[AgentTable, list[int]]]
    returns: list[JobReturn]
    errors: list[ConfigError | None]
    refused: list[ConfigError]
    one_config: bool


def _jobs(job_overrides: Sequence[Sequence[str]]) -> tuple[tuple[str, ...], ...]:
    """A batch's jobs as a key."""
    return tuple(tuple(job) for job in job_overrides)


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
