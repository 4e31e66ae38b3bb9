"""Job configs of a large sweep without composing each one from scratch.

Hydra composes every job's config from the YAML files and the command line: about 0.4 s a job
here, twice per job in a multirun (the basic sweeper checks each batch by composing it, then the
launcher composes it again). For a 256-agent grid that is minutes before any training. Jobs of a
grid differ only in a few plain ``key=value`` overrides, so :func:`sweep_configs` composes the first
job fully and derives each other job from it by applying its differing overrides with
``OmegaConf.update``, exactly as Hydra applies a value override, and by setting the two fields
Hydra derives from the overrides (``hydra.overrides.task`` and ``hydra.job.override_dirname``) on
one ``hydra`` node that the derived jobs share, one job at a time (a job needs its node only while
its folder is set up).
Any other kind of override (a config group such as ``experiment=bounded``, ``+key``, ``~key``,
a key the config does not have) makes that job fall back to Hydra's full composition.

At tens of thousands of jobs even a copy per job is too slow: when the jobs differ only in numbers
of the per-agent keys (``seed=0..65535``, ``algo.lr=...``), :func:`agent_columns` gives one config and
each job's values, read from the override's text without a config or a parser call per job.

:func:`checked_batch` is a batch composed one of these two ways and checked: what
``hydra/sweeper=population`` checks before any folder, and what the population launcher trains (it
keeps the sweeper's composition instead of composing the batch again).
"""

from __future__ import annotations

import copy
import functools
import re
from collections.abc import Iterator, Sequence
from typing import NamedTuple

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, OverrideType
from omegaconf import DictConfig, OmegaConf, flag_override, open_dict, read_write

from drone_torchrl.compat import overrides_dirname

_MISSING = object()
# The numbers Hydra's grammar reads as an int or a float, written the plain way (a job with any
# other spelling takes the per-job path).
_INT = re.compile(r"[+-]?(0|[1-9][0-9]*)")
_FLOAT = re.compile(r"[+-]?([0-9]+\.[0-9]*|\.[0-9]+|[0-9]+)([eE][+-]?[0-9]+)?")


def _is_plain_value(override: Override, template: DictConfig, groups: set[str]) -> bool:
    """A ``key=value`` change of a key the config has that is not a config group."""
    key = override.key_or_group
    return (
        override.type == OverrideType.CHANGE
        and override.package is None
        and not override.is_hydra_override()
        and key not in groups
        and OmegaConf.select(template, key, default=_MISSING) is not _MISSING
    )


def sweep_configs(config_loader, master: DictConfig, jobs: Sequence[Sequence[str]]) -> Iterator[DictConfig]:
    """Each job's config in turn, equal to ``config_loader.load_sweep_config(master, overrides)``.

    The jobs derived from the first share one ``hydra`` node, rewritten for each job (copying
    Hydra's part is four fifths of the cost of deriving a job): a config's ``hydra`` node is valid
    until the next config is asked for, and is then taken off it.
    """
    # Hydra's grammar is slow per override, and the jobs of a grid repeat most of theirs.
    parse = functools.cache(OverridesParser.create().parse_override)
    first = list(jobs[0])
    template = config_loader.load_sweep_config(master, first)
    first_parsed = {o.input_line: o for o in map(parse, first)}
    groups = set(template.hydra.runtime.choices)
    shared = _take_hydra(template)
    dirname = shared.job.config.override_dirname
    for overrides in jobs:
        parsed = list(map(parse, overrides))
        changed = [o for o in parsed if o.input_line not in first_parsed]
        same_keys = [o.key_or_group for o in parsed] == [o.key_or_group for o in first_parsed.values()]
        if same_keys and all(_is_plain_value(o, template, groups) for o in changed):
            cfg, hydra = copy.deepcopy(template), shared
            for override in changed:
                OmegaConf.update(cfg, override.key_or_group, override.value(), merge=True)
            with read_write(hydra), open_dict(hydra):
                task = [o for o in parsed if not o.is_hydra_override()]
                hydra.overrides.task = [o.input_line for o in task]
                # Hydra's schema of the node: kv_sep, item_sep, exclude_keys.
                hydra.job.override_dirname = overrides_dirname(overrides=task, **dirname)
        else:
            cfg = config_loader.load_sweep_config(master, list(overrides))
            hydra = _take_hydra(cfg)
        # The node is set without a copy (OmegaConf copies a node it is given, by default).
        with open_dict(cfg), flag_override(cfg, "no_deepcopy_set_nodes", True):
            cfg["hydra"] = hydra
        yield cfg
        if "hydra" in cfg:
            _take_hydra(cfg)


