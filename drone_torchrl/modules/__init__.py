"""Policies for the drone: the paper's three nets, as one actor or stacked for many agents."""

from drone_torchrl.modules.policy import DISTRIBUTIONS, ThreeNetPolicy, actor_from_net, make_actor
from drone_torchrl.modules.stacked import ActionSampler, StackedThreeNet

__all__ = [
    "DISTRIBUTIONS",
    "ActionSampler",
    "StackedThreeNet",
    "ThreeNetPolicy",
    "actor_from_net",
    "make_actor",
]
