"""``hydra/sweeper=population``: Hydra's basic sweeper, checking a batch without composing every job.

The basic sweeper composes each job's config once to check the batch before launching it (about
0.4 s a job here). This one checks it through :func:`.compose.sweep_configs`: the first job is
composed fully, jobs that differ from it only in plain ``key=value`` overrides are checked by
applying them (an unknown key still fails), any other job is composed fully. Everything else,
grid expansion, batches, ``max_batch_size``, ``params``, is the basic sweeper's.
"""

from collections.abc import Sequence
from dataclasses import dataclass

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper, BasicSweeperConf
from hydra.core.config_store import ConfigStore


@dataclass
class PopulationSweeperConf(BasicSweeperConf):
    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_sweeper.PopulationSweeper"


ConfigStore.instance().store(
    group="hydra/sweeper", name="population", node=PopulationSweeperConf, provider="drone_torchrl"
)


class PopulationSweeper(BasicSweeper):
    def validate_batch_is_legal(self, batch: Sequence[Sequence[str]]) -> None:
        from hydra_plugins.drone_torchrl_launcher.compose import sweep_configs

        assert self.config is not None and self.hydra_context is not None
        sweep_configs(self.hydra_context.config_loader, self.config, batch)
