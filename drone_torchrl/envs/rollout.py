"""Episodes as plain tensors, one per row: the engines', evaluator's and plots' common layout.

:class:`Episodes` converts from and to the layout of TorchRL's ``EnvBase.rollout(...,
break_when_all_done=True)`` on :class:`~drone_torchrl.envs.drone_env.DroneEnv`, so the loss, the episode
metrics and the plots read both engines' episodes alike. :func:`fly_reference` flies a TensorDict
policy through the reference (a ``DroneEnv`` and TorchRL's rollout) into this layout.
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


class Episodes(NamedTuple):
    """One episode per row, as plain tensors: what the fast engine trains on and the metrics read.

    ``states [*B, T + 1, 6]`` (before each step, then after the row's last step),
    ``action [*B, T, 2]``, ``reward [*B, T]``, ``cause [*B, T]`` (int64 :class:`~.dynamics.TerminationCause`
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
        """The buffers' step dimension ``T`` (the longest episode they can hold)."""
        return self.reward.shape[-1]

    def valid(self) -> torch.Tensor:
        """``[*B, T]`` bool: the steps of each row's episode."""
        return torch.arange(self.steps, device=self.length.device) < self.length.unsqueeze(-1)

    def last(self) -> torch.Tensor:
        """``[*B, T]`` bool: each row's last step (none for an empty row)."""
        return torch.arange(self.steps, device=self.length.device) == (self.length - 1).unsqueeze(-1)

    @classmethod
    def from_rollout(cls, rollout: TensorDictBase) -> Episodes:
        """The first episode of each row of a ``[*B, T]`` TorchRL rollout.

        The rollout is in ``EnvBase.rollout``'s layout; a row may go on after its first ``done``,
        repeating or starting a new episode: that part is dropped.
        """
        done = rollout.get(("next", "done")).squeeze(-1)
        length = ((done.cumsum(-1) - done.to(torch.int64)) == 0).sum(-1)  # up to the first done
        # A disturbed env's observation is a measurement; its "state" entry is the true state.
        key = "state" if "state" in rollout else "observation"
        next_obs = rollout.get(("next", key))
        states = torch.cat([rollout.get(key), next_obs[..., -1:, :]], -2)
        # The state after each row's last step (the rows that end early may repeat after it).
        at = length.reshape(*length.shape, 1, 1).expand(*length.shape, 1, states.shape[-1])
        states = states.scatter(-2, at, next_obs.gather(-2, (at - 1).clamp_min(0)))
        # Zeros after each row's end: its states up to the one after its last step, and those steps.
        keep = torch.arange(states.shape[-2], device=length.device) <= length.unsqueeze(-1)
        valid = keep[..., :-1] & keep[..., 1:]
        episodes = cls(
            torch.where(keep.unsqueeze(-1), states, 0.0),
            torch.where(valid.unsqueeze(-1), rollout.get("action"), 0.0),
            torch.where(valid, rollout.get(("next", "reward")).squeeze(-1), 0.0),
            torch.where(valid, rollout.get(("next", "termination_cause")).squeeze(-1), 0),
            length,
        )
        if key == "state":
            seen = rollout.get("observation")
            episodes = episodes._replace(observation=torch.where(valid.unsqueeze(-1), seen, 0.0))
        return episodes

    def as_rollout(self, max_steps: int) -> TensorDict:
        """These episodes as the ``[*B, T]`` tensordict ``EnvBase.rollout`` would return.

        That of ``EnvBase.rollout(..., break_when_all_done=True)``, cut after the longest episode:
        ``observation``, ``action``, ``step_count`` and ``next`` (``observation``,
        ``reward``, ``terminated``, ``truncated``, ``done``, ``termination_cause``). A row that did not
        terminate by step ``max_steps`` is truncated there.
        """
        n = max(int(self.length.max()), 1) if self.length.numel() else 1
        cause = self.cause[..., :n]
        terminated = cause != int(TerminationCause.NONE)
        truncated = self.last()[..., :n] & ~terminated & (self.length == max_steps).unsqueeze(-1)
        batch = [*self.length.shape, n]
        steps = torch.arange(n, device=cause.device).expand(*batch)
        column = lambda x: x.unsqueeze(-1)  # noqa: E731
        following = {
            "observation": self.states[..., 1 : n + 1, :],
            "reward": column(self.reward[..., :n]),
            "terminated": column(terminated),
            "truncated": column(truncated),
            "done": column(terminated | truncated),
            "termination_cause": column(cause),
        }
        now = {
            "observation": self.states[..., :n, :],
            "action": self.action[..., :n, :],
            "step_count": column(steps),
        }
        return TensorDict({**now, "next": following}, batch_size=batch)


#: Start states ``[*B, 6]`` (and, under disturbances, episode ``keys`` ``[*B]``) -> whole episodes, one
#: per row, with the deterministic action (the fast engine's KernelRollout).
RolloutFn = Callable[..., Episodes]


@torch.no_grad()
def fly_reference(
    policy: TensorDictModuleBase,
    start: torch.Tensor,
    keys: torch.Tensor | None = None,
    device: str | torch.device = "cpu",
    **env_kwargs,
) -> Episodes:
    """Fly a TensorDict policy's deterministic episodes from ``start`` ``[*B, 6]`` in the reference env.

    The policy: an actor, the PD controller, a replayed plan; under disturbances with episode
    ``keys`` ``[*B]``. The reference: a ``DroneEnv(batch_size=B, **env_kwargs)`` and TorchRL's
    rollout, one episode per row.
    """
    env = DroneEnv(batch_size=list(start.shape[:-1]), device=device, **env_kwargs)
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
