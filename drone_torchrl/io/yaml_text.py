"""Configs as YAML text: what ``OmegaConf.to_yaml`` writes, on libyaml's emitter where PyYAML has it.

A population writes each agent's config twice when it starts (``.hydra/config.yaml`` and the run's
``config.yaml``) and Hydra's node once; libyaml's emitter writes a file several times faster than
OmegaConf's pure-Python one. The representers are OmegaConf's (strings that would read back as
a number or a boolean are quoted), so the text is the same for configs of ASCII and most other
text; libyaml escapes a few characters Python's emitter writes as they are (those beyond the Basic
Multilingual Plane, such as emoji, and U+0085), which read back the same.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from omegaconf import Container, OmegaConf

from drone_torchrl.compat import omegaconf_str_representer
from drone_torchrl.io.storage import write_atomically


class _Dumper(getattr(yaml, "CDumper", yaml.Dumper)):  # type: ignore[misc]
    pass


_Dumper.add_representer(str, omegaconf_str_representer())


def to_yaml(cfg: Container | dict | list) -> str:
    """``OmegaConf.to_yaml(cfg)`` (interpolations kept); a plain dict or list is dumped as it is."""
    container: Any = (
        OmegaConf.to_container(cfg, resolve=False, enum_to_str=True) if isinstance(cfg, Container) else cfg
    )
    return yaml.dump(container, default_flow_style=False, allow_unicode=True, sort_keys=False, Dumper=_Dumper)


def save_yaml(cfg: Container | dict | list, path: str | Path) -> None:
    """``OmegaConf.save(cfg, path)``, faster (see :func:`to_yaml`), replacing the file atomically."""
    write_atomically(path, to_yaml(cfg).encode("utf-8"))
