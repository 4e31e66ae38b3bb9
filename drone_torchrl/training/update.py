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

REINFORCE's update of a population (:meth:`drone_torchrl.algorithms.reinforce.Reinforce.update`)
trains every active agent at once; PPO's, A2C's and SAC's (:meth:`drone_torchrl.algorithms.ppo.OneRun.update`)
one run, its episodes padded with a ``"valid"`` mask.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class UpdateOutput(NamedTuple):
    """``k`` updates of ``N`` agents: their ``metrics`` and finished ``episodes``.

    ``metrics``: ``[k, N]`` each (REINFORCE's ``"train/loss"``, ``"train/grad_norm"``,
    ``"policy/std_mean"``); ``"active"`` ``[k, N]`` bool, who was trained in each update;
    ``"checks"`` ``[k, N, C]`` bool, the learner's ``checks`` (REINFORCE's :data:`~drone_torchrl.algorithms.reinforce.CHECKS`).
    ``episodes``: ``[k, N, E]`` each, :data:`~drone_torchrl.episodes.EPISODE_KEYS`, and where the
    updates end a varying number of episodes a ``"valid"`` mask (:meth:`~drone_torchrl.algorithms.ppo.OneRun.update`'s).
    """

    metrics: dict[str, torch.Tensor]
    episodes: dict[str, torch.Tensor]
