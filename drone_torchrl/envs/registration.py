"""Registers ``Drone2D-v0`` with Gymnasium (done by ``import drone_torchrl``)."""

import gymnasium as gym

GYM_ID = "Drone2D-v0"


def register_envs() -> None:
    """Register ``Drone2D-v0`` with Gymnasium, once per process."""
    if GYM_ID not in gym.registry:
        gym.register(
            id=GYM_ID,
            entry_point="drone_torchrl.envs.gym_env:DroneGymEnv",
            # Truncation is the env's own (max_steps), so Gymnasium's TimeLimit is not added.
            max_episode_steps=None,
        )
