"""Packages whose names load on first use (PEP 562), so ``import drone_torchrl`` and ``--help`` need no torch."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_getattr(package: str, names: Mapping[str, str]) -> Callable[[str], Any]:
    """A package's module-level ``__getattr__``: ``names`` (name -> module) and its submodules, imported when first asked for.

    A submodule is found as an eagerly imported package would have it (``drone_torchrl.envs.disturbances``).
    """

    def __getattr__(name: str) -> Any:
        module = names.get(name)
        if module is not None:
            return getattr(importlib.import_module(module), name)
        try:
            return importlib.import_module(f"{package}.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"{package}.{name}":
                raise
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
