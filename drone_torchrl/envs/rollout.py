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
from typing import NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.envs.drone_env import DroneEnv
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


class Episodes(NamedTuple):
    """One episode per row, as plain tensors: what the fast engine trains on and the metrics read.

    ``states [*B, T + 1, 6]`` (before each step, then after the row's last step),
    ``action [*B, T, 2]``, ``reward [*B, T]``, ``cause [*B, T]`` (int64 :class:`TerminationCause`
    codes) and ``length [*B]`` (int64 steps of each row's episode). Entries after a row's end are
    zeros. ``observation [*B, T, D]`` is what the policy saw before each step where that is not the
    state (disturbed drones: noisy positions, past commands), else ``None``. :meth:`as_rollout`
    gives the layout of TorchRL's ``EnvBase.rollout``.
    """

    states: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    cause: torch.Tensor
    length: torch.Tensor
    observation: torch.Tensor | None = None

    def inputs(self) -> torch.Tensor:
        """What the policy saw before each step, ``[*B, T, D]``."""
        return self.states[..., :-1, :] if self.observation is None else self.observation

    @property
    def steps(self) -> int:
        return self.reward.shape[-1]

    def valid(self) -> torch.Tensor:
        """``[*B, T]`` bool: the steps of each row's episode."""
        return torch.arange(self.steps, device=self.length.device) < self.length.unsqueeze(-1)

    def last(self) -> torch.Tensor:
        """``[*B, T]`` bool: each row's last step (none for an empty row)."""
        return torch.arange(self.steps, device=self.length.device) == (self.length - 1).unsqueeze(-1)

    @classmethod
    def from_steps(
        cls,
        states: torch.Tensor,
        action: torch.Tensor,
        reward: torch.Tensor,
        cause: torch.Tensor,
        length: torch.Tensor,
    ) -> Episodes:
        """Rows of ``length`` steps out of longer buffers (``states[..., length, :]`` is the state after a
        row's last step): the entries after each row's end are zeroed."""
        steps = torch.arange(reward.shape[-1] + 1, device=length.device)
        keep = steps <= length.unsqueeze(-1)  # states: up to the one after the last step
        valid = keep[..., :-1] & keep[..., 1:]
        return cls(
            torch.where(keep.unsqueeze(-1), states, 0.0),
            torch.where(valid.unsqueeze(-1), action, 0.0),
            torch.where(valid, reward, 0.0),
            torch.where(valid, cause, 0),
            length,
        )

    @classmethod
    def from_rollout(cls, rollout: TensorDictBase) -> Episodes:
        """The first episode of each row of a ``[*B, T]`` rollout (``EnvBase.rollout``'s layout; a row may
        go on after its first ``done``, repeating or starting a new episode: that part is dropped)."""
        done = rollout.get(("next", "done")).squeeze(-1)
        length = ((done.cumsum(-1) - done.to(torch.int64)) == 0).sum(-1)  # up to the first done
        # A disturbed env's observation is a measurement; its "state" entry is the true state.
        key = "state" if "state" in rollout else "observation"
        next_obs = rollout.get(("next", key))
        states = torch.cat([rollout.get(key), next_obs[..., -1:, :]], -2)
        # The state after each row's last step (the rows that end early may repeat after it).
        at = length.reshape(*length.shape, 1, 1).expand(*length.shape, 1, states.shape[-1])
        states = states.scatter(-2, at, next_obs.gather(-2, (at - 1).clamp_min(0)))
        reward = rollout.get(("next", "reward")).squeeze(-1)
        cause = rollout.get(("next", "termination_cause")).squeeze(-1)
        episodes = cls.from_steps(states, rollout.get("action"), reward, cause, length)
        if key == "state":
            seen = rollout.get("observation")
            episodes = episodes._replace(observation=torch.where(episodes.valid().unsqueeze(-1), seen, 0.0))
        return episodes

    def as_rollout(self, max_steps: int) -> TensorDict:
        """The ``[*B, T]`` tensordict of ``EnvBase.rollout(..., break_when_all_done=True)``, cut after the
        longest episode: ``observation``, ``action``, ``step_count`` and ``next`` (``observation``,
        ``reward``, ``terminated``, ``truncated``, ``done``, ``termination_cause``). A row that did not
        terminate by step ``max_steps`` is truncated there."""
        n = max(int(self.length.max()), 1) if self.length.numel() else 1
        cause = self.cause[..., :n]
        terminated = cause != int(TerminationCause.NONE)
        truncated = self.last()[..., :n] & ~terminated & (self.length == max_steps).unsqueeze(-1)
        batch = [*self.length.shape, n]
        steps = torch.arange(n, device=cause.device).expand(*batch)
        column = lambda x: x.unsqueeze(-1)  # noqa: E731
        following = TensorDict(
            {
                "observation": self.states[..., 1 : n + 1, :],
                "reward": column(self.reward[..., :n]),
                "terminated": column(terminated),
                "truncated": column(truncated),
                "done": column(terminated | truncated),
                "termination_cause": column(cause),
            },
            batch_size=batch,
        )
        return TensorDict(
            {
                "observation": self.states[..., :n, :],
                "action": self.action[..., :n, :],
                "step_count": column(steps),
                "next": following,
            },
            batch_size=batch,
        )


