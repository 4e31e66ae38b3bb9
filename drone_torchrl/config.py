"""Where the Hydra configs live, and the checks every config passes before any work starts."""

from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import os
from collections.abc import Iterable, Mapping, Sequence
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from drone_torchrl import loggers, memory_estimate, migrations, schema, sweep_folder
from drone_torchrl.checks import ConfigError, dotted, first_line, plain_name
from drone_torchrl.envs.drone_env import check_env_args, make_params
from drone_torchrl.envs.params import PARAM_NAMES, DroneParams
from drone_torchrl.io import folders
from drone_torchrl.io.checkpoint import (
    CheckpointError,
    check_weights,
    is_population,
    load_checkpoint,
    resolve_checkpoint,
)
from drone_torchrl.io.storage import name_too_long, unwritable
from drone_torchrl.registry import ALGORITHMS
from drone_torchrl.schema import Rule

# The device kinds the code runs on. Others fail deep inside (mps has no float64 for the
# population optimizer's per-agent scalars; meta holds no numbers), so they are refused up front.
DEVICE_KINDS = ("cpu", "cuda")
# The DroneEnv arguments a config holds under env.*: the env schema's keys but the TorchRL
# collector's worker count (drone_torchrl.schema.EnvConf is the one list of them).
ENV_ARGS = tuple(f.name for f in dataclasses.fields(schema.EnvConf) if f.name not in schema.ENV_NON_ARGS)
#: The env arguments added after the first runs, with the value the runs saved before them behaved
#: as; a saved config (a checkpoint's, a run folder's config.yaml) without one of them gets it (env_kwargs).
ENV_ADDED = {
    "disturbance": None,  # a section (env.disturbance.*): a config from before it flew the nominal drone
    **{
        key: rule.added for key, rule in schema.fields(schema.EnvConf, {}) if "." not in key and rule.is_added
    },
}


# Resolvers the configs use (registered at import: every process that composes imports this module).
OmegaConf.register_new_resolver("drone_torchrl.job_dirname", migrations.job_dirname, replace=True)
# Not cached: each job's folder is its own (drone_torchrl.io.folders.record_subdir).
OmegaConf.register_new_resolver("drone_torchrl.record_subdir", folders.record_subdir, replace=True)
# Cached as Hydra's ${now:} is: each job's config gets the sweep's value (drone_torchrl.sweep_folder).
OmegaConf.register_new_resolver(
    "drone_torchrl.sweep_folder", sweep_folder.sweep_folder, replace=True, use_cache=True
)


