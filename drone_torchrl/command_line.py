"""What ``drone-train``, ``drone-eval`` and ``drone-export`` check (and claim) before Hydra writes anything.

Hydra writes ``<run>/.hydra/`` and the job log before our code runs, and reports an argument or an
override it cannot parse in several lines (argparse's usage, Hydra's grammar hint). So the command
line is checked first, each problem in one line, and the run folder a single run will write is
claimed (:mod:`drone_torchrl.io.run_lock`) before Hydra touches it.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from drone_torchrl import config, extras, migrations
from drone_torchrl.checks import ConfigError, dotted
from drone_torchrl.compat import hydra_args_parser
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import is_last_of_its_run, resolve_checkpoint, run_dir_of
from drone_torchrl.io.folders import check_fork_folder
from drone_torchrl.io.storage import StorageError
from drone_torchrl.sweep_folder import SEARCH_LAUNCHERS, SWEEP_RECORD


def parse_flags(prog: str, args: list[str]) -> argparse.Namespace:
    """Hydra's own command-line flags, parsed with its parser; a bad flag is a one-line error.

    An unknown or incomplete flag is a :class:`~.checks.ConfigError` instead of argparse's usage
    text.
    """
    parser = hydra_args_parser()
    parser.prog = prog
    parser.exit_on_error = False
    try:
        known, unknown = parser.parse_known_args(args)
    except argparse.ArgumentError as err:
        raise ConfigError(f"{err} (see {prog} --help)") from None
    if unknown and unknown[0].startswith("-"):
        raise ConfigError(f"{unknown[0]} is not an option of {prog} (see {prog} --help)")
    if unknown:
        raise ConfigError(
            f"{unknown[0]} comes after a flag that split the overrides: Hydra reads them as one group, so put "
            f"flags first (e.g. {prog} -m key=a,b)"
        )
    for word in known.overrides:  # Hydra's own answer to a bare word is its parser's, in several lines
        if "=" not in word and not word.startswith("~"):
            raise ConfigError(_not_an_override(prog, word))
    return known


def _not_an_override(prog: str, word: str) -> str:
    """The refusal of an argument that is not ``KEY=VALUE``, with the override it likely meant."""
    if Path(word).exists():  # a run folder or checkpoint, given without its key
        hint: str | None = f"{'resume' if prog == 'drone-train' else 'checkpoint'}={word}"
    else:
        hint = next((f"{g}={word}" for g in config.group_names() if word in config.group_options(g)), None)
    return f"{word!r} is not KEY=VALUE; " + (f"did you mean {hint}?" if hint else f"see {prog} --help")


# Each command's config in conf/.
CONFIGS = {"drone-train": "config", "drone-eval": "eval", "drone-export": "export"}


def check(prog: str) -> list[Path]:
    """Check ``sys.argv`` for ``prog`` (drone-train, drone-eval, drone-export); returns the folders claimed.

    In the order the errors are reported: drone-train's old keys (each with a note naming today's,
    :func:`~drone_torchrl.migrations.legacy_arguments`), the flags and bare words
    (:func:`parse_flags`), the overrides (:func:`~drone_torchrl.config.check_overrides`, skipped when
    the command line picks another config, whose keys ``conf/`` does not describe) and the folder
    Hydra writes first; then drone-train's own: missing extras, ``-m`` with ``--cfg``, the launcher's
    keys, a sweep's or a single run's checks, and the claim of the run folder. Exits with
    ``<prog>: error: <message>`` on a bad input.
    """
    import sys

    from hydra import compose, initialize_config_dir

    trains = prog == "drone-train"
    args = sys.argv[1:]
    try:
        if trains:  # old keys (engine=, compile=, ...) work, passed on as +legacy.<key>
            args, notes = migrations.legacy_arguments(args)
            for note in notes:
                print(f"{prog}: {note}", file=sys.stderr)
            sys.argv[1:] = args
        flags = parse_flags(prog, args)
        # {key: value} of the key=value overrides (the last one wins, as in Hydra)
        pairs = (arg.split("=", 1) for arg in args if not arg.startswith("-") and "=" in arg)
        overrides = {key.lstrip("+~"): value for key, value in pairs}
        # A resumed run's own plug-ins (algo=ppo) where the defaults are others: its keys are theirs.
        implied = resumed_plugins(overrides) if trains and not flags.multirun else []
        config.imply_choices(implied)
        flags.overrides[:0] = implied  # beside the others: Hydra reads the overrides after a flag as unknown
        at = sys.argv.index(flags.overrides[len(implied)]) if implied else 0
        sys.argv[at:at] = implied
        own_config = flags.config_name is None and flags.config_dir is None
        if own_config and flags.config_path is None:
            config.check_overrides(flags.overrides, CONFIGS[prog])
        if trains:
            check_extras(overrides)  # hydra/launcher=, logger= whose extra is missing
        prints = flags.cfg or flags.info or flags.help or flags.hydra_help  # and trains nothing
        if trains and flags.multirun and (flags.cfg or flags.info):  # Hydra: a ValueError traceback
            flag = "--cfg" if flags.cfg else "--info"
            raise ConfigError(
                f"{flag} and -m are not allowed together: {flag} prints one job's config; drop -m and give "
                "one value per key"
            )
        if not prints and own_config and prog != "drone-export":  # drone-export writes no folder of Hydra's
            config.check_default_folder(CONFIGS[prog], args)
        if not trains:
            return []
        if own_config:
            check_launcher_keys(flags.overrides)
        if flags.multirun:
            if overrides.get("resume", "null") not in ("null", ""):
                raise ConfigError(
                    f"resume={overrides['resume']} continues one run and cannot be swept (-m); to continue a "
                    "sweep, run the same sweep command again: its finished jobs are skipped and the others resume"
                )
            return []
        check_single_run(flags.overrides, trains=not prints)
        if flags.cfg in ("job", "all") and own_config:  # refused as when training, not printed as fine
            with initialize_config_dir(config.config_dir(), version_base="1.3"):
                cfg = compose("config", overrides=flags.overrides)
            migrations.apply_legacy(cfg)
            config.validate(cfg)
        folder = None if prints else claim_run_folder(overrides)
    except (ConfigError, StorageError) as err:
        sys.exit(f"{prog}: error: {err}")
    return [] if folder is None else [folder]


def check_extras(overrides: dict[str, str]) -> None:
    """Refuse, in one line, a ``hydra/launcher=`` or ``logger=`` choice whose extra is not installed.

    What each choice needs is :mod:`drone_torchrl.extras`'s (a logger's: its backend's
    :attr:`~drone_torchrl.loggers.Backend.extra`); each option of a swept choice (``logger=csv,mlflow``)
    is checked. Raises :class:`~.checks.ConfigError` naming the choice as typed and the extra.
    """
    if "hydra/launcher" in overrides:
        for option in _options("hydra/launcher", overrides["hydra/launcher"]):
            extras.check(f"hydra/launcher={option}", extras.LAUNCHERS.get(option))
    from hydra.errors import HydraException

    from drone_torchrl import loggers

    for option in _options("logger", overrides["logger"]) if "logger" in overrides else []:
        try:  # Hydra composes the option (its file names its backend, or inherits one)
            needs = loggers.get(config._option_plugins("config", (("logger", option),))["logger"]).needs
        except (HydraException, ConfigError):  # an option Hydra cannot compose: it says why, later
            continue
        extras.check(f"logger={option}", needs)


def _options(group: str, value: str) -> list[str]:
    """The options of ``group=value`` as Hydra reads them: one, or each of a sweep's."""
    return [
        v for o in _parsed([f"{group}={value}"]) for v in config._override_values(o) if isinstance(v, str)
    ]


