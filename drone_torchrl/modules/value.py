"""The critics trained beside the three-net actor: PPO's state value and SAC's action value (Q) MLPs."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchrl.modules import MLP, ValueOperator

from drone_torchrl.envs.dynamics import ACTION_DIM, STATE_DIM
from drone_torchrl.modules.policy import ACTIVATIONS


def make_critic(
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    observation_dim: int = STATE_DIM,
) -> ValueOperator:
    """A state-value network: ``"observation"`` in, ``"state_value"`` out, in ``dtype``.

    A ``ValueOperator`` reading ``"observation"`` and writing ``"state_value"``, in ``dtype``
    (the env's: initialised in float32, then converted).
    """
    net = MLP(
        in_features=observation_dim,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=ACTIVATIONS[activation],
        device=device,
    )
    return ValueOperator(net.to(dtype), in_keys=["observation"])


def make_q_value(
    hidden_sizes: Sequence[int],
    activation: str,
    device: torch.device | str,
    dtype: torch.dtype,
    observation_dim: int = STATE_DIM,
) -> ValueOperator:
    """SAC's Q-network: ``"observation"`` and ``"action"`` in, ``"state_action_value"`` out.

    A ``ValueOperator`` over an MLP of the observation and the action (concatenated by TorchRL's
    MLP), in ``dtype``.
    """
    net = MLP(
        in_features=observation_dim + ACTION_DIM,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=ACTIVATIONS[activation],
        device=device,
    )
    return ValueOperator(net.to(dtype), in_keys=["observation", "action"], out_keys=["state_action_value"])
