"""Per-episode metrics of rollouts: what the run record logs and the evaluator summarises."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from drone_torchrl.envs.dynamics import TerminationCause, in_target_zone
from drone_torchrl.objectives.reinforce import valid_steps


def episode_stats(rollout: TensorDictBase) -> dict[str, torch.Tensor]:
    """Metrics of each row of a ``[*B, T]`` rollout that holds one episode per row (shape ``[*B]`` each).

    ``return``, ``length``; ``time_in_zone``: fraction of the episode's steps that ended inside the
    target zone; ``negative_thrust_fraction``: fraction of motor commands below zero (the paper's
    exploit); ``termination_cause``: the code on the episode's last step (0 when truncated);
    ``first_zone_step``: 1-based step at which the drone first ended a step inside the zone
    (0 if it never did).
    """
    done = rollout.get(("next", "done"))
    valid = valid_steps(done).squeeze(-1)
    length = valid.sum(-1)
    reward = rollout.get(("next", "reward")).squeeze(-1)
    terminated = rollout.get(("next", "terminated")).squeeze(-1)
    zone = in_target_zone(rollout.get(("next", "observation"))) & valid & ~terminated
    negative = (rollout.get("action") < 0) & valid.unsqueeze(-1)
    last = (length - 1).clamp_min(0).unsqueeze(-1)
    cause = rollout.get(("next", "termination_cause")).squeeze(-1).gather(-1, last).squeeze(-1)
    steps = length.clamp_min(1).to(reward.dtype)
    reached = zone.any(-1)
    return {
        "return": torch.where(valid, reward, 0.0).sum(-1),
        "length": length,
        "time_in_zone": zone.sum(-1) / steps,
        "negative_thrust_fraction": negative.sum((-1, -2)) / (steps * negative.shape[-1]),
        "termination_cause": cause,
        "first_zone_step": torch.where(reached, zone.to(torch.int64).argmax(-1) + 1, 0),
    }


def cause_counts(causes: torch.Tensor) -> dict[str, int]:
    """How many episodes ended with each :class:`TerminationCause` (``NONE`` = truncated)."""
    return {cause.name: int((causes == cause).sum()) for cause in TerminationCause}