def agent_columns(
    config_loader, master: DictConfig, jobs: Sequence[Sequence[str]], keys: Sequence[str]
) -> tuple[DictConfig, DictConfig, dict[str, list]] | None:
    """The jobs as ``(config, hydra node, columns)`` when they differ from the first job only in
    plain numbers of ``keys``, else None.

    ``config``: the first job's config without its ``hydra`` node (returned apart); ``columns``:
    each of ``keys`` -> every job's value (the config's own where no job overrides it). A job
    qualifies when its overrides are the first job's, in the same order, except ``key=number``
    ones of ``keys`` where the first job has the same key as a plain value override.
    """
    first = list(jobs[0])
    template = config_loader.load_sweep_config(master, first)
    groups = set(template.hydra.runtime.choices)
    hydra = _take_hydra(template)
    varying: dict[int, str] = {}  # position in the overrides -> the per-agent key there
    for position, override in enumerate(OverridesParser.create().parse_overrides(first)):
        if override.key_or_group in keys and _is_plain_value(override, template, groups):
            varying[position] = override.key_or_group
    columns = {key: [] for key in varying.values()}
    for overrides in jobs:
        if len(overrides) != len(first):
            return None
        for position, (line, line_of_first) in enumerate(zip(overrides, first, strict=True)):
            if line == line_of_first and position not in varying:
                continue
            key, _, text = line.partition("=")
            if varying.get(position) != key or (value := _number(text)) is None:
                return None
            columns[key].append(value)
    values = {key: columns.get(key) or [OmegaConf.select(template, key)] * len(jobs) for key in keys}
    return template, hydra, values


def checked(cfg: DictConfig, values: dict[str, list] | None = None) -> None:
    """A job's config (or a population's, ``values`` each agent's) as a single run takes it: old
    keys migrated to today's, then every value checked (:class:`~drone_torchrl.checks.ConfigError`)."""
    from drone_torchrl import migrations
    from drone_torchrl.config import check_agent_values, validate

    migrations.apply_legacy(cfg)
    validate(cfg)
    if values is not None:
        check_agent_values(cfg, values)


class Batch(NamedTuple):  # not a dataclass: Hydra's plug-in scan runs this module outside sys.modules
    """A batch's jobs composed and checked (:func:`checked_batch`): each job's config without its
    ``hydra`` node (one config for them all when ``values``, each per-agent key's column, is given)
    and Hydra's record of the first job's node (what ``.hydra/hydra.yaml`` holds)."""

    configs: list[DictConfig]
    values: dict[str, list] | None
    hydra_record: dict


def checked_batch(config_loader, master: DictConfig, jobs: Sequence[Sequence[str]]) -> Batch:
    """Every job of a batch composed (:func:`agent_columns` when the jobs differ only in per-agent
    numbers, else :func:`sweep_configs`) and checked (:func:`checked`), before any job folder exists.

    Raises :class:`~drone_torchrl.checks.ConfigError` for the first job refused, in one line naming it.
    """
    from drone_torchrl.config import AgentValueError, ConfigError, per_agent_keys

    def refused(err: ConfigError, overrides: Sequence[str]) -> ConfigError:
        return ConfigError(f"{err} (in the sweep's job {' '.join(overrides)}; no job was started)")

    table = agent_columns(config_loader, master, jobs, per_agent_keys())
    if table is not None:  # one config, checked once
        cfg, hydra, values = table
        try:
            checked(cfg, values)
        except AgentValueError as err:
            raise refused(err, jobs[err.agent]) from None
        except ConfigError as err:
            raise refused(err, jobs[0]) from None
        return Batch([cfg] * len(jobs), values, hydra_record(hydra))
    configs: list[DictConfig] = []
    record: dict = {}
    for overrides, cfg in zip(jobs, sweep_configs(config_loader, master, jobs), strict=True):
        hydra = _take_hydra(cfg)
        record = record or hydra_record(hydra)
        try:
            checked(cfg)
        except ConfigError as err:
            raise refused(err, overrides) from None
        configs.append(cfg)
    return Batch(configs, None, record)


def hydra_record(hydra: DictConfig) -> dict:
    """What ``.hydra/hydra.yaml`` holds of a job's ``hydra`` node: the node as written, unresolved."""
    return {"hydra": OmegaConf.to_container(hydra, resolve=False, enum_to_str=True)}


def _number(text: str) -> int | float | None:
    """``text`` as Hydra reads it, if it is a plainly written int or float."""
    if not _FLOAT.fullmatch(text):
        return None
    return int(text) if _INT.fullmatch(text) else float(text)


def _take_hydra(cfg: DictConfig) -> DictConfig:
    """Remove and return ``cfg``'s ``hydra`` node."""
    with open_dict(cfg):
        return cfg.pop("hydra")
