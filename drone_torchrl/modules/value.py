"""The critic PPO trains beside the three-net actor: an MLP from the observation to a state value."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchrl.modules import MLP, ValueOperator

from drone_torchrl.envs.dynamics import STATE_DIM
from drone_torchrl.modules.policy import ACTIVATIONS


def make_critic(
    hidden_sizes: Sequence[int] = (64, 64),
    activation: str = "tanh",
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
    observation_dim: int = STATE_DIM,
) -> ValueOperator:
    """A ``ValueOperator`` reading ``"observation"`` and writing ``"state_value"``, in ``dtype``
    (the env's: initialised in float32, then converted)."""
    net = MLP(
        in_features=observation_dim,
        out_features=1,
        num_cells=list(hidden_sizes),
        activation_class=ACTIVATIONS[activation],
        device=device,
    )
    return ValueOperator(net.to(dtype), in_keys=["observation"])
