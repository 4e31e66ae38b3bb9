"""``hydra/sweeper=population``: Hydra's basic sweeper, checking a batch without composing every job,
and going on past failed jobs.

- The basic sweeper composes each job's config once to check the batch before launching it (about
  0.4 s a job here). This one checks it through :func:`.compose.sweep_configs`: the first job is
  composed fully, jobs that differ from it only in plain ``key=value`` overrides are checked by
  applying them (an unknown key still fails), any other job is composed fully. Each job's values
  then pass :func:`drone_torchrl.config.validate`: a bad value stops the sweep with one line
  before any job starts.
- The basic sweeper raises the first failed job's error after its batch, so later batches never run
  and the end-of-sweep summary is skipped. Here every batch runs; the summary
  (``SweepSummary``) then lists each job's status and exits non-zero if any failed.

Everything else, grid expansion, batches, ``max_batch_size``, ``params``, is the basic sweeper's.
"""

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig

from drone_torchrl.compat import basic_sweeper_class
from hydra_plugins.drone_torchrl_launcher import schemas  # noqa: F401  (registers hydra/sweeper=population)


class PopulationSweeper(Sweeper):
    """The basic sweeper with a cheaper ``validate_batch_is_legal``.

    It wraps rather than subclasses ``BasicSweeper``: Hydra's plugin scan re-executes its core
    plugin modules, and ``BasicSweeper.__init__`` calls ``super(BasicSweeper, self)`` with the class
    the module defines now, which a subclass of the class imported earlier is not.
    """

    config: DictConfig | None = None
    hydra_context: HydraContext | None = None

    def __init__(self, max_batch_size: int | None = None, params: dict[str, str] | None = None) -> None:
        self._basic = basic_sweeper_class()(max_batch_size=max_batch_size, params=params)
        self._basic.validate_batch_is_legal = self.validate_batch_is_legal

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config, self.hydra_context = config, hydra_context
        self._basic.setup(hydra_context=hydra_context, task_function=task_function, config=config)
        self._basic.launcher = _GoOn(self._basic.launcher)

    def sweep(self, arguments: list[str]) -> Any:
        """The basic sweeper's sweep, with the sweep folder this process's while it runs: the same
        sweep command started again while this one is alive is refused in one line, before Hydra
        writes into the folder (:mod:`drone_torchrl.io.run_lock`; each job folder is also held by the
        process that trains it, under every launcher)."""
        from drone_torchrl.config import ConfigError
        from drone_torchrl.io import run_lock
        from drone_torchrl.io.folders import remove_if_untouched

        assert self.config is not None
        sweep_dir = str(self.config.hydra.sweep.dir)
        try:
            run_lock.hold(sweep_dir)
        except (ConfigError, OSError) as err:
            sys.exit(f"drone-train: error: sweep {err}")
        try:
            return self._basic.sweep(arguments)
        finally:
            run_lock.release(sweep_dir)
            # A sweep refused before its first job leaves no folder (Hydra wrote only its multirun.yaml).
            remove_if_untouched(Path(sweep_dir), also=frozenset({"multirun.yaml"}))

    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        """Every job composes, and every job's values pass the config checks: a bad value in a
        sweep is one line before any job folder exists, not a failed job per value."""
        from drone_torchrl import migrations
        from drone_torchrl.checks import ConfigError
        from drone_torchrl.config import AgentValueError, check_agent_values, per_agent_keys, validate
        from hydra_plugins.drone_torchrl_launcher.compose import agent_columns, sweep_configs

        assert self.config is not None and self.hydra_context is not None

        def refuse(err: ConfigError, overrides: Sequence[str]) -> None:
            sys.exit(
                f"drone-train: error: {err} (in the sweep's job {' '.join(overrides)}; no job was started)"
            )

        loader = self.hydra_context.config_loader
        table = agent_columns(loader, self.config, batch, per_agent_keys())
        if table is not None:  # jobs that differ only in per-agent numbers: one config, checked once
            cfg, _, values = table
            try:
                migrations.apply_legacy(cfg)
                validate(cfg)
                check_agent_values(cfg, values)
            except AgentValueError as err:
                refuse(err, batch[err.agent])
            except ConfigError as err:
                refuse(err, batch[0])
            return
        for overrides, cfg in zip(
            batch, sweep_configs(loader, self.config, batch, task_only=True), strict=True
        ):
            try:
                migrations.apply_legacy(cfg)
                validate(cfg)
            except ConfigError as err:
                refuse(err, overrides)


class _GoOn:
    """A launcher as the basic sweeper sees it: failed jobs keep their error (Hydra's callbacks and
    the job folders say FAILED), but do not stop the sweep."""

    def __init__(self, launcher: Any) -> None:
        self.launcher = launcher

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        returns = self.launcher.launch(job_overrides, initial_job_idx=initial_job_idx)
        for ret in returns:
            if ret.status == JobStatus.FAILED:
                ret.status, ret.return_value = JobStatus.COMPLETED, None
        return returns

    def __getattr__(self, name: str) -> Any:
        return getattr(self.launcher, name)