def config_dir() -> str:
    """Absolute path of the ``conf/`` folder.

    A wheel ships the top-level ``conf/`` as ``drone_torchrl/conf`` (pyproject's package-dir);
    a source checkout or editable install reads the top-level folder itself.
    """
    # The configs name hydra/launcher=fused and hydra/sweeper=population, and list the schemas of
    # drone_torchrl.schema (imported above) and of every plug-in (each algorithm and logger module
    # stores its own when imported: discovered here): all must be in Hydra's ConfigStore before
    # composing, also where Hydra's plugin scan does not see them (an editable install's
    # hydra_plugins is an import hook, not a folder).
    import drone_torchrl.launcher_schemas  # noqa: F401

    _discover_plugins()

    package = Path(__file__).resolve().parent
    for candidate in (package / "conf", package.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return str(candidate)
    raise FileNotFoundError(f"drone_torchrl's conf/ folder is missing (looked in {package} and its parent)")


# Free space a run folder needs before Hydra starts: Hydra writes its record (.hydra/, three YAML
# files) and the job's log there before any of our code runs, and fails in many lines when it
# cannot; a tmpfs takes a 4 KiB page per file. 1 MiB holds them and the first checkpoint or plot.
HYDRA_ROOM = 1 << 20
# What a run writes into its folder: logger.exp_name must not collide with one of them.
RUN_FOLDER_ENTRIES = frozenset(
    {"checkpoints", "videos", "episodes.csv", "config.yaml", "FAILED.txt", ".hydra", "train.log", ".lock"}
)
# Groups chosen with ``group=option`` (a file conf/<group>/<option>.yaml); Hydra's own groups
# (hydra/launcher, hydra/sweeper) are Hydra's to check.
_HYDRA_PREFIX = "hydra"
# The registry of each plug-in group (drone_torchrl.schema.plugin_groups): its one-line error names
# the registered plug-ins when a config names another; the plug-ins page lists them (plugin_docs).
REGISTRIES = {"algo": ALGORITHMS.get, "logger": loggers.get}


@functools.cache
def schema_keys(name: str = "config", **plugins: str | None) -> dict[str, Rule]:
    """Every key of a ``conf/<name>.yaml`` config, in order, with its :class:`~drone_torchrl.schema.Rule`.

    Returns ``{"algo.lr": rule, ...}``, from the schemas in Hydra's ConfigStore. ``plugins``: the
    plug-in of each plug-in group (``algo="ppo"``; a group not given, or a plug-in without a stored
    schema, adds no keys).
    """
    _discover_plugins()  # a plug-in not imported yet has no stored schema: its keys would be missing
    nodes = {group: schema.plugin_schema(group, plugin) for group, plugin in plugins.items()}
    return dict(schema.fields(schema.PRIMARY[name], nodes))


def _discover_plugins() -> None:
    """Import every algorithm and logger plug-in, so that each stores its schema.

    Each stores it when imported. The cached key lists above must not be made before they are (a
    caller that asks before any app ran).
    """
    ALGORITHMS.names()
    loggers.BACKENDS.names()


@functools.cache
def per_agent_keys(name: str = "config") -> tuple[str, ...]:
    """Keys that may differ between the agents of one population (every plug-in's): all others must be equal."""
    return tuple(key for key, rule in _every_key(name).items() if rule.per_agent)


def resume_rule(key: str) -> str:
    """What a continued run does with ``key``; a key no schema has is kept.

    One of :data:`~drone_torchrl.schema.KEPT`, ``IF_SET``, ``BUDGET`` or ``PROCESS``.
    """
    rule = _every_key("config").get(key)
    return schema.KEPT if rule is None else rule.on_resume


@functools.cache
def _every_key(name: str) -> dict[str, Rule]:
    """Every key of ``conf/<name>.yaml`` with any plug-in stored in the ConfigStore.

    Each plug-in's rule of a key the plug-ins share is the same.
    """
    _discover_plugins()  # stored_plugins lists the schemas stored, each when its plug-in is imported
    out: dict[str, Rule] = {}
    for group in schema.plugin_groups(name):
        for plugin in schema.stored_plugins(group):
            out.update(schema_keys(name, **{group: plugin}))
    return out or dict(schema_keys(name))


def leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """``{"algo.lr": 0.0001, ...}``: every leaf of a config (lists are leaves), Hydra's node left out."""
    if not isinstance(node, DictConfig | Mapping):
        return {prefix: OmegaConf.to_container(node) if isinstance(node, ListConfig) else node}
    out: dict[str, Any] = {}
    for key in node:
        if not prefix and key == _HYDRA_PREFIX:
            continue
        out.update(leaves(node[key], f"{prefix}.{key}" if prefix else str(key)))
    return out


# The ``group=option`` choices drone-train added to a resumed run's command line
# (drone_torchrl.command_line.resumed_plugins):
# the run's own plug-ins, not keys the user set.
_implied: list[str] = []


def imply_choices(choices: Iterable[str]) -> None:
    """Record the choices added to this process's command line for a resumed run: not the user's keys.

    They are :func:`drone_torchrl.command_line.resumed_plugins`'.
    """
    _implied[:] = list(choices)


def command_line_keys() -> set[str] | None:
    """Keys (and group names) set on the command line of this Hydra job; None outside a Hydra app.

    The choices drone-train added for a resumed run's plug-ins (:func:`imply_choices`) are not among them.
    """
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    # Unresolved: an override's value may be an interpolation that does not resolve (reported later).
    task = OmegaConf.to_container(HydraConfig.get().overrides.task, resolve=False)
    implied = set(_implied)
    return {str(o).split("=", 1)[0].lstrip("+~") for o in task if str(o) not in implied}


def composed_leaves(overrides: tuple[str, ...] = (), name: str = "config") -> dict[str, Any]:
    """Every leaf of ``conf/<name>.yaml`` composed with ``overrides`` (:func:`leaves`, completed)."""
    cfg = _composed(name, tuple(overrides))
    complete(cfg, name)
    return leaves(cfg)


def implied_choices() -> tuple[str, ...]:
    """The choices :func:`imply_choices` recorded."""
    return tuple(_implied)


def group_options(group: str) -> list[str]:
    """The options of config group ``group`` (``algo`` -> ``["a2c", "ppo", ...]``: its YAML files), sorted."""
    return sorted(p.stem for p in (Path(config_dir()) / group).glob("*.yaml"))


def options_by_plugin(group: str, name: str = "config") -> dict[str, list[str]]:
    """The plug-in each option of plug-in group ``group`` chooses, with the options that choose it.

    Returns ``{"reinforce": ["reinforce", "reinforce_plus"], ...}``; an option Hydra cannot compose
    is left out.
    """
    out: dict[str, list[str]] = {}
    for option in group_options(group):
        try:
            plugin = _option_plugins(name, ((group, option),))[group]
        except Exception:  # noqa: BLE001  (a broken option file: Hydra says why when it is used)
            continue
        out.setdefault(plugin, []).append(option)
    return out


def group_names() -> list[str]:
    """The config groups of ``conf/`` (its folders, Hydra's own left out), sorted."""
    return sorted(p.name for p in Path(config_dir()).iterdir() if p.is_dir() and p.name != _HYDRA_PREFIX)


def _unknown(key: str, known: Iterable[str]) -> ConfigError:
    group = key.split(".")[0]
    if group in schema.plugin_groups():  # another plug-in's key: say whose, not a look-alike of this one's
        owners = sorted(
            option
            for plugin, options in options_by_plugin(group).items()
            if key in schema_keys("config", **{group: plugin})
            for option in options
        )
        if owners:
            return ConfigError(
                f"{key} is not a key of this {group}; it belongs to {group}={f' or {group}='.join(owners)}"
            )
    # A group's name misspelt (algoo=ppo) is nearer a group than any key's full dotted name.
    group = difflib.get_close_matches(key, group_names(), n=1, cutoff=0.75) if "." not in key else []
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]}?" if close else " (see conf/ or drone-train --cfg job for the keys)"
    if group:
        hint = f"; did you mean {group[0]}={'|'.join(group_options(group[0]))}?"
    return ConfigError(f"{key} is not a config key{hint}")


