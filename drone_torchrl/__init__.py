"""drone_torchrl: teach a 2D drone to fly with reinforcement learning on TorchRL."""

from typing import Any

from drone_torchrl.envs.registration import GYM_ID, register_envs

__version__ = "0.1.0"

register_envs()

# The Python entry points (docs/python.md), imported on first use: ``import drone_torchrl`` stays light.
_API = ("train", "evaluate", "TrainResult", "EvalResult", "ConfigError")

__all__ = ["GYM_ID", "__version__", *_API]


def __getattr__(name: str) -> Any:
    """``drone_torchrl.train`` and the other entry points of :mod:`drone_torchrl.api`, imported lazily."""
    if name == "ConfigError":
        from drone_torchrl.checks import ConfigError

        return ConfigError
    if name in _API:
        from drone_torchrl import api

        return getattr(api, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
