"""``hydra/sweeper=population``: Hydra's basic sweeper, checking a batch without composing every job,
and going on past failed jobs.

- The basic sweeper composes each job's config once to check the batch before launching it (about
  0.4 s a job here). This one checks it through :func:`.compose.checked_batch`: the first job is
  composed fully, jobs that differ from it only in plain ``key=value`` overrides are checked by
  applying them (an unknown key still fails), any other job is composed fully. Each job's values
  then pass :func:`drone_torchrl.config.validate`: a bad value stops the sweep with one line
  before any job starts. A population launcher is handed the checked batch
  (:meth:`~.population_launcher.PopulationLauncher.check`) and trains it without composing it again.
- A key searched by ``hydra/launcher=pbt`` may be given as a range: ``algo.lr=interval(1e-5,1e-2)``
  or ``algo.lr=tag(log,interval(1e-5,1e-2))`` (the basic sweeper refuses an interval). The other
  overrides make the grid of jobs (agents) as usual, and each job gets ``key=<value>`` drawn
  from the range by a generator keyed by its ``seed`` and the key (:meth:`.pbt.Range.first_values`):
  the same command gives each agent the same value again. The PBT launcher is told the range, which
  its exploration keeps to (:class:`drone_torchrl.training.pbt.PBTSettings`). Any other launcher,
  or a key PBT does not search, is refused in one line.
- The basic sweeper raises the first failed job's error after its batch, so later batches never run
  and the end-of-sweep summary is skipped. Here every batch runs; the summary
  (``SweepSummary``) then lists each job's status and exits non-zero if any failed.

Grid expansion and batches are the basic sweeper's (its ``split_arguments``); ``max_batch_size`` and
``params`` mean what they mean there.
"""

import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, ValueType
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

from drone_torchrl import launcher_schemas  # noqa: F401  (registers hydra/sweeper=population)
from drone_torchrl.checks import ConfigError
from drone_torchrl.compat import basic_sweeper_class
from hydra_plugins.drone_torchrl_launcher.compose import checked_batch
from hydra_plugins.drone_torchrl_launcher.population_launcher import PopulationLauncher


