"""Plug-in registries: algorithms and logger backends are found by name the same way.

The algorithms are :mod:`drone_torchrl.algorithms`, the logger backends :mod:`drone_torchrl.loggers`.

A plug-in module calls :meth:`Registry.register` when imported. A registry imports the modules of
its own package, and those another package names in its entry-point group, when a name is first
looked up, not when it is created: plug-ins use the config helpers, which look them up.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from importlib import metadata
from typing import Generic, TypeVar

from drone_torchrl.checks import ConfigError

#: The type of the plug-ins a :class:`Registry` holds.
T = TypeVar("T")
# What a plug-in may be called.
NAME = re.compile(r"[a-z][a-z0-9_]*")


class Registry(Generic[T]):
    """Named plug-ins of one kind.

    Args:
        key: the config key that names one (``algo.name``), for error messages.
        package: the package whose modules are the built-in plug-ins.
        entry_points: the entry-point group through which other packages add theirs.
    """

    def __init__(self, key: str, package: str, entry_points: str) -> None:
        self.key, self.package, self.entry_points = key, package, entry_points
        self._items: dict[str, T] = {}
        self._discovered = False

    def register(self, name: str, item: T) -> T:
        """Add ``item`` as ``name``; a duplicate or a malformed name is refused.

        A duplicate is another item of the same name; a well-formed name is lowercase letters,
        digits and ``_``, starting with a letter (it is typed on command lines and names folders and
        config keys).
        """
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ValueError(f"{self.key}={name!r} cannot be registered: a name is {NAME.pattern}")
        known = self._items.get(name)
        if known is not None and known != item:
            raise ValueError(f"two plug-ins are registered as {self.key}={name}: {known!r} and {item!r}")
        self._items[name] = item
        return item

    def _discover(self) -> None:
        if self._discovered:
            return
        self._discovered = True
        package = importlib.import_module(self.package)
        for module in pkgutil.iter_modules(package.__path__):
            importlib.import_module(f"{self.package}.{module.name}")
        for entry in metadata.entry_points(group=self.entry_points):
            importlib.import_module(entry.value)

    def names(self) -> tuple[str, ...]:
        """The registered names, sorted."""
        self._discover()
        return tuple(sorted(self._items))

    def get(self, name: object) -> T:
        """The plug-in called ``name``; else a one-line :class:`~.checks.ConfigError` naming the choices."""
        self._discover()
        if not isinstance(name, str) or name not in self._items:
            raise ConfigError.of(
                self.key,
                name,
                f"one of {list(self.names())} (registered in {self.package} or '{self.entry_points}')",
            )
        return self._items[name]