_LAUNCHER_KEY = "hydra.launcher."


def check_single_run(args: list[str], trains: bool = True) -> None:
    """Refuse, in one line, what only a sweep (``-m``) reads, on a command line without ``-m``.

    A sweep override (``key=a,b``, ``key=interval(low,high)``: Hydra's message is several lines) and,
    where the command ``trains`` (not ``--cfg``, ``--info``), a population or search launcher
    (:data:`~drone_torchrl.sweep_folder.SEARCH_LAUNCHERS`, which Hydra would ignore). Raises :class:`~.checks.ConfigError`.
    """
    for override in _parsed(args):
        key = override.key_or_group
        if override.is_sweep_override():
            raise ConfigError(
                f"{override.input_line} is not allowed without -m: it gives several values (a sweep); give "
                f"one value, write a list value as {key}=[a,b], or sweep it: drone-train -m {override.input_line}"
            )
        if trains and key == "hydra/launcher" and override.value() in SEARCH_LAUNCHERS:
            raise ConfigError(
                f"{override.input_line} is not allowed without -m: it trains the jobs of a sweep (a single "
                f"run would ignore it); expected drone-train -m {override.input_line} <key>=<a>,<b>,... "
                "(e.g. seed=0,1,2,3)"
            )


def check_launcher_keys(args: list[str]) -> None:
    """Refuse, in one line, a ``hydra.launcher.<key>`` override that the chosen launcher does not have.

    Hydra refuses an unknown one in several lines, and takes ``+hydra.launcher.<key>`` silently (or
    fails when it makes the launcher). The launcher is the command line's ``hydra/launcher`` (each
    option of a swept one), else the one the config and its chosen options give. Raises
    :class:`~.checks.ConfigError` naming the key and the launcher's keys.
    """
    from hydra.errors import HydraException
    from omegaconf import OmegaConf

    parsed = _parsed(args)
    given = [o for o in parsed if o.key_or_group.startswith(_LAUNCHER_KEY)]
    if not given:
        return
    # Group choices (+sweep=lr may set the launcher) composed as given; swept ones and values left out.
    choices = [
        o.input_line
        for o in parsed
        if "." not in o.key_or_group and o.key_or_group != "hydra/launcher" and not o.is_sweep_override()
    ]
    launcher = next((o for o in parsed if o.key_or_group == "hydra/launcher"), None)
    options = [None] if launcher is None else _options("hydra/launcher", launcher.input_line.split("=", 1)[1])
    for option in options:
        try:  # the launcher these choices compose (the checks' compositions are cached)
            cfg = config._composed(
                "config", (*choices, *([] if option is None else [f"hydra/launcher={option}"]))
            )
        except HydraException:  # Hydra's own message says why, later
            continue
        name = cfg.hydra.runtime.choices["hydra/launcher"]
        keys = sorted(k for k in OmegaConf.to_container(cfg.hydra.launcher, resolve=False) if k != "_target_")
        for override in given:
            key = override.key_or_group.removeprefix(_LAUNCHER_KEY).split(".")[0]
            if key not in keys:
                known = f"its keys: {', '.join(keys)}" if keys else "it takes no hydra.launcher keys"
                raise ConfigError(
                    f"{override.input_line} is not allowed: hydra/launcher={name} has no key {key!r}; {known}"
                )


