"""The update contract every learner follows (REINFORCE's update of a population behind it: :mod:`drone_torchrl.algorithms.reinforce`).

The contract::

    update(state, k, active) -> (state, UpdateOutput)

- ``state``: the population's :attr:`~.population.Population.state`, a ``TensorDict`` of batch size
  ``[N]`` (parameters, optimizer state, per-agent hyper-parameters, RNG counters), updated in place
  (None for a learner of one run, PPO's, A2C's, SAC's, which keeps its own);
- ``k``: how many updates to run in this call; the training loop caps it at the next evaluation,
  checkpoint or end of budget of any agent, so nothing is due inside a call (1 where the updates
  end a varying number of episodes);
- ``active``: ``[N]`` bool, the agents to train (finished and failed agents sit out);
- the output holds ``k`` updates' metrics and finished episodes as ``[k, N, ...]`` tensors, which the
  loop copies to the host once per call (one sync, however many updates and agents).

One update, for all agents at once: the fast engine flies and differentiates every active agent's
episodes in one C++ call; the reference collector's rollout is scored by
:class:`~drone_torchrl.objectives.reinforce.ReinforceLoss` on the stored actions (each agent's loss is the
mean over its own episodes, the total their sum, so each
agent's gradient is exactly its own), one backward gives the ``[N, P]`` gradient, each agent clips
its norm, an agent whose actions, loss or gradient are not finite does not step and drops out of
the rest of the call, the others take their Adam step.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from drone_torchrl.episodes import EPISODE_KEYS


class UpdateOutput(NamedTuple):
    """``k`` updates of ``N`` agents: their ``metrics`` and finished ``episodes``.

    ``metrics``: ``[k, N]`` each (REINFORCE's ``"train/loss"``, ``"train/grad_norm"``,
    ``"policy/std_mean"``); ``"active"`` ``[k, N]`` bool, who was trained in each update;
    ``"checks"`` ``[k, N, C]`` bool, the learner's ``checks`` (REINFORCE's :data:`~drone_torchrl.algorithms.reinforce.CHECKS`).
    ``episodes``: ``[k, N, E]`` each, :data:`~drone_torchrl.episodes.EPISODE_KEYS`, and where the
    updates end a varying number of episodes a ``"valid"`` mask (:func:`one_agent_output`).
    """

    metrics: dict[str, torch.Tensor]
    episodes: dict[str, torch.Tensor]


def one_agent_output(
    metrics: list[dict[str, float]],
    episodes: list[dict[str, list]],
    checks: tuple[str, ...],
    active: torch.Tensor,
) -> UpdateOutput:
    """One agent's ``k`` updates (their ``checks`` metrics, each finite or not) in the contract's layout.

    For a learner whose updates end a varying number of episodes: they come padded, with a
    ``"valid"`` mask. Float64 holds each value exactly, as ``float()`` gave it.
    """
    most = max(1, *(len(e["return"]) for e in episodes))
    padded = {
        key: torch.as_tensor(np.array([[e[key] + [0] * (most - len(e[key]))] for e in episodes]))
        for key in EPISODE_KEYS
    }
    valid = [[[True] * len(e["return"]) + [False] * (most - len(e["return"]))] for e in episodes]
    values = torch.tensor([[[m[name] for name in checks]] for m in metrics], dtype=torch.float64)
    out = {name: values[..., i] for i, name in enumerate(checks)}
    out.update(active=active.reshape(1, 1).expand(len(metrics), 1), checks=values.isfinite())
    return UpdateOutput(out, {**padded, "valid": torch.tensor(valid)})