# start states [*B, 6] -> whole episodes, one per row, with the deterministic action.
RolloutFn = Callable[[torch.Tensor], Episodes]


def fly(chunk: ChunkFn, start: torch.Tensor, max_steps: int, steps_per_call: int = 1) -> TensorDict:
    """:func:`fly_episodes` as :meth:`Episodes.as_rollout`'s ``[*B, T]`` tensordict (``T``: the step
    the last episode ended at)."""
    return fly_episodes(chunk, start, max_steps, steps_per_call).as_rollout(max_steps)


@torch.no_grad()
def fly_episodes(chunk: ChunkFn, start: torch.Tensor, max_steps: int, steps_per_call: int = 1) -> Episodes:
    """Fly ``start`` (``[*B, 6]``) until every episode has terminated or ``max_steps`` steps passed.

    ``chunk`` flies up to ``steps_per_call`` steps per call (:func:`chunked` turns a
    :data:`StepFn` into one); the steps a chunk flies after the last episode ended are dropped, so
    the result does not depend on ``steps_per_call``. One episode per row: rows that terminated
    early keep being stepped until the last one ends, and those steps are then dropped (zeros,
    after the row's end).
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
    states = torch.cat([obs, state.unsqueeze(0)]).movedim(0, -2)
    cause = cause.movedim(0, -1)
    terminated = cause != int(TerminationCause.NONE)
    # Each row's episode ends at its first termination (the rows stepped on after it are dropped).
    length = torch.where(terminated.any(-1), terminated.int().argmax(-1) + 1, cause.shape[-1])
    return Episodes.from_steps(states, action.movedim(0, -2), reward.movedim(0, -1), cause, length)


@torch.no_grad()
def fly_reference(
    policy: TensorDictModuleBase,
    start: torch.Tensor,
    keys: torch.Tensor | None = None,
    device: str | torch.device = "cpu",
    **env_kwargs,
) -> Episodes:
    """The deterministic episodes of a TensorDict policy (an actor, the PD or PID controller, a
    replayed plan) from ``start`` (``[*B, 6]``; under disturbances with episode ``keys`` ``[*B]``),
    flown by the reference: a ``DroneEnv(batch_size=B, **env_kwargs)`` and TorchRL's rollout, one
    episode per row."""
    env = DroneEnv(batch_size=list(start.shape[:-1]), device=device, **env_kwargs)
    if callable(reset := getattr(policy, "reset", None)):
        reset()  # a stateful controller (the PID's integrals) starts new episodes
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(
            env.max_steps,
            policy,
            auto_reset=False,
            tensordict=env.reset_to(start, keys),
            break_when_any_done=False,
            break_when_all_done=True,
        )
    env.close()
    return Episodes.from_rollout(rollout)
