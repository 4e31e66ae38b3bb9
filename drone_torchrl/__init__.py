"""drone_torchrl: teach a 2D drone to fly with reinforcement learning on TorchRL."""

from drone_torchrl.envs.registration import GYM_ID, register_envs
from drone_torchrl.lazy import lazy_getattr

__version__ = "0.1.0"

register_envs()

# The Python entry points (docs/python.md), imported on first use: ``import drone_torchrl`` stays light.
_API = {name: "drone_torchrl.api" for name in ("train", "evaluate", "TrainResult", "EvalResult")}
_API["ConfigError"] = "drone_torchrl.checks"

__all__ = ["GYM_ID", "__version__", *_API]

__getattr__ = lazy_getattr(__name__, _API)


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
