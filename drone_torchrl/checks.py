"""The one-line checks of config values: :class:`ConfigError` and the number, choice and list checks
the schema's rules (:mod:`drone_torchrl.schema`) and the cross-field checks use."""

from __future__ import annotations

import math
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


def check_number(
    key: str,
    value: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    integer: bool = False,
) -> None:
    """``value`` of ``key`` is a finite number (an integer with ``integer``) within the bounds."""
    numeric = isinstance(value, int | float) and not isinstance(value, bool)
    if (
        numeric
        and (not integer or isinstance(value, int))
        and math.isfinite(value)
        and (low is None or value > low or (value == low and not low_open))
        and (high is None or value <= high)
    ):
        return
    kind = "an integer" if integer else "a number"
    bounds = []
    if low is not None:
        bounds.append(f"{'>' if low_open else '>='} {low}")
    if high is not None:
        bounds.append(f"<= {high}")
    raise ConfigError.of(key, value, f"{kind} {' and '.join(bounds)}".strip())


def check_choice(key: str, value: Any, choices: tuple, expected: str | None = None) -> None:
    """``value`` of ``key`` is one of ``choices``."""
    if value not in choices:
        raise ConfigError.of(key, value, expected or f"one of {list(choices)}")


def check_sizes(key: str, value: Any) -> None:
    """``value`` of ``key`` is a non-empty list of layer sizes."""
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in value)
    ):
        raise ConfigError.of(key, value, "a non-empty list of integers >= 1, e.g. [32,32]")