def _option_plugins(name: str, choices: tuple[tuple[str, str], ...]) -> dict[str, str | None]:
    """The plug-in each plug-in group names in ``conf/<name>.yaml`` composed with these group options.

    Returns ``{"algo": "reinforce", "logger": "tensorboard"}``; Hydra composes the config with the
    options given (``(("algo", "reinforce_plus"),)``; the others: the config's defaults). An
    option's file name is free, so only Hydra knows its plug-in: several options may share one
    (reinforce_plus is REINFORCE with other values).
    """
    # A default option is left out: the default composition (the checks' first) serves it.
    default = _chosen(name, ()) if choices else {}
    cfg = _composed(name, tuple(f"{g}={o}" for g, o in choices if default.get(g) != o))
    return {
        group: OmegaConf.select(cfg, f"{group}.{rule.plugin_key}", default=None)
        for group, rule in schema.plugin_groups(name).items()
    }


@functools.cache
def _composed(name: str, overrides: tuple[str, ...]) -> DictConfig:
    """``conf/<name>.yaml`` composed by Hydra with ``overrides``, Hydra's node included.

    Cached: the checks ask for the same composition (about 0.2 s) several times.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    inside = GlobalHydra.instance().is_initialized()  # inside a Hydra app (or a test's initialize)
    with nullcontext() if inside else initialize_config_dir(config_dir(), version_base="1.3"):
        return compose(name, overrides=list(overrides), return_hydra_config=True)


def _chosen(name: str, overrides: tuple[str, ...]) -> dict[str, str]:
    """The option of each config group (Hydra's own left out) of :func:`_composed`."""
    choices = _composed(name, overrides).hydra.runtime.choices
    return {g: choices[g] for g in choices if g.split("/")[0] != _HYDRA_PREFIX}


def check_keys(cfg: DictConfig | Mapping, name: str = "config") -> Mapping:
    """Refuse keys the schema does not have, keys without a value, and plug-ins without a schema.

    The schema is that of ``conf/<name>.yaml``; a key it lacks was e.g. added with ``+``. Returns
    the config as resolved plain data with attribute access (``???`` and interpolations to nothing
    are refused).
    """
    # The config as plain data, resolved, Hydra's own node left out: each section at once rather
    # than node by node through OmegaConf, which costs more than twice as much.
    resolved: Any = {} if isinstance(cfg, DictConfig) else cfg
    try:
        for key in (k for k in cfg if k != _HYDRA_PREFIX) if isinstance(cfg, DictConfig) else ():
            value = cfg[key]
            if isinstance(value, DictConfig | ListConfig):
                try:
                    value = OmegaConf.to_container(value, resolve=True, throw_on_missing=True)
                except OmegaConfBaseException:
                    leaves(value)  # read node by node: the error then names the key from the root
                    raise
            resolved[str(key)] = value
    except OmegaConfBaseException as err:  # e.g. algo.lr=${oops}: an interpolation that resolves to nothing
        key = getattr(err, "full_key", None) or "a config value"
        first = first_line(err)
        raise ConfigError(f"{key} cannot be read: {first}") from None
    known = schema_keys(name, **_plugins(resolved, name))
    for section in complete(resolved, name):  # set to something else than its keys: null, a number...
        _check_section(section, dotted(resolved, section), known, group_names())
    given = leaves(resolved)
    missing = [k for k in known if k not in given and not any(g.startswith(f"{k}.") for g in given)]
    if missing:
        raise ConfigError(f"{missing[0]} is missing (deleted with ~?); every config key needs a value")
    for key in given:
        # A list or dict value (e.g. model.hidden_sizes) may hold any shape of its own.
        if key not in known and not any(key.startswith(f"{k}.") for k in known):
            raise _unknown(key, known)
    return _plain(resolved)


def complete(cfg: DictConfig | dict, name: str = "config") -> list[str]:
    """Fill in place the keys an open section of ``cfg`` leaves out with their ``added`` values.

    A composed config lists ``env.disturbance.*`` only where they differ from the nominal drone; the
    code and a run's saved config see them all.

    Args:
        cfg: a composed config, or one as nested dicts.
        name: the primary config it is of (``config``, ``eval``).

    Returns:
        The open sections that hold something other than a mapping (left as they are, for
        :func:`check_keys` to refuse).
    """
    refused = []
    for section, defaults in schema.open_sections(schema.PRIMARY[name]).items():
        parent_key, _, last = section.rpartition(".")
        parent = dotted(cfg, parent_key)
        if not isinstance(parent, Mapping) or last not in parent:
            continue
        given = parent[last]
        if not isinstance(given, Mapping):
            refused.append(section)
            continue
        if set(defaults) <= set(given):
            continue
        with open_dict(parent) if isinstance(parent, DictConfig) else nullcontext():
            parent[last] = {**defaults, **given}
    return refused


def _plugins(resolved: Mapping, name: str) -> dict[str, str]:
    """The plug-in each plug-in group of ``resolved`` names; one that has no schema is refused."""
    _discover_plugins()  # a fresh process (a joblib or submitit worker) has imported none of them
    out: dict[str, str] = {}
    for group, rule in schema.plugin_groups(name).items():
        plugin = dotted(resolved, f"{group}.{rule.plugin_key}")
        if schema.plugin_schema(group, plugin) is None:
            REGISTRIES[group](plugin)  # not a registered plug-in: its registry's one-line error
            raise ConfigError(
                f"{group}.{rule.plugin_key}={plugin!r} has no config schema: its plug-in must store one "
                f"with drone_torchrl.schema.store_plugin({group!r}, {plugin!r}, ...)"
            )
        out[group] = plugin
    return out


def check_values(resolved: Mapping, name: str = "config") -> None:
    """Check every rule of the schema (:mod:`drone_torchrl.schema`) on the resolved config.

    ``resolved``: nested dicts, keys checked by :func:`check_keys`. The first value a rule refuses
    raises :class:`~.checks.ConfigError`.
    """
    for key, rule in schema_keys(name, **_plugins(resolved, name)).items():
        rule.check(key, dotted(resolved, key), resolved)


def check_overrides(overrides: Iterable[str], name: str = "config") -> None:
    """One-line errors for command-line overrides Hydra would reject in several lines, or accept wrongly.

    Accepted wrongly means accepted though they make no sense. The overrides refused: an unknown
    key (with or without ``+``), an unknown group option, a run folder that is a file, and an
    override Hydra cannot parse (its grammar error in one line).
    """
    parsed = parse_overrides(overrides)
    groups = group_names()
    plugin_keys = {f"{group}.{rule.plugin_key}": group for group, rule in schema.plugin_groups(name).items()}
    # The options each group picks: its last override's, every one a sweep names (one that is no
    # option is refused below, in its turn).
    picks = {
        o.key_or_group: [v for v in _override_values(o) if v in group_options(o.key_or_group)]
        for o in parsed
        if o.key_or_group in groups and not o.is_delete()
    }
    known = _override_keys(picks, name)
    if known is None:  # Hydra cannot compose these group options: its own message says why
        return
    for override in parsed:
        key = override.key_or_group
        section = key not in known and any(k.startswith(f"{key}.") for k in known)
        if override.is_delete():
            # OmegaConf refuses to delete a field of a nested schema (several lines); a top-level key
            # would be refused as missing: either way, say it first.
            if key in known or (section and key not in groups):
                raise ConfigError(f"{key} cannot be deleted (~{key}); every config key needs a value")
            if key in groups and any(k.startswith(f"{key}.") or f".{key}." in k for k in known):
                raise ConfigError(
                    f"{key} cannot be deleted (~{key}): its keys need values; choose another option: "
                    f"{key}=<one of {group_options(key)}>"
                )
            continue
        values = _override_values(override)
        if key in plugin_keys:
            # The plug-in comes with its keys, so it is chosen with its group, which sets the key;
            # setting the key alone leaves the other plug-in's keys.
            group = plugin_keys[key]
            options = [
                o for o in group_options(group) if _option_plugins(name, ((group, o),))[group] == values[0]
            ]
            how = f"{group}={options[0]}" if options else f"{group}=<option>, one of {group_options(group)}"
            raise ConfigError(
                f"{key}={values[0]!r} cannot be set on its own (each {group} option sets it, "
                f"with its plug-in's keys); choose it with {how}"
            )
        if key.startswith(f"{migrations.LEGACY}.") and migrations.is_old_key(key.split(".", 1)[1]):
            continue  # an old key, passed on as +legacy.<key> (drone_torchrl.migrations.legacy_arguments)
        hydra = key.split(".")[0].split("/")[0] == _HYDRA_PREFIX
        for value in values:
            if key in ("hydra.run.dir", "hydra.sweep.dir"):
                _check_folder(key, value)
            elif hydra and "/" in key and not isinstance(value, str):  # a Hydra group (hydra/launcher)
                # Hydra raises a traceback for null or a list.
                raise ConfigError.of(key, value, f"the name of one of its options, e.g. {key}=basic")
            elif key == "sweep_name" and value is not None:  # the multirun folder (null: named by overrides)
                _check_folder_name(key, value, "a folder name (no '/' or '..'), e.g. lr")
            elif key in groups and value not in group_options(key):
                raise ConfigError.of(key, value, f"one of {group_options(key)}")
            elif section and key not in groups:
                _check_section(key, value, known, groups)
        if hydra or section or key == "sweep_name" or key in groups:
            continue
        if key in migrations.FIXED:  # on drone-train's command line it was passed on as +legacy.<key>
            raise ConfigError(migrations.fixed_refusal(key, values[0]))
        if key not in known:
            raise _unknown(key, known)


def parse_overrides(overrides: Iterable[str], strict: bool = True) -> list:
    """The overrides parsed by Hydra, one by one.

    One Hydra cannot parse is refused in one line (its grammar error), or left out when not
    ``strict`` (:func:`check_overrides` refuses it).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    parsed = []
    for override in overrides:
        try:
            parsed += parser.parse_overrides([override])
        except HydraException as err:
            if not strict:
                continue
            lines = (x for x in str(err).splitlines() if x.strip() and not x.startswith("Error parsing"))
            reason = next(lines, type(err).__name__)  # Hydra's first line of substance
            raise ConfigError(
                f"{override} cannot be parsed: {reason} (Hydra's override syntax: key=value, "
                "key=[a,b] for a list, quote values with special characters)"
            ) from None
    return parsed


def _override_values(override: Any) -> list[Any]:
    """The value of a parsed override, or each value of a sweep (an interval's: its two ends)."""
    if override.is_sweep_override() and not override.is_discrete_sweep():
        return [override.value().start, override.value().end]
    return list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]


def _check_section(key: str, value: Any, known: Mapping[str, Rule], groups: list[str]) -> None:
    """Check that a section set on the command line is a mapping of its own keys.

    A section is e.g. ``env.disturbance`` or ``eval``, which Hydra merges; null, a number or a list
    fail Hydra's merge in several lines.
    """
    if isinstance(value, Mapping):
        for sub, inner in value.items():
            full = f"{key}.{sub}"
            if full not in known and not any(k.startswith(f"{full}.") for k in known):
                raise _unknown(full, known)
            if isinstance(inner, Mapping):
                _check_section(full, inner, known, groups)
        return
    first = next(k for k in known if k.startswith(f"{key}."))
    group = key.split(".")[-1]
    preset = (
        f", or a preset: {group}=<one of {group_options(group)}>" if group in groups and group != key else ""
    )
    raise ConfigError.of(key, value, f"its keys set one by one (e.g. {first}=...){preset}")


# The group whose options are presets (experiment=bounded). A preset's keys of one plug-in live in
# conf/<plug-in group>/presets/<plug-in>/<preset>.yaml, which that plug-in's options include
# (conf/algo/reinforce.yaml), so they reach only that plug-in.
PRESET_GROUP = "experiment"
PLUGIN_PRESETS = "presets"


def _override_keys(picks: Mapping[str, list[str]], name: str) -> dict[str, Rule] | None:
    """The keys of ``conf/<name>.yaml`` composed with the group options ``picks`` names, or None.

    ``picks``: each group's options (several: a sweep's); an option of any group may pick the
    plug-in, e.g. ``experiment=hover_optimal`` picks ``algo=ppo``. None if Hydra cannot compose
    those. Over a sweep, the keys every one of its jobs has. A preset that picks a plug-in given
    another on the command line is refused, naming the preset it builds on as the way.
    """
    plugin_groups = schema.plugin_groups(name)
    if not plugin_groups:
        return schema_keys(name)
    known: dict[str, Rule] | None = None
    for combination in itertools.product(*([(g, o) for o in opts] for g, opts in picks.items() if opts)):
        chosen = dict(combination)
        preset, own = chosen.get(PRESET_GROUP), {}
        if preset is not None:  # the plug-ins the preset picks: its choices that differ from none's
            try:  # an option Hydra cannot compose (a broken file): Hydra's own message says what
                bare, picked = (_chosen(name, (o,)) for o in (f"~{PRESET_GROUP}", f"{PRESET_GROUP}={preset}"))
            except Exception:  # noqa: BLE001
                return None
            own = {g: o for g, o in picked.items() if g != PRESET_GROUP and bare.get(g) != o}
        for group in plugin_groups:
            mine, theirs = chosen.get(group), own.get(group)
            if mine is None or theirs is None or mine == theirs:
                continue
            # The presets it builds on: the options of its own group in its defaults list.
            defaults = OmegaConf.load(Path(config_dir()) / PRESET_GROUP / f"{preset}.yaml").get("defaults")
            bases = [d for d in defaults or [] if isinstance(d, str) and d in group_options(PRESET_GROUP)]
            way = (
                f"{PRESET_GROUP}={bases[0]} {group}={mine}"
                if bases
                else f"{group}={mine} without {PRESET_GROUP}"
            )
            also = " ".join(f"{g}={o}" for g, o in own.items() if g != group and g not in chosen)
            raise ConfigError(
                f"{PRESET_GROUP}={preset} is made for {group}={theirs} (it sets {theirs}'s values) and cannot "
                f"take {group}={mine}; for {group}={mine} use {way}"
                + (f" (it also sets {also})" if also else "")
            )
        try:
            keys = schema_keys(name, **_option_plugins(name, combination))
        except Exception:  # noqa: BLE001  (e.g. a broken option file: Hydra's own message says what)
            return None
        known = keys if known is None else {k: rule for k, rule in known.items() if k in keys}
    return known


def preset_notes(choices: Mapping[str, Any], name: str = "config") -> list[str]:
    """The notes on a preset's keys that the chosen plug-in does not take (they are dropped).

    One line per plug-in group whose chosen plug-in does not take keys the chosen preset sets for
    another plug-in of the group, e.g. ``experiment=paper_code: algo.optimizer, ... do not apply to
    algo=ppo; dropped`` (``choices``: each config group's option, as Hydra's ``runtime.choices``).
    """
    preset = choices.get(PRESET_GROUP)
    if not isinstance(preset, str):
        return []
    notes = []
    for group in schema.plugin_groups(name):
        option = choices.get(group)
        files = sorted((Path(config_dir()) / group / PLUGIN_PRESETS).glob(f"*/{preset}.yaml"))
        if option is None or not files:
            continue
        keys = {file.parent.name: leaves(OmegaConf.load(file)) for file in files}
        own = keys.pop(str(_option_plugins(name, ((group, option),))[group]), {})
        dropped = [
            f"{group}.{k}" for k in dict.fromkeys(k for other in keys.values() for k in other) if k not in own
        ]
        if dropped:
            notes.append(
                f"{PRESET_GROUP}={preset}: {', '.join(dropped)} do not apply to {group}={option}; dropped"
            )
    return notes


def _check_folder_name(key: str, value: Any, expected: str, taken: Iterable[str] = ()) -> None:
    """Check that ``value`` of ``key`` names one folder, none of ``taken``, of a length the file system allows.

    Not one folder (:func:`plain_name`) or a taken name: the message asks for ``expected``. The
    length is the working folder's file system's (where run and sweep folders go by default).
    """
    if not plain_name(value) or value in taken:
        raise ConfigError.of(key, value, expected)
    if (too_long := name_too_long(value)) is not None:
        raise ConfigError.of(key, value, f"a folder name this file system takes ({too_long})")


def _check_folder(key: str, value: Any) -> None:
    """Check that the run can create or write into ``folder``.

    It must not be empty or a file, must be a name the file system takes, and must lie under a
    folder that is writable and not full (:func:`drone_torchrl.io.storage.unwritable`).
    """
    if not isinstance(value, str):
        return
    if not value.strip():
        raise ConfigError.of(key, value, "a folder path, not an empty string")
    # Hydra's own interpolations (${now:...}) resolve later: the folders above them are checked.
    literal = value.split("${")[0]
    why = unwritable(value if literal == value else os.path.dirname(literal) or ".", HYDRA_ROOM)
    if why is not None:
        raise ConfigError.of(key, value, f"a folder this user can write ({why})")


def check_default_folder(name: str, args: Iterable[str]) -> None:
    """The folder Hydra makes and writes its record into before any of our code runs.

    It is checked when ``args`` name none: the default of ``hydra.run.dir`` (``hydra.sweep.dir``
    with ``-m``) in ``conf/<name>.yaml``, e.g. ``outputs/<date>/<time>``. A read-only or full
    working folder is refused in one line (it was Hydra's traceback). For commands that train or
    fly (not for ``--cfg``, ``--help``), which write there.
    """
    args = list(args)
    key = "hydra.sweep.dir" if {"-m", "--multirun"} & set(args) else "hydra.run.dir"
    if any(a.split("=", 1)[0].lstrip("+") == key for a in args):
        return  # checked with the other overrides
    node = OmegaConf.to_container(OmegaConf.load(Path(config_dir()) / f"{name}.yaml"), resolve=False)
    _check_folder(key, dotted(node, key))


def run_config(saved: dict[str, Any]) -> DictConfig:
    """The config stored in a checkpoint, in today's keys, with the keys added since filled in.

    The keys replaced since are read as their new ones
    (:func:`drone_torchrl.migrations.migrate_config`: ``engine`` as ``backend``...). The keys added
    since get the value those runs behaved as (the schema's ``added``; only the keys of its
    plug-ins: a PPO run has no REINFORCE optimizer keys), so old runs can still be evaluated and
    resumed.
    """
    cfg = OmegaConf.create(migrations.migrate_config(saved))

    def fill(key: str, rule: Rule) -> Any:
        if OmegaConf.select(cfg, key, default=_ABSENT) is _ABSENT:
            OmegaConf.update(cfg, key, rule.added, force_add=True)
        return OmegaConf.select(cfg, key)

    # The plug-ins first (a config from before plug-ins gets their added ones), then their keys.
    plugins = {
        group: fill(f"{group}.{rule.plugin_key}", rule) for group, rule in schema.plugin_groups().items()
    }
    for key, rule in schema_keys("config", **plugins).items():
        if rule.is_added:
            fill(key, rule)
    return cfg


_ABSENT = object()


def physics_params(kwargs: dict[str, Any]) -> DroneParams:
    """The validated physical parameters and arena among ``DroneEnv`` arguments (what the dynamics need)."""
    return make_params(**{k: v for k, v in kwargs.items() if k in PARAM_NAMES})


def env_kwargs(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """The ``DroneEnv`` arguments of a config (a ``DictConfig`` or a saved one's plain dict).

    A saved config from before an argument existed gets its :data:`ENV_ADDED` value.
    """
    env = cfg["env"]
    kwargs = {name: env[name] if name in env else ENV_ADDED[name] for name in ENV_ARGS}
    if isinstance(kwargs["disturbance"], Mapping):  # plain, with the keys an open section leaves out: nominal
        kwargs["disturbance"] = {
            **schema.open_sections(schema.TrainConfig)["env.disturbance"],
            **kwargs["disturbance"],
        }
    return kwargs


def open_checkpoint(key: str, location: Any) -> tuple[Path, dict[str, Any]]:
    """The checkpoint that config value ``key`` (``resume``, ``checkpoint``) names.

    A checkpoint file or a run folder. Raises :class:`~.checks.ConfigError` naming the key for anything that
    is not a readable one. A population run's checkpoint comes back as it is (``population_record.open_agent``
    reads one agent of it).
    """
    if not isinstance(location, str | Path) or not str(location).strip():
        raise ConfigError.of(key, location, "a run folder or a checkpoint file (a path)")
    try:
        path = resolve_checkpoint(location)
    except FileNotFoundError as err:
        raise ConfigError(f"{key}={str(location)!r} is not allowed; {err}") from None
    try:
        state = load_checkpoint(path)
        if is_population(state):
            return path, state
        name = OmegaConf.select(run_config(state["config"]), "algo.name")
        if name not in ALGORITHMS.names():
            known = f"known: {list(ALGORITHMS.names())}"
            raise CheckpointError(f"it was written by algo.name={name!r}, which is not installed ({known})")
        if missing := [entry for entry in ALGORITHMS.get(name).checkpoint_keys if entry not in state]:
            raise CheckpointError(
                f"it lacks {', '.join(missing)} (algo.name={name} writes it): a damaged or foreign checkpoint"
            )
    except CheckpointError as err:
        raise ConfigError(f"{key}={str(path)!r} cannot be used: {err}") from None
    return path, state


def check_networks(key: str, path: Path, state: dict[str, Any], cfg: DictConfig) -> None:
    """Check that the checkpoint's weights fit the networks of ``cfg``.

    ``cfg`` is the run's config, validated. The networks are its actor and, for an algorithm that
    keeps one among its checkpoint entries, its critic; each tensor must have their shape.
    :class:`~.checks.ConfigError` naming the key, the file and the first tensor that differs;
    the networks are built on the meta device (shapes only: no memory, no time).
    """
    from drone_torchrl.modules.factory import build_actor, build_critic

    meta = OmegaConf.merge(cfg, {"device": "meta"})
    with torch.device("meta"):
        networks = {"actor": build_actor(meta)}
        if "critic" in ALGORITHMS.get(cfg.algo.name).checkpoint_keys:  # PPO's and A2C's value network
            networks["critic"] = build_critic(meta)
    try:
        for entry, module in networks.items():
            check_weights(module, state[entry], path, entry)
    except CheckpointError as err:
        raise ConfigError(f"{key}={str(path)!r} cannot be used: {err}") from None


def check_device(device: Any) -> None:
    """Raise :class:`~.checks.ConfigError` for a device torch does not know or this machine does not have."""
    try:
        kind = torch.device(device).type
    except (RuntimeError, TypeError, ValueError, OverflowError):  # ValueError: an index past int64
        raise ConfigError.of("device", device, "a torch device such as 'cpu' or 'cuda'") from None
    if kind not in DEVICE_KINDS:
        raise ConfigError.of("device", device, "'cpu' or 'cuda' ('cuda:N' for GPU number N)")
    if kind == "cuda" and not torch.cuda.is_available():
        raise ConfigError.of("device", device, "'cpu' here (this torch build or machine has no CUDA device)")


class _Plain(dict):
    """A resolved config as nested dicts with attribute access (``cfg.algo.lr``), for validation.

    It reads about 150 values, each a slow read through OmegaConf, and a population validates every job. (A key
    named like a dict method, ``items`` say, must be read as ``cfg["items"]``.)
    """

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


def _plain(node: Any) -> Any:
    if isinstance(node, dict):
        return _Plain((key, _plain(value)) for key, value in node.items())
    return node


def check_agent_values(cfg: DictConfig, values: Mapping[str, Sequence[Any]]) -> None:
    """The per-agent values of a population whose group config ``cfg`` passed :func:`validate`.

    Each distinct value of each column against its key's rule; the first refused raises
    :class:`AgentValueError` naming the agent. Then the config with every column's smallest values,
    and the one with its largest, pass :func:`validate` whole: the per-agent keys' rules are bounds,
    so the checks that relate them to other keys (an algorithm's own) meet their worst case at a
    column's ends (an end that is ``cfg`` itself is not checked again). Thousands of agents cost a
    few config checks, not one each.
    """
    varying = {key: column for key, column in values.items() if len(set(column)) > 1}
    if not varying:  # every agent's config is cfg, which passed
        return
    resolved = check_keys(cfg)
    rules = schema_keys("config", **_plugins(resolved, "config"))
    for key, column in varying.items():
        for value in dict.fromkeys(column):
            try:
                rules[key].check(key, value, resolved)
            except ConfigError as err:
                raise AgentValueError(column.index(value), str(err)) from None
    for pick in (min, max):
        values_at_end = {key: pick(column) for key, column in varying.items()}
        typed = {key: (type(value), value) for key, value in values_at_end.items()}
        if typed == {key: (type(v := OmegaConf.select(cfg, key)), v) for key in varying}:
            continue  # cfg itself (its agent is at this end), which passed
        end = cfg.copy()
        for key, value in values_at_end.items():
            OmegaConf.update(end, key, value)
        try:
            validate(end)
        except ConfigError as err:
            agent = min(column.index(pick(column)) for column in varying.values())
            raise AgentValueError(agent, str(err)) from None


class AgentValueError(ConfigError):
    """A per-agent value that is not allowed (:func:`check_agent_values`).

    Args:
        agent: the index of the agent whose value it is.
        message: the one-line error.
    """

    def __init__(self, agent: int, message: str) -> None:
        super().__init__(message)
        self.agent = agent


def validate(cfg: DictConfig, training: bool = True) -> None:
    """Raise :class:`~.checks.ConfigError` for the first value that is not allowed.

    ``training``: the config is about to train here, so its logger's extra must be installed and its memory
    must fit (``drone-eval`` reads a checkpoint's config for its values only).
    """
    cfg = check_keys(cfg)  # also refuses ??? and interpolations to nothing, in one line
    check_device(cfg.device)
    try:  # the env's own checks of its arguments (the schema leaves them to it; the device: above)
        env = check_env_args(**env_kwargs(cfg))  # no env built
    except ValueError as err:
        raise ConfigError(f"env.{err}") from None
    check_values(cfg)  # the bounds and choices of every key; what follows relates keys to each other
    if cfg.backend == migrations.FAST:
        from drone_torchrl.kernels.coverage import fast_refusal

        reason = fast_refusal(
            cfg.device,
            cfg.model.hidden_sizes,
            cfg.model.activation,
            cfg.env.dtype,
            env.disturbance,
            cfg.algo.name,
        )
        if reason is not None:
            raise ConfigError(f"backend=fast cannot take {reason}; backend=reference takes every option")
    ALGORITHMS.get(cfg.algo.name).validate(cfg)
    for key, acts in (("stop_return", "it ends a run"), ("rollback_drop", "it acts")):
        if cfg.eval.get(key) is not None and not cfg.eval.every_episodes:
            expected = f"null unless eval.every_episodes > 0 ({acts} at a periodic evaluation)"
            raise ConfigError.of(f"eval.{key}", cfg.eval[key], expected)
    drop = cfg.eval.get("rollback_drop")
    if drop is not None and not ALGORITHMS.get(cfg.algo.name).learner.takes_rollback_drop:
        takers = [n for n in ALGORITHMS.names() if ALGORITHMS.get(n).learner.takes_rollback_drop]
        expected = f"null with algo={cfg.algo.name} (taken by algo={'/'.join(takers)})"
        raise ConfigError.of("eval.rollback_drop", drop, expected)
    if training:  # drone-eval reads a finished run's values: its logger is the training's business
        loggers.check_backend(cfg)  # after the values: a bad value is named whether or not the extra is there
        if cfg.get("agent") is not None and cfg.get("resume") is None:  # else nothing reads it
            raise ConfigError.of(
                "agent",
                cfg.agent,
                "null without resume=: agent=K picks the agent of a population run to continue "
                "(drone-train resume=<population run> agent=K), to fly (drone-eval) or export (drone-export)",
            )
    if cfg.model.distribution == "tanh_normal" and cfg.env.max_thrust is None:
        raise ConfigError.of(
            "model.distribution",
            "tanh_normal",
            "'normal' unless env.max_thrust is set (e.g. env.max_thrust=1.0)",
        )
    expected = (
        f"a new folder name inside the run folder (no '/' or '..', none of {sorted(RUN_FOLDER_ENTRIES)}), "
        "e.g. tensorboard"
    )
    _check_folder_name("logger.exp_name", cfg.logger.exp_name, expected, RUN_FOLDER_ENTRIES)
    if cfg.sweep_name is not None:  # null: an ad-hoc sweep, its folder named by its overrides
        _check_folder_name("sweep_name", cfg.sweep_name, "a folder name (no '/' or '..'), e.g. lr")
    if training:
        check_memory(cfg)  # last: every value is allowed; does the run fit in this machine?


def check_memory(cfg: Mapping[str, Any], agents: int = 1) -> None:
    """Refuse in one line a config whose memory exceeds what this machine has free.

    The memory is :mod:`drone_torchrl.memory_estimate`'s, with ``agents`` runs trained
    together in one process.
    """
    learner = ALGORITHMS.get(cfg["algo"]["name"]).memory
    memory_estimate.check(memory_estimate.estimate(cfg, agents, learner), cfg["device"])
