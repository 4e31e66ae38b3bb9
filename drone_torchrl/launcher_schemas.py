"""The config schemas of our Hydra plug-ins (``hydra/launcher=fused``, ``population``, ... and ``hydra/sweeper=population``).

Stored in Hydra's ConfigStore when imported. Kept apart from the plug-ins (``hydra_plugins/``, which
import the training code when they run) and below the config, which needs them to compose: composing
the configs needs nothing but this module.
"""

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore

from drone_torchrl.compat import basic_sweeper_conf

BasicSweeperConf = basic_sweeper_conf()


@dataclass
class FusedLauncherConf:
    """``hydra/launcher=fused``: a sweep's compatible jobs trained as one population."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.fused_launcher.FusedLauncher"


@dataclass
class PopulationLauncherConf:
    """``hydra/launcher=population``: each population run of a sweep trained as one."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_launcher.PopulationLauncher"


@dataclass
class PBTLauncherConf:
    """``hydra/launcher=pbt``: population runs with population-based training.

    See :mod:`drone_torchrl.training.pbt` (Ray Tune's defaults). Typed Any so that a bad value reaches
    the launcher's one-line check, not OmegaConf's type error.
    """

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_launcher.PBTLauncher"
    every_updates: Any = 100
    quantile: Any = 0.25
    # The factors a key searched over a range (interval(low,high)) is multiplied by; a key searched
    # over a list moves to a neighbouring list value instead, and ignores them.
    perturb: Any = field(default_factory=lambda: [0.8, 1.2])
    # The chance that an explored key is drawn again from its list or range instead.
    resample_probability: Any = 0.25
    keys: Any = field(default_factory=lambda: ["algo.lr", "algo.gamma"])


@dataclass
class PB2LauncherConf:
    """``hydra/launcher=pb2``: PBT whose explore step is chosen by a Gaussian process.

    Population-based bandits (:mod:`drone_torchrl.training.pb2`). No perturb: nothing is explored at random.
    """

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_launcher.PB2Launcher"
    every_updates: Any = 100
    quantile: Any = 0.25
    keys: Any = field(default_factory=lambda: ["algo.lr", "algo.gamma"])


@dataclass
class HalvingLauncherConf:
    """``hydra/launcher=halving``: population runs with successive halving."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_launcher.HalvingLauncher"
    rungs: Any = field(default_factory=lambda: [500, 1500])
    fraction: Any = 0.5
    keys: Any = field(default_factory=lambda: ["algo.lr", "algo.gamma"])


@dataclass
class PBTReplayLauncherConf:
    """``hydra/launcher=pbt_replay``: a PBT agent's values replayed on a new population."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_launcher.PBTReplayLauncher"
    run: Any = None
    agent: Any = None


@dataclass
class PopulationSweeperConf(BasicSweeperConf):
    """``hydra/sweeper=population``: the basic sweeper with cheaper checks, going on past failed jobs."""

    _target_: str = "hydra_plugins.drone_torchrl_launcher.population_sweeper.PopulationSweeper"


for group, name, node in (
    ("hydra/launcher", "fused", FusedLauncherConf),
    ("hydra/launcher", "population", PopulationLauncherConf),
    ("hydra/launcher", "pbt", PBTLauncherConf),
    ("hydra/launcher", "pb2", PB2LauncherConf),
    ("hydra/launcher", "pbt_replay", PBTReplayLauncherConf),
    ("hydra/launcher", "halving", HalvingLauncherConf),
    ("hydra/sweeper", "population", PopulationSweeperConf),
):
    ConfigStore.instance().store(group=group, name=name, node=node, provider="drone_torchrl")


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
