"""The one-line checks of config values: :class:`ConfigError` and the number, choice and list checks
every part of the config (the shared keys, each algorithm's, each logger's) uses."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A config value that is not allowed: the message names the key, the value and what is allowed."""

    @classmethod
    def of(cls, key: str, value: Any, allowed: str) -> ConfigError:
        return cls(f"{key}={as_override(value)} is not allowed; expected {allowed}")


def as_override(value: Any) -> str:
    # How the user would have typed it: null and true/false, as Hydra writes them.
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    return repr(value)


def plain_name(name: Any) -> bool:
    """A single folder name: no separators, not ``.`` or ``..``."""
    return isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name


def number(
    cfg: Mapping[str, Any],
    key: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
) -> None:
    """``key`` (dotted) is a finite number (an integer with ``integer``) within the bounds."""
    value = cfg
    for part in key.split("."):
        value = value[part]
    kind = "an integer" if integer else "a number"
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low}")
    if high is not None:
        bounds.append(f"<= {high}")
    allowed = f"{kind} {' and '.join(bounds)}".strip()
    numeric = isinstance(value, int | float) and not isinstance(value, bool)
    if not numeric or (integer and not isinstance(value, int)) or not math.isfinite(value):
        raise ConfigError.of(key, value, allowed)
    if low is not None and (value < low or (low_open and value == low)):
        raise ConfigError.of(key, value, allowed)
    if high is not None and value > high:
        raise ConfigError.of(key, value, allowed)


def choice(cfg: Mapping[str, Any], key: str, choices: tuple) -> None:
    """``section.name`` is one of ``choices``."""
    section, name = key.split(".")
    if cfg[section][name] not in choices:
        raise ConfigError.of(key, cfg[section][name], f"one of {list(choices)}")


def sizes(cfg: Mapping[str, Any], key: str) -> None:
    """``key`` (dotted) is a non-empty list of layer sizes."""
    value = cfg
    for part in key.split("."):
        value = value[part]
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in value)
    ):
        raise ConfigError.of(key, value, "a non-empty list of integers >= 1, e.g. [32,32]")
