"""The config schemas of our Hydra plug-ins that extend another's: ``hydra/sweeper=population`` and ``slurm_population``'s.

Stored in Hydra's ConfigStore when imported. Kept apart from the plug-ins (``hydra_plugins/``, which
import the training code when they run) and below the config, which needs them to compose. Our own
launcher's options (``hydra/launcher=population``, ``fused``, ``pbt``, ...) are files in
``conf/hydra/launcher/``.
"""

from dataclasses import dataclass
from typing import Any

from hydra.core.config_store import ConfigStore

from drone_torchrl.compat import basic_sweeper_conf

BasicSweeperConf = basic_sweeper_conf()


@dataclass
class PopulationSweeperConf(BasicSweeperConf):
    """``hydra/sweeper=population``: the basic sweeper with cheaper checks, going on past failed jobs."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_sweeper.PopulationSweeper"


ConfigStore.instance().store(
    group="hydra/sweeper", name="population", node=PopulationSweeperConf, provider="drone_torchrl"
)


try:  # hydra/launcher=slurm_population extends the submitit plugin's SLURM schema (the submitit extra)
    from hydra_plugins.hydra_submitit_launcher.config import SlurmQueueConf
except ImportError:
    pass
else:

    @dataclass
    class SlurmPopulationConf(SlurmQueueConf):
        """``hydra/launcher=submitit_slurm_population``: populations of sweep jobs, one SLURM job each."""

        _target_: str = "hydra_plugins.drone_torchrl_launcher.slurm_launcher.SlurmPopulationLauncher"
        # Sweep jobs trained together as one population in each SLURM job. Typed Any so that a bad
        # value (agents_per_job=abc) reaches the launcher's one-line check, not OmegaConf's type error.
        agents_per_job: Any = 32

    ConfigStore.instance().store(
        group="hydra/launcher",
        name="submitit_slurm_population",
        node=SlurmPopulationConf,
        provider="drone_torchrl",
    )