class PopulationSweeper(Sweeper):
    """Hydra's basic sweeper (its grid, batches, ``max_batch_size`` and ``params``), checking each batch
    cheaply and going on past failed jobs (the module's docstring).

    It does the basic sweeper's few steps itself rather than subclass ``BasicSweeper``: Hydra's plugin
    scan re-executes its core plugin modules, and ``BasicSweeper.__init__`` calls ``super(BasicSweeper,
    self)`` with the class the module defines now, which a subclass of the class imported earlier is not.
    """

    config: DictConfig | None = None
    hydra_context: HydraContext | None = None
    launcher: Any = None

    def __init__(self, max_batch_size: int | None = None, params: dict[str, str] | None = None) -> None:
        self.max_batch_size, self.params = max_batch_size, params or {}

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        from hydra.core.plugins import Plugins

        self.config, self.hydra_context = config, hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> Any:
        """The basic sweeper's sweep, with the sweep folder this process's while it runs: the same
        sweep command started again while this one is alive is refused in one line, before Hydra
        writes into the folder (:mod:`drone_torchrl.io.run_lock`; each job folder is also held by the
        process that trains it, under every launcher).

        Every batch runs: a failed job keeps its error (Hydra's callbacks and the job folders say
        FAILED) but does not stop the sweep. A disk that refuses a write
        (:class:`~drone_torchrl.io.storage.StorageError`, out of a launcher that trains in this
        process: ``fused``, ``population``, ``pbt``, ...) does: the jobs after it would fail alike.
        One line then names the file and the command that continues.
        """
        from drone_torchrl.io import run_lock
        from drone_torchrl.io.folders import remove_if_untouched
        from drone_torchrl.io.storage import StorageError
        from drone_torchrl.training.jobs import this_command

        assert self.config is not None and self.hydra_context is not None
        sweep_dir = str(self.config.hydra.sweep.dir)
        try:
            run_lock.hold(sweep_dir)
        except (ConfigError, OSError) as err:
            sys.exit(f"drone-train: error: sweep {err}")
        try:
            parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
            params = [f"{key}={value}" for key, value in self.params.items()]
            batches = self.split_arguments(parser.parse_overrides([*params, *arguments]), self.max_batch_size)
            Path(sweep_dir).mkdir(parents=True, exist_ok=True)
            OmegaConf.save(self.config, Path(sweep_dir) / "multirun.yaml")
            returns, start = [], 0
            for batch in batches:
                try:
                    returns.append(self.launcher.launch(batch, initial_job_idx=start))
                except StorageError as err:  # checkpoints are replaced whole: the last of each job stands
                    sys.exit(
                        f"drone-train: error: {err}; every checkpoint written is intact (each job continues "
                        f"from its own); continue with: {this_command()}"
                    )
                start += len(batch)
            return returns
        finally:
            run_lock.release(sweep_dir)
            # A sweep refused before its first job leaves no folder (Hydra wrote only its multirun.yaml).
            remove_if_untouched(Path(sweep_dir), also=frozenset({"multirun.yaml"}))

    def split_arguments(self, overrides: list[Override], max_batch_size: int | None) -> list[list[list[str]]]:
        """The basic sweeper's batches of jobs, with each range (``interval``) drawn per job, each checked.

        A range override is taken out of the grid; every job then gets ``key=<value>``, drawn from
        the range with a generator keyed by the job's ``seed`` (the config's where the job sets
        none). A range is refused in one line unless the launcher is ``pbt`` and searches the key.
        Every batch is then checked before the basic sweeper writes the sweep folder (its
        ``multirun.yaml``): each job's values (:func:`.compose.checked_batch`), then what the launcher
        refuses of the batch (a population launcher's
        :meth:`~.population_launcher.PopulationLauncher.check`, which keeps the composed jobs): a
        refused command writes nothing. Exits with one line.
        """
        assert self.config is not None and self.hydra_context is not None
        launcher = self.launcher
        grid = [o for o in overrides if o.value_type != ValueType.INTERVAL_SWEEP]
        batches = basic_sweeper_class().split_arguments(grid, max_batch_size)
        try:
            ranges = [_range(o, launcher) for o in overrides if o.value_type == ValueType.INTERVAL_SWEEP]
            if ranges:
                launcher.search = replace(launcher.search, ranges=tuple(ranges))
                launcher.search.bounds(self.config)  # a range reaching past its key's values
            for batch in batches:
                seeds = [_job_seed(job, int(self.config.seed)) for job in batch]
                for span in ranges:
                    for job, value in zip(batch, span.first_values(seeds), strict=True):
                        job.append(f"{span.key}={value!r}")
                checked = checked_batch(self.hydra_context.config_loader, self.config, batch)
                if isinstance(launcher, PopulationLauncher):
                    launcher.check(batch, checked)
        except ConfigError as err:
            sys.exit(f"drone-train: error: {err}")
        return batches


def _range(override: Override, launcher: Any) -> Any:
    """``key=interval(low,high)`` (``tag(log,...)``: log-uniform) as a :class:`.pbt.Range`, checked.

    Raises :class:`~drone_torchrl.checks.ConfigError` (one line) for a launcher other than ``pbt``,
    a key it does not search, or bad ends.
    """
    from drone_torchrl.training.pbt import PBTSettings, Range

    key, sweep = override.key_or_group, override.value()
    low, high, log = float(sweep.start), float(sweep.end), "log" in sweep.tags
    text = f"{override.input_line} is not allowed; expected"
    search = getattr(launcher, "search", None)
    if not isinstance(search, PBTSettings):
        raise ConfigError(
            f"{text} a list of values (e.g. {key}=1e-4,3e-4,1e-3): a range is searched only by hydra/launcher=pbt or pb2"
        )
    if key not in search.keys:
        raise ConfigError(
            f"{text} a list of values: a range is allowed only for a key PBT searches "
            f"(hydra.launcher.keys={list(search.keys)})"
        )
    if not (low < high and (low > 0 or not log)):
        allowed = "0 < low < high (a log range)" if log else "low < high"
        raise ConfigError(f"{text} interval(low,high) with {allowed}")
    return Range(key, low, high, log)


def _job_seed(job: Sequence[str], default: int) -> int:
    """The seed a job's ``seed=N`` override sets, else ``default``."""
    return next((int(line[len("seed=") :]) for line in job if line.startswith("seed=")), default)