def _parsed(args: list[str]) -> list:
    """The command line's overrides, parsed by Hydra (those it cannot parse are refused elsewhere)."""
    return config.parse_overrides([a for a in args if not a.startswith("-") and "=" in a], strict=False)


def resumed_plugins(overrides: dict[str, str]) -> list[str]:
    """The ``group=<option>`` choices a single run's ``resume=<checkpoint>`` is composed with.

    The resumed run's plug-ins where they are not the defaults and the command line chooses no
    option of their group: ``resume=<a PPO run> algo.target_kl=...`` is then checked and composed
    against PPO's keys, as they are keys of the run. None for a checkpoint that
    :func:`~drone_torchrl.config.open_checkpoint` refuses (the resume refuses it in its own line), nor
    when the command line chooses a preset, whose options may pick plug-ins themselves.
    """
    from drone_torchrl import schema

    resume = overrides.get("resume")
    if resume in (None, "", "null") or "${" in resume:
        return []
    # Only where they matter (a checkpoint may be GBs): a plug-in's key the default plug-in lacks,
    # or a group choice (the keys it sets are told from the config composed with the run's plug-ins).
    defaults = config._option_plugins("config", ())
    known = config.schema_keys("config", **defaults)
    plugin_groups = schema.plugin_groups("config")
    chosen = {key for key in overrides if key in config.group_names()}
    if config.PRESET_GROUP in chosen or not any(
        key in chosen or (key.split(".")[0] in plugin_groups and key not in known) for key in overrides
    ):
        return []
    try:
        _, state = config.open_checkpoint("resume", resume)
    except ConfigError:
        return []
    saved = config.run_config(state["config"])
    out = []
    for group, rule in plugin_groups.items():
        plugin = dotted(saved, f"{group}.{rule.plugin_key}")
        if group in chosen or plugin == defaults.get(group):
            continue
        options = config.options_by_plugin(group).get(plugin, [])  # composes each option of the group
        if options:
            out.append(f"{group}={plugin if plugin in options else options[0]}")
    return out


def claim_run_folder(overrides: dict[str, str]) -> Path | None:
    """Claim the folder a single run will write before Hydra writes into it; returns it (or None).

    - ``hydra.run.dir=<folder>``: refused inside a sweep folder (unless it is one of its jobs, which
      then continues); claimed. If it already holds a run, Hydra does not rewrite that run's
      ``.hydra/`` record (``hydra.output_subdir``: :func:`~drone_torchrl.io.folders.record_subdir`).
    - ``resume=<run>`` (its last checkpoint): that run's folder is claimed.
    - ``resume=<another checkpoint>`` (a fork) with ``hydra.run.dir=<folder>``: refused unless the
      folder is new or empty (:func:`~drone_torchrl.io.folders.check_fork_folder`), before its lock
      is taken: another run's folder stays byte for byte.

    Values Hydra resolves later (``${...}``) and paths that are not usable are left to the checks
    that report them.
    """
    resume = overrides.get("resume")
    path = None
    if resume not in (None, "", "null") and "${" not in resume:
        with contextlib.suppress(OSError):
            path = resolve_checkpoint(resume)
    run_dir = overrides.get("hydra.run.dir")
    if run_dir is not None and run_dir.strip() and "${" not in run_dir:
        folder = Path(run_dir).expanduser()
        root = next((p for p in folder.resolve().parents if (p / SWEEP_RECORD).is_file()), None)
        if root is not None and not (folder / ".hydra").is_dir():
            raise ConfigError(
                f"hydra.run.dir={run_dir} is inside the sweep folder {root}, whose job folders its sweep "
                "names; give the run a folder outside it"
            )
        if path is not None and not is_last_of_its_run(path):
            check_fork_folder(folder, resume)
        run_lock.hold(folder)
        return folder
    if path is not None and is_last_of_its_run(path):
        run_lock.hold(run_dir_of(path))
        return run_dir_of(path)
    return None
