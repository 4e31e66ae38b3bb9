"""The one-line checks of config values: :class:`~.checks.ConfigError` and its checks.

The range check of numbers (:func:`check_number`, the one range checker) is the schema's rules'
(:mod:`drone_torchrl.schema`, which check choices and lists themselves), the env's and the
cross-field checks'.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from numbers import Integral, Real
from pathlib import Path
from typing import Any

# The largest numbers the tensors hold: a float key beyond float32's largest finite value turns into
# inf in the env's and the nets' float32 tensors, a count beyond int64's overflows torch's integers.
# A rule without an upper bound of its own is bounded by these.
FLOAT32_MAX = 3.4028234663852886e38
INT64_MAX = 2**63 - 1
# The most characters of a value an error message shows.
SHOWN_CHARS = 100
LOG2_10 = math.log2(10)  # bits per decimal digit


class ConfigError(ValueError):
    """A config value that is not allowed: the message names the key, the value and what is allowed."""

    @classmethod
    def of(cls, key: str, value: Any, allowed: str) -> ConfigError:
        """The one-line error ``key=value is not allowed; expected <allowed>``."""
        return cls(f"{key}={as_override(value)} is not allowed; expected {allowed}")


def as_override(value: Any) -> str:
    """``value`` as the user would have typed it in an override, shortened if too long for a message."""
    # How the user would have typed it: null and true/false, as Hydra writes them; a value too long to
    # read in a message (a pasted file, an int of thousands of digits) shortened to its start.
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    if isinstance(value, int) and value.bit_length() > SHOWN_CHARS * LOG2_10:  # repr refuses > 4300 digits
        return f"<an integer of {value.bit_length()} bits>"
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else f"{text[:SHOWN_CHARS]}... ({len(text)} characters)"


def first_line(err: BaseException) -> str:
    """The first line of ``err``'s message, or its type's name when it has none."""
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def plain_name(name: Any) -> bool:
    """A single folder name: no separators, not ``.`` or ``..``."""
    return isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name


def is_number(value: Any) -> bool:
    """Whether ``value`` is an int or a float (a bool, though an int to Python, is not)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_number(
    key: str,
    value: Any,
    *,
    low: float | tuple[str, float] | None = None,
    high: float | tuple[str, float] | None = None,
    low_open: bool = False,
    high_open: bool = False,
    integer: bool = False,
    dtype_range: bool = True,
) -> Any:
    """Check that ``value`` of ``key`` is a finite number within the bounds; return it.

    A bound is a number, or ``(label, number)`` to show the label: ``("z_min", 0.0)`` reads
    ``z_min (0.0)``, a label that is not a name (``("1000 m", 1000.0)``) reads as itself.
    With ``integer`` it must be an integer. With ``dtype_range`` (config values) it must also be
    within float32's range (an integer: int64's), the upper bound when there is no other; without it
    (the env's arguments) any finite number is, and the message says "a finite number". The error is
    one line naming the key, the value and the bounds.
    """
    # A bound named by another argument shows its value too; a literal one ("1000 m") is its value.
    (low_label, low), (high_label, high) = (
        (f"{b[0]} ({b[1]!r})" if b[0].isidentifier() else b[0], b[1]) if isinstance(b, tuple) else (f"{b}", b)
        for b in (low, high)
    )
    limit = INT64_MAX if integer else FLOAT32_MAX
    # An int too large for a float (10**400) is compared as an int: math.isfinite would overflow.
    ok = (
        isinstance(value, Real)
        and not isinstance(value, bool)
        and (not integer or isinstance(value, Integral))
        and (isinstance(value, Integral) or math.isfinite(value))
        and (not dtype_range or -limit <= value <= limit)
        and (low is None or value > low or (value == low and not low_open))
        and (high is None or value < high or (value == high and not high_open))
    )
    if ok:
        return value
    parts = [] if low is None else [f"{'>' if low_open else '>='} {low_label}"]
    if high is not None:
        parts.append(f"{'<' if high_open else '<='} {high_label}")
    if not dtype_range:
        raise ConfigError.of(key, value, " ".join(["a finite number", " and ".join(parts)]).rstrip())
    kind = "an integer" if integer else "a number"
    dtype = "int64" if integer else "float32"
    if not parts:
        raise ConfigError.of(key, value, f"{kind} within {dtype}'s range, +-{limit}")
    if high is None:
        parts.append(f"<= {limit} ({dtype}'s largest)")
    raise ConfigError.of(key, value, f"{kind} {' and '.join(parts)}")


def dotted(cfg: Any, key: str) -> Any:
    """The value at dotted ``key`` (``algo.lr``) of nested mappings, or None where a part is absent."""
    for part in key.split("."):
        cfg = cfg.get(part) if isinstance(cfg, Mapping) else None
    return cfg
