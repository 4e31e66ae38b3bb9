"""drone_torchrl: teach a 2D drone to fly with reinforcement learning on TorchRL."""

from drone_torchrl.envs.registration import GYM_ID, register_envs

__version__ = "0.1.0"

register_envs()

__all__ = ["GYM_ID", "__version__"]
