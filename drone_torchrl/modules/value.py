"""The critics trained beside the three-net actor: PPO's state value and SAC's action value (Q) MLPs."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchrl.modules import MLP, ValueOperator

from drone_torchrl.envs.dynamics import ACTION_DIM, STATE_DIM
from drone_torchrl.modules.policy import ACTIVATIONS


def _mlp(
    inputs: int, hidden_sizes: Sequence[int], activation: str, device: torch.device | str, dtype: torch.dtype
) -> MLP:
    """A one-output MLP, made in float32 on ``device`` then converted to ``dtype``."""
    net = MLP(
        in_features=inputs,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=ACTIVATIONS[activation],
        device=device,
    )
    return net.to(dtype)


def make_critic(
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    observation_dim: int = STATE_DIM,
) -> ValueOperator:
    """A state-value network: ``"observation"`` in, ``"state_value"`` out, in ``dtype``.

    ``dtype``: the env's (initialised in float32, then converted).
    """
    return ValueOperator(_mlp(observation_dim, hidden_sizes, activation, device, dtype), in_keys=["observation"])


def make_q_value(
    hidden_sizes: Sequence[int],
    activation: str,
    device: torch.device | str,
    dtype: torch.dtype,
    observation_dim: int = STATE_DIM,
) -> ValueOperator:
    """SAC's Q-network: ``"observation"`` and ``"action"`` in, ``"state_action_value"`` out.

    The observation and the action are concatenated by TorchRL's MLP; in ``dtype``.
    """
    net = _mlp(observation_dim + ACTION_DIM, hidden_sizes, activation, device, dtype)
    return ValueOperator(net, in_keys=["observation", "action"], out_keys=["state_action_value"])
