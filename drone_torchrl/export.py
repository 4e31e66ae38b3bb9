"""A trained policy as a standalone file: ``torch.export`` of its deterministic action.

The exported program maps an observation batch ``[B, 6]`` in the env's state layout
(``x, x_dot, z, z_dot, alpha, alpha_dot``) and dtype (float32; float64 for a run with
``env.dtype=float64``, whose weights are float64) to the motor commands ``[B, 2]`` (left, right) as
fractions of the weight, exactly what the env applies: the Normal head's mean, or the TanhNormal
head's deterministic action (``ExplorationType.DETERMINISTIC``: the squashed mean), clamped to
``[0, max_thrust]`` when thrust is bounded. It needs plain torch only::

    policy = torch.export.load("policy.pt2").module()
    thrust = policy(observation)          # observation: float32 [B, 6] (the run's env.dtype)
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from drone_torchrl.config import ConfigError, open_checkpoint, run_config
from drone_torchrl.envs.dynamics import STATE_DIM
from drone_torchrl.modules.factory import build_actor, build_policy


class DeterministicPolicy(nn.Module):
    """Observation ``[B, 6]`` -> the motor commands ``[B, 2]`` the env applies (deterministic)."""

    def __init__(self, net: nn.Module, distribution: str, max_thrust: float | None) -> None:
        super().__init__()
        self.net = net
        self.squash = distribution == "tanh_normal"
        self.max_thrust = max_thrust

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        loc, _ = self.net(observation)
        if (
            self.squash
        ):  # TanhNormal(low=0, high=max_thrust, tanh_loc=False): the mean through tanh onto [0, A]
            loc = (torch.tanh(loc) + 1.0) * (0.5 * self.max_thrust)
        if self.max_thrust is not None:  # what dynamics.clamp_action does in the env
            loc = loc.clamp(0.0, self.max_thrust)
        return loc


def deterministic_policy(checkpoint: str | os.PathLike) -> tuple[DeterministicPolicy, Path]:
    """The deterministic policy of a checkpoint file or run folder (:class:`ConfigError` if unusable)."""
    path, state = open_checkpoint("checkpoint", checkpoint)
    cfg = run_config(state["config"])
    cfg.device = "cpu"
    net = build_policy(cfg)
    build_actor(cfg, net).load_state_dict(state["actor"])  # the actor's keys; the net holds the weights
    return DeterministicPolicy(net, cfg.model.distribution, cfg.env.max_thrust).eval(), path


def export_policy(checkpoint: str | os.PathLike, output: str | os.PathLike) -> Path:
    """Write the deterministic policy of ``checkpoint`` to ``output`` (``torch.export``, ``.pt2``)."""
    output = Path(output)
    if output.is_dir():
        raise ConfigError.of("output", str(output), "a file path such as policy.pt2, not a folder")
    policy, _ = deterministic_policy(checkpoint)
    policy.requires_grad_(False)  # an inference program: no autograd graph in its outputs
    example = torch.zeros(2, STATE_DIM, dtype=next(policy.parameters()).dtype)
    batch = torch.export.Dim("batch")
    with torch.no_grad():
        program = torch.export.export(policy, (example,), dynamic_shapes=({0: batch},))
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(output.name + ".tmp.pt2")
    torch.export.save(program, tmp)
    os.replace(tmp, output)  # never a half-written file under the final name
    return output
