"""The package's optional extras, and the command-line choices that need one.

The one table of "choice -> the module it imports -> the extra that installs it" (pyproject.toml's
``[project.optional-dependencies]``). ``drone-train`` checks the choices typed on its command line
against it before Hydra starts (:func:`drone_torchrl.command_line.check_extras`), so a choice whose
extra is missing is refused in one line that names the choice as typed and the extra, with nothing
written::

    drone-train: error: hydra/launcher=pbt needs pyarrow: pip install 'drone_torchrl[population]'

- ``hydra/launcher=<option>``: :data:`LAUNCHERS` (Hydra's launcher plug-ins; the population runs'
  Parquet record).
- ``logger=<option>``: the extra its backend declares (:attr:`drone_torchrl.loggers.Backend.extra`,
  so a logger plug-in from another package declares its own); :func:`drone_torchrl.loggers.check_backend`
  refuses it again, with the same line, where the logger comes from elsewhere than the command line.

The code that imports an extra's module refuses with :func:`missing` too, for the ways past these
checks (a choice made in a config file).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass

from drone_torchrl.checks import ConfigError


@dataclass(frozen=True)
class Needs:
    """What a choice needs: a module, and the extra that installs it.

    Attributes:
        module: the module it imports (looked up, not imported).
        extra: the package extra that installs it (``pip install 'drone_torchrl[<extra>]'``).
        label: how the one-line error names the module (default: ``module``).
    """

    module: str
    extra: str
    label: str | None = None

    @property
    def installed(self) -> bool:
        """Whether :attr:`module` can be imported (looked up without importing it)."""
        try:
            return importlib.util.find_spec(self.module) is not None
        except ImportError:  # a dotted module whose parent package is missing
            return False


# A population run records its episodes, agents and lineage as Parquet (training.population_record).
POPULATION = Needs("pyarrow", "population")
_JOBLIB = Needs("hydra_plugins.hydra_joblib_launcher", "joblib", "Hydra's joblib launcher plug-in")
_SUBMITIT = Needs("hydra_plugins.hydra_submitit_launcher", "submitit", "Hydra's submitit launcher plug-in")
_RAY = Needs("hydra_plugins.hydra_ray_launcher", "ray", "Hydra's Ray launcher plug-in")

#: ``hydra/launcher`` options and what each needs. ``fused`` and ``slurm_population`` train their
#: populations into one folder per job (no Parquet), so they need no pyarrow.
LAUNCHERS: dict[str, Needs] = {
    **dict.fromkeys(("population", "pbt", "pb2", "halving", "pbt_replay"), POPULATION),
    **dict.fromkeys(("local_parallel", "joblib"), _JOBLIB),
    **dict.fromkeys(
        ("local_submitit", "submitit_local", "submitit_slurm", "slurm", "slurm_population"), _SUBMITIT
    ),
    **dict.fromkeys(("ray_local", "ray"), _RAY),
}


def missing(choice: str, needs: Needs) -> str:
    """The one line saying that ``choice`` (as typed, ``key=value``) needs what ``needs`` installs."""
    return f"{choice} needs {needs.label or needs.module}: pip install 'drone_torchrl[{needs.extra}]'"


def check(choice: str, needs: Needs | None) -> None:
    """Refuse ``choice`` (as typed, ``key=value``) in one line when what it needs is missing (:class:`~.checks.ConfigError`)."""
    if needs is not None and not needs.installed:
        raise ConfigError(missing(choice, needs))
