"""Drone2D environments: the natively batched TorchRL env and its Gymnasium twin."""

from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.envs.dynamics import DroneParams, TerminationCause
from drone_torchrl.envs.factory import make_env
from drone_torchrl.envs.gym_env import DroneGymEnv

__all__ = ["DroneEnv", "DroneGymEnv", "DroneParams", "TerminationCause", "make_env"]
