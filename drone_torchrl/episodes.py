"""Per-episode metrics of rollouts: what the run record logs and the evaluator summarises."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from drone_torchrl.envs.dynamics import ACTION_DIM, REWARD_IN_ZONE, TerminationCause
from drone_torchrl.envs.rollout import Episodes


def _in_zone(reward: torch.Tensor) -> torch.Tensor:
    """The steps ``[*B, T]`` that ended inside the target zone without terminating.

    Those are the steps the env rewarded with :data:`~drone_torchrl.envs.dynamics.REWARD_IN_ZONE`
    (it alone knows its zone, bounds and dtype; the other rewards, 1 and 0, differ from it).
    """
    return reward == REWARD_IN_ZONE


#: The paper's smoothing window, in episodes, of the running means a run logs and ends with (its final metrics).
RUNNING_MEAN_WINDOW = 100

#: What a run record books of each finished episode (one episodes.csv column each).
EPISODE_KEYS = ("return", "length", "time_in_zone", "negative_thrust_fraction", "termination_cause")


def episode_stats(rollout: TensorDictBase | Episodes) -> dict[str, torch.Tensor]:
    """Metrics of each row of a ``[*B, T]`` rollout that holds one episode per row (shape ``[*B]`` each).

    ``rollout`` is a tensordict in ``EnvBase.rollout``'s layout (steps after a row's first ``done``
    are ignored) or :class:`~drone_torchrl.envs.rollout.Episodes`.

    ``return``, ``length``; ``time_in_zone``: fraction of the episode's steps that ended inside the
    target zone; ``negative_thrust_fraction``: fraction of motor commands below zero (the paper's
    exploit); ``termination_cause``: the code on the episode's last step (0 when truncated);
    ``first_zone_step``: 1-based step at which the drone first ended a step inside the zone
    (0 if it never did); ``thrust_mean`` / ``thrust_max``: mean and largest motor command of the
    episode, as a fraction of the weight (0.5 per motor hovers).
    """
    episodes = rollout if isinstance(rollout, Episodes) else Episodes.from_rollout(rollout)
    valid, length, action = episodes.valid(), episodes.length, episodes.action
    terminated = episodes.cause != int(TerminationCause.NONE)
    zone = _in_zone(episodes.reward) & valid & ~terminated
    negative = (action < 0) & valid.unsqueeze(-1)
    last = (length - 1).clamp_min(0).unsqueeze(-1)
    steps = length.clamp_min(1).to(episodes.reward.dtype)
    reached = zone.any(-1)
    return {
        "return": episodes.reward.sum(-1),  # zero after each row's end
        "length": length,
        "time_in_zone": zone.sum(-1) / steps,
        "negative_thrust_fraction": negative.sum((-1, -2)) / (steps * negative.shape[-1]),
        "termination_cause": episodes.cause.gather(-1, last).squeeze(-1),
        "first_zone_step": torch.where(reached, zone.to(torch.int64).argmax(-1) + 1, 0),
        "thrust_mean": action.sum((-1, -2)) / (steps * action.shape[-1]),
        "thrust_max": torch.where(valid.unsqueeze(-1), action, -math.inf).amax((-1, -2)),
    }


def counted_metrics(length: torch.Tensor, counts: torch.Tensor) -> dict[str, torch.Tensor]:
    """:data:`EPISODE_KEYS` of each episode from the counts the C++ rollout (and EpisodeTracker) keeps.

    The counts are ``[*B, 4]`` (:data:`drone_torchrl.kernels.ops.STAT_NAMES`), read with the
    lengths; the numbers are the same as :func:`episode_stats`'s.
    """
    steps = length.clamp_min(1).to(counts.dtype)
    return {
        "return": counts[..., 0],
        "length": length,
        "time_in_zone": counts[..., 1] / steps,
        "negative_thrust_fraction": counts[..., 2] / (steps * ACTION_DIM),
        "termination_cause": counts[..., 3].to(torch.int64),
    }


def cause_counts(causes: torch.Tensor) -> dict[str, int]:
    """How many episodes ended with each :class:`~.dynamics.TerminationCause` (``NONE`` = truncated)."""
    return {cause.name: int((causes == cause).sum()) for cause in TerminationCause}


class EpisodeTracker:
    """Per-episode metrics of a stream of ``[N, T]`` collector batches (auto-reset envs).

    The episodes start and end anywhere in a batch and run across batches (auto-reset envs, as
    TorchRL's collectors give them).

    The same metrics as :func:`episode_stats`, for each episode that ends in a batch, in the order
    they end (by step, then by env index). Episodes still running carry over to the next batch.

    Args:
        num_envs: the batches' ``N``, the envs stepped together.
        device: where the running sums live (the batches').
    """

    def __init__(self, num_envs: int, device: torch.device | str = "cpu") -> None:
        # Each env's running episode: its return, length, steps in the zone and negative commands.
        self._sums = torch.zeros(4, num_envs, device=device)

    def state(self) -> list[torch.Tensor]:
        """The running episodes' sums so far (return, length, steps in the zone, negative commands)."""
        return [acc.clone() for acc in self._sums]

    def load_state(self, state: list[torch.Tensor]) -> None:
        """Carry on the running episodes of :meth:`state` (a resumed run's)."""
        self._sums = torch.stack(state)

    def update(self, batch: TensorDictBase) -> dict[str, list]:
        """Track one ``[N, T]`` batch; returns the metrics of the episodes that ended in it."""
        reward = batch.get(("next", "reward")).squeeze(-1)
        done = batch.get(("next", "done")).squeeze(-1)
        terminated = batch.get(("next", "terminated")).squeeze(-1)
        zone = _in_zone(reward) & ~terminated
        negative = (batch.get("action") < 0).sum(-1)
        cause = batch.get(("next", "termination_cause")).squeeze(-1)
        steps = torch.stack(
            [reward, torch.ones_like(reward), zone.to(reward.dtype), negative.to(reward.dtype)]
        )
        ended: dict[str, list] = {k: [] for k in EPISODE_KEYS}
        for t in range(reward.shape[-1]):
            self._sums += steps[..., t]
            if not done[:, t].any():
                continue
            idx = done[:, t].nonzero().squeeze(-1)
            total, length, in_zone, negatives = self._sums[:, idx]
            counts = torch.stack([total, in_zone, negatives, cause[idx, t].to(total.dtype)], -1)
            for key, value in counted_metrics(length.to(torch.int64), counts).items():
                ended[key] += value.tolist()
            self._sums[:, idx] = 0
        return ended
