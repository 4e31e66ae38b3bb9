"""Drone2D environments: the natively batched TorchRL env and its Gymnasium twin."""

from __future__ import annotations

from drone_torchrl.lazy import lazy_getattr

# Loaded on first use (PEP 562): ``import drone_torchrl`` imports this package for its Gymnasium
# registration, which needs no torch, and a command's --help must not pay torch's import.
_LAZY = {
    "DroneEnv": "drone_torchrl.envs.drone_env",
    "DroneGymEnv": "drone_torchrl.envs.gym_env",
    "DroneParams": "drone_torchrl.envs.params",
    "TerminationCause": "drone_torchrl.envs.dynamics",
    "make_env": "drone_torchrl.envs.factory",
}

__all__ = ["DroneEnv", "DroneGymEnv", "DroneParams", "TerminationCause", "make_env"]


__getattr__ = lazy_getattr(__name__, _LAZY)
