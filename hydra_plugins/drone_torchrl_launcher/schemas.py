"""The config schemas of ``hydra/launcher=fused`` and ``hydra/sweeper=population``, in Hydra's ConfigStore.

Kept apart from the plugins (which import the training code when they run) so that composing the
configs needs nothing but this module.
"""

from dataclasses import dataclass

from hydra._internal.core_plugins.basic_sweeper import BasicSweeperConf
from hydra.core.config_store import ConfigStore


@dataclass
class FusedLauncherConf:
    _target_: str = "hydra_plugins.drone_torchrl_launcher.fused_launcher.FusedLauncher"


@dataclass
class PopulationSweeperConf(BasicSweeperConf):
    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_sweeper.PopulationSweeper"


ConfigStore.instance().store(
    group="hydra/launcher", name="fused", node=FusedLauncherConf, provider="drone_torchrl"
)
ConfigStore.instance().store(
    group="hydra/sweeper", name="population", node=PopulationSweeperConf, provider="drone_torchrl"
)
