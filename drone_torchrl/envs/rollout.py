"""Fly a batch of drones on the pure dynamics, without ``EnvBase``: the fast path's rollout.

TorchRL's fixed cost per ``EnvBase.step`` (about 0.15-0.35 ms here) is larger than the whole step
of a small policy on a few hundred drones, so the fast training path and the evaluator call the
physics of :mod:`drone_torchrl.envs.dynamics` directly. The result has the layout of
``EnvBase.rollout(..., break_when_all_done=True)`` on :class:`~drone_torchrl.envs.DroneEnv`, so the
loss, the episode metrics and the plots read both alike.

Steps come in chunks: a :data:`ChunkFn` flies ``k`` steps per call, and the loop asks the device
whether every episode has ended once per chunk, not once per step. The training engine compiles
its chunk as one graph (``steps_per_call``), which removes the fixed cost of a compiled call
(guards, wrappers: about 40 us) from all but one step in ``k``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict

from drone_torchrl.envs.dynamics import TerminationCause

# state [*B, 6], step index -> (action [*B, 2], next state [*B, 6], reward [*B], cause [*B])
StepFn = Callable[[torch.Tensor, int], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]
# state [*B, 6], first step index t, steps k -> the k steps' (actions [k, *B, 2], states after each
# step [k, *B, 6], rewards [k, *B], causes [k, *B])
ChunkFn = Callable[[torch.Tensor, int, int], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


def chunked(step: StepFn) -> ChunkFn:
    """A :data:`ChunkFn` that calls ``step`` once per step (the same arithmetic, step by step)."""

    def chunk(state: torch.Tensor, t: int, k: int) -> tuple[torch.Tensor, ...]:
        outputs = []
        for i in range(k):
            action, state, reward, cause = step(state, t + i)
            outputs.append((action, state, reward, cause))
        return tuple(torch.stack(column) for column in zip(*outputs, strict=True))

    return chunk


@torch.no_grad()
def fly(chunk: ChunkFn, start: torch.Tensor, max_steps: int, steps_per_call: int = 1) -> TensorDict:
    """Fly ``start`` (``[*B, 6]``) until every episode has terminated or ``max_steps`` steps passed.

    ``chunk`` flies up to ``steps_per_call`` steps per call (:func:`chunked` turns a
    :data:`StepFn` into one); the steps a chunk flies after the last episode ended are dropped, so
    the result does not depend on ``steps_per_call``. One episode per row: rows that terminated
    early keep being stepped until the last one ends (as ``break_when_all_done`` repeats them);
    :func:`~drone_torchrl.objectives.valid_steps` masks those steps. Returns a ``[*B, T]``
    tensordict with ``observation``, ``action``, ``step_count`` and ``next`` (``observation``,
    ``reward``, ``terminated``, ``truncated``, ``done``, ``termination_cause``).
    """
    state = start
    pieces: list[tuple[torch.Tensor, ...]] = []
    ended = torch.zeros(start.shape[:-1], dtype=torch.bool, device=start.device)
    t, all_ended = 0, [False]
    while t < max_steps and True not in all_ended:
        k = min(steps_per_call, max_steps - t)
        actions, states, rewards, causes = chunk(state, t, k)
        observations = torch.cat([state.unsqueeze(0), states[:-1]])
        # An episode that terminated stays ended even if its repeated steps come back in bounds.
        ended_after = (causes != int(TerminationCause.NONE)).cummax(0).values | ended
        all_ended = ended_after.flatten(1).all(1).tolist()  # the one host sync per chunk
        if True in all_ended:
            k = all_ended.index(True) + 1
        pieces.append(tuple(x[:k] for x in (observations, actions, rewards, causes)))
        state, ended, t = states[k - 1], ended_after[k - 1], t + k
    obs, action, reward, cause = (torch.cat(column) for column in zip(*pieces, strict=True))
    obs, action, reward, cause = (
        obs.movedim(0, -2),
        action.movedim(0, -2),
        reward.movedim(0, -1),
        cause.movedim(0, -1),
    )
    n = cause.shape[-1]
    terminated = cause != int(TerminationCause.NONE)
    truncated = torch.zeros_like(terminated)
    if n == max_steps:
        truncated[..., -1] = ~terminated[..., -1]
    next_obs = torch.cat([obs[..., 1:, :], state.unsqueeze(-2)], -2)
    steps = torch.arange(n, device=start.device).expand(*start.shape[:-1], n)
    return TensorDict(
        {
            "observation": obs,
            "action": action,
            "step_count": steps.unsqueeze(-1),
            "next": {
                "observation": next_obs,
                "reward": reward.unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
                "truncated": truncated.unsqueeze(-1),
                "done": (terminated | truncated).unsqueeze(-1),
                "termination_cause": cause.unsqueeze(-1),
            },
        },
        batch_size=[*start.shape[:-1], n],
    )
