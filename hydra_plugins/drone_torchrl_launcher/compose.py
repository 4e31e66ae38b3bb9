"""Job configs of a large sweep without composing each one from scratch.

Hydra composes every job's config from the YAML files and the command line: about 0.4 s a job
here, twice per job in a multirun (the basic sweeper checks each batch by composing it, then the
launcher composes it again). For a 256-agent grid that is minutes before any training. Jobs of a
grid differ only in a few plain ``key=value`` overrides, so :func:`sweep_configs` composes the first
job fully and derives each other job from it by applying its differing overrides with
``OmegaConf.update``, exactly as Hydra applies a value override, and by setting the two fields
Hydra derives from the overrides (``hydra.overrides.task`` and ``hydra.job.override_dirname``).
Any other kind of override (a config group such as ``experiment=bounded``, ``+key``, ``~key``,
a key the config does not have) makes that job fall back to Hydra's full composition.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

from hydra._internal.config_loader_impl import get_overrides_dirname
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, OverrideType
from omegaconf import DictConfig, OmegaConf, open_dict

_MISSING = object()


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


def sweep_configs(
    config_loader, master: DictConfig, jobs: Sequence[Sequence[str]], task_only: bool = False
) -> list[DictConfig]:
    """Each job's config, equal to ``config_loader.load_sweep_config(master, overrides)``.

    ``task_only``: without the ``hydra`` node (what the job's task sees; what a sweeper checks
    before launching); copying Hydra's own part is four fifths of the cost of deriving a job.
    """
    if not jobs:
        return []
    parser = OverridesParser.create()
    first = list(jobs[0])
    template = config_loader.load_sweep_config(master, first)
    first_parsed = {o.input_line: o for o in parser.parse_overrides(first)}
    dirname = template.hydra.job.config.override_dirname
    groups = set(template.hydra.runtime.choices)
    task_template = _without_hydra(template) if task_only else template
    configs = [task_template]
    for overrides in jobs[1:]:
        parsed = parser.parse_overrides(list(overrides))
        changed = [o for o in parsed if o.input_line not in first_parsed]
        same_keys = [o.key_or_group for o in parsed] == [o.key_or_group for o in first_parsed.values()]
        if not (same_keys and all(_is_plain_value(o, task_template, groups) for o in changed)):
            composed = config_loader.load_sweep_config(master, list(overrides))
            configs.append(_without_hydra(composed) if task_only else composed)
            continue
        cfg = copy.deepcopy(task_template)
        for override in changed:
            OmegaConf.update(cfg, override.key_or_group, override.value(), merge=True)
        if task_only:
            configs.append(cfg)
            continue
        with open_dict(cfg.hydra):
            task = [o.input_line for o in parsed if not o.is_hydra_override()]
            cfg.hydra.overrides.task = task
            cfg.hydra.job.override_dirname = get_overrides_dirname(
                overrides=[o for o in parsed if not o.is_hydra_override()],
                kv_sep=dirname.kv_sep,
                item_sep=dirname.item_sep,
                exclude_keys=dirname.exclude_keys,
            )
        configs.append(cfg)
    return configs


def _without_hydra(cfg: DictConfig) -> DictConfig:
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg
