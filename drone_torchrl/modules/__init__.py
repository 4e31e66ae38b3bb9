"""Policies for the drone."""

from drone_torchrl.modules.policy import DISTRIBUTIONS, ThreeNetPolicy, make_actor

__all__ = ["DISTRIBUTIONS", "ThreeNetPolicy", "make_actor"]
