"""Every use of another package's private API, in one place, checked against the versions it was written for.

Hydra, OmegaConf, hydra-submitit-launcher and PyTorch keep some of what this project needs behind
underscored names. Each such use is one function here, named for what it gives, with the versions
it was checked on. :func:`check_versions` (run when this module is imported) refuses, in one line,
a version outside those ranges, so an upgrade that moved a private name fails on start with the
package's name rather than deep in a sweep. ``pyproject.toml`` pins the same ranges; the check
catches installs that bypassed them (``pip install --no-deps``, a cluster's module system).

What each one is for:

- :func:`basic_sweeper_class`, :func:`basic_sweeper_conf`: ``hydra/sweeper=population`` sweeps as
  Hydra's basic sweeper (its batches, its schema), which Hydra ships only under ``hydra._internal``.
- :func:`overrides_dirname`: ``hydra.job.override_dirname`` for derived jobs, computed exactly as
  Hydra does (``hydra._internal.config_loader_impl``).
- :func:`hydra_args_parser`: the parser of a Hydra app's flags (``hydra._internal.utils``), so
  ``drone-train`` reports a bad flag in one line before Hydra prints argparse's usage.
- :func:`omegaconf_str_representer`: OmegaConf's YAML quoting of strings, reused on libyaml's faster
  emitter (``omegaconf._utils``).
- :func:`submitit_cluster`, :func:`submitit_params`: the cluster name and parameters of
  hydra-submitit-launcher's launcher (``_EXECUTOR``, ``params``), to build its executor the way it
  does.
- :func:`fused_adam`: torch's fused Adam/AdamW kernels over lists of tensors (``torch._fused_adam_``),
  what ``torch.optim.Adam(fused=True)`` calls, applied per group of agents.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from importlib import metadata
from typing import Any

from packaging.version import Version

# distribution -> (lowest version checked, first version not checked): [low, high).
CHECKED = {
    "hydra-core": ("1.3.2", "1.4"),
    "omegaconf": ("2.3.0", "2.4"),
    "hydra-submitit-launcher": ("1.2.0", "1.3"),
    "torch": ("2.5", "2.14"),
}


def _release(version: str) -> tuple[int, ...]:
    """``"2.13.0+cpu"`` -> ``(2, 13, 0)``: the numeric release part of a version (a pre-release's too)."""
    return Version(version).release


def check_versions(checked: dict[str, tuple[str, str]] = CHECKED) -> None:
    """Raise ``RuntimeError`` (one line) if an installed package is outside the range checked here.

    Packages not installed (an extra) are skipped.
    """
    for name, (low, high) in checked.items():
        try:
            version = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
        if not _release(low) <= _release(version) < _release(high):
            raise RuntimeError(
                f"{name} {version} is not supported: drone_torchrl uses its private API checked on "
                f">={low},<{high}; install a version in that range"
            )


def basic_sweeper_class() -> type:
    """Hydra's ``BasicSweeper``, imported afresh.

    Hydra's plugin scan re-executes its core plugin modules, so the class must be looked up when it is used,
    not kept from an earlier import.
    """
    return importlib.import_module("hydra._internal.core_plugins.basic_sweeper").BasicSweeper


def basic_sweeper_conf() -> type:
    """The dataclass schema of Hydra's basic sweeper (``max_batch_size``, ``params``)."""
    return importlib.import_module("hydra._internal.core_plugins.basic_sweeper").BasicSweeperConf


def overrides_dirname(overrides: Any, exclude_keys: Any, item_sep: str, kv_sep: str) -> str:
    """``hydra.job.override_dirname`` of a job's parsed overrides, as Hydra computes it."""
    from hydra._internal.config_loader_impl import get_overrides_dirname

    return get_overrides_dirname(overrides, exclude_keys, item_sep, kv_sep)


def hydra_args_parser() -> Any:
    """The ``argparse`` parser of a Hydra app's command line (``--cfg``, ``-m``, overrides...)."""
    from hydra._internal.utils import get_args_parser

    return get_args_parser()


def omegaconf_str_representer() -> Callable:
    """OmegaConf's YAML representer for strings (quotes those that would read back as another type)."""
    from omegaconf._utils import get_omega_conf_dumper

    return get_omega_conf_dumper().str_representer


def submitit_cluster(launcher: Any) -> str:
    """The submitit cluster a hydra-submitit launcher submits to (``"slurm"`` or ``"local"``)."""
    return launcher._EXECUTOR


def submitit_params(launcher: Any) -> dict[str, Any]:
    """A hydra-submitit launcher's parameters, as its config gave them."""
    return launcher.params


def fused_adam(decoupled_weight_decay: bool) -> Callable:
    """Torch's fused multi-tensor Adam (or AdamW with ``decoupled_weight_decay``) step on the CPU."""
    import torch

    return torch._fused_adamw_ if decoupled_weight_decay else torch._fused_adam_


check_versions()
