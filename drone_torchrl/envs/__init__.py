"""Drone2D environments: the natively batched TorchRL env and its Gymnasium twin."""

from __future__ import annotations

import importlib
from typing import Any

# Loaded on first use (PEP 562): ``import drone_torchrl`` imports this package for its Gymnasium
# registration, which needs no torch, and a command's --help must not pay torch's import.
_LAZY = {
    "DroneEnv": "drone_torchrl.envs.drone_env",
    "DroneGymEnv": "drone_torchrl.envs.gym_env",
    "DroneParams": "drone_torchrl.envs.dynamics",
    "TerminationCause": "drone_torchrl.envs.dynamics",
    "make_env": "drone_torchrl.envs.factory",
}

__all__ = ["DroneEnv", "DroneGymEnv", "DroneParams", "TerminationCause", "make_env"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is not None:
        return getattr(importlib.import_module(module), name)
    # A submodule, as an eager package had it imported (drone_torchrl.envs.disturbances).
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as err:
        if err.name != f"{__name__}.{name}":
            raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
