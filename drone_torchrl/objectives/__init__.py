"""Losses."""

from drone_torchrl.objectives.reinforce import ReinforceLoss, discounted_returns, valid_steps

__all__ = ["ReinforceLoss", "discounted_returns", "valid_steps"]
