"""The package's optional extras, and the command-line choices that need one.

The one table of "choice -> the module it imports -> the extra that installs it" (pyproject.toml's
``[project.optional-dependencies]``). ``drone-train`` checks the choices typed on its command line
against it before Hydra starts (:func:`check_choices`, with its other command-line checks),
so a choice whose extra is missing is refused in one line that names the choice as typed and the
extra, with nothing written::

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
from collections.abc import Mapping
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
    "population": POPULATION,
    "pbt": POPULATION,
    "halving": POPULATION,
    "pbt_replay": POPULATION,
    "local_parallel": _JOBLIB,
    "joblib": _JOBLIB,
    "local_submitit": _SUBMITIT,
    "submitit_local": _SUBMITIT,
    "submitit_slurm": _SUBMITIT,
    "slurm": _SUBMITIT,
    "slurm_population": _SUBMITIT,
    "ray_local": _RAY,
    "ray": _RAY,
}


def missing(choice: str, needs: Needs) -> str:
    """The one line saying that ``choice`` (as typed, ``key=value``) needs what ``needs`` installs."""
    return f"{choice} needs {needs.label or needs.module}: pip install 'drone_torchrl[{needs.extra}]'"


def logger_needs(option: str) -> Needs | None:
    """What ``logger=<option>`` needs: its backend's extra (:attr:`~drone_torchrl.loggers.Backend.extra`).

    None when it needs nothing, and for an option whose backend cannot be told here (Hydra says why
    when it composes it).
    """
    from hydra.errors import HydraException

    from drone_torchrl import loggers
    from drone_torchrl.config import _option_plugins

    try:
        # Hydra composes the option (its file names its backend, or inherits one): about 0.2 s.
        backend = loggers.get(_option_plugins("config", (("logger", option),))["logger"])
    except (HydraException, ConfigError):
        return None
    return None if backend.extra is None else Needs(backend.extra, backend.extra)


def needs_of(group: str, option: str) -> Needs | None:
    """What ``<group>=<option>`` needs, or None: :data:`LAUNCHERS`, or the logger's backend's extra."""
    if group == "hydra/launcher":
        return LAUNCHERS.get(option)
    if group == "logger":
        return logger_needs(option)
    return None


#: The config groups whose choices :func:`check_choices` checks.
GROUPS = ("hydra/launcher", "logger")


def check_choices(overrides: Mapping[str, str]) -> None:
    """Refuse, in one line (:class:`~.checks.ConfigError`), a choice whose extra is not installed.

    ``overrides``: the command line's ``{key: value}``; each option of a swept choice
    (``logger=csv,mlflow``) is checked.
    """
    for group in GROUPS:
        if group not in overrides:
            continue
        for option in _options(group, overrides[group]):
            needs = needs_of(group, option)
            if needs is not None and not needs.installed:
                raise ConfigError(missing(f"{group}={option}", needs))


def _options(group: str, value: str) -> list[str]:
    """The options of ``group=value`` as Hydra reads them: one, or each of a sweep's."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        (override,) = OverridesParser.create().parse_overrides([f"{group}={value}"])
    except HydraException:  # refused with its own line by the command line's checks
        return []
    if override.is_sweep_override():
        return [str(option) for option in override.sweep_string_iterator()]
    value = override.value()
    return [value] if isinstance(value, str) else []
