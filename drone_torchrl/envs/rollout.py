"""Fly a batch of drones on the pure dynamics, without ``EnvBase``: the fast path's rollout.

TorchRL's fixed cost per ``EnvBase.step`` (about 0.15-0.35 ms here) is larger than the whole step
of a small policy on a few hundred drones, so the fast training path and the evaluator call the
physics of :mod:`drone_torchrl.envs.dynamics` directly. The result has the layout of
``EnvBase.rollout(..., break_when_all_done=True)`` on :class:`~drone_torchrl.envs.DroneEnv`, so the
loss, the episode metrics and the plots read both alike.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict

from drone_torchrl.envs.dynamics import TerminationCause

# state [*B, 6], step index -> (action [*B, 2], next state [*B, 6], reward [*B], cause [*B])
StepFn = Callable[[torch.Tensor, int], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


@torch.no_grad()
def fly(step: StepFn, start: torch.Tensor, max_steps: int) -> TensorDict:
    """Fly ``start`` (``[*B, 6]``) until every episode has terminated or ``max_steps`` steps passed.

    One episode per row: rows that terminated early keep being stepped until the last one ends
    (as ``break_when_all_done`` repeats them); :func:`~drone_torchrl.objectives.valid_steps`
    masks those steps. Returns a ``[*B, T]`` tensordict with ``observation``, ``action``,
    ``step_count`` and ``next`` (``observation``, ``reward``, ``terminated``, ``truncated``,
    ``done``, ``termination_cause``).
    """
    state = start
    observations, actions, rewards, causes = [], [], [], []
    alive = torch.ones(start.shape[:-1], dtype=torch.bool, device=start.device)
    for t in range(max_steps):
        observations.append(state)
        action, state, reward, cause = step(state, t)
        actions.append(action)
        rewards.append(reward)
        causes.append(cause)
        alive = alive & (cause == int(TerminationCause.NONE))
        if not bool(alive.any()):
            break
    n = len(rewards)
    cause = torch.stack(causes, -1)
    terminated = cause != int(TerminationCause.NONE)
    truncated = torch.zeros_like(terminated)
    if n == max_steps:
        truncated[..., -1] = ~terminated[..., -1]
    obs = torch.stack(observations, -2)
    next_obs = torch.cat([obs[..., 1:, :], state.unsqueeze(-2)], -2)
    steps = torch.arange(n, device=start.device).expand(*start.shape[:-1], n)
    return TensorDict(
        {
            "observation": obs,
            "action": torch.stack(actions, -2),
            "step_count": steps.unsqueeze(-1),
            "next": {
                "observation": next_obs,
                "reward": torch.stack(rewards, -1).unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
                "truncated": truncated.unsqueeze(-1),
                "done": (terminated | truncated).unsqueeze(-1),
                "termination_cause": cause.unsqueeze(-1),
            },
        },
        batch_size=[*start.shape[:-1], n],
    )
