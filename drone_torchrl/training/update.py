"""The update contract every learner follows, and REINFORCE's update of a population behind it.

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
from omegaconf import DictConfig
from tensordict import TensorDictBase

from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.episodes import EPISODE_KEYS, counted_metrics, episode_stats
from drone_torchrl.kernels.modules import KernelReinforce
from drone_torchrl.objectives.reinforce import ReinforceLoss
from drone_torchrl.training.optim import clip_grad_norms
from drone_torchrl.training.population import Population

#: What the finite checks test, in their row order (then the weights after the step).
CHECKS = ("actions", "loss", "gradients", "weights")


class UpdateOutput(NamedTuple):
    """``k`` updates of ``N`` agents: their ``metrics`` and finished ``episodes``.

    ``metrics``: ``[k, N]`` each (REINFORCE's ``"train/loss"``, ``"train/grad_norm"``,
    ``"policy/std_mean"``); ``"active"`` ``[k, N]`` bool, who was trained in each update;
    ``"checks"`` ``[k, N, C]`` bool, the learner's ``checks`` (REINFORCE's :data:`CHECKS`).
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


class Gradient(NamedTuple):
    """One update's gradient of every agent and what the loop books of it (``[N]`` unless noted)."""

    grad: torch.Tensor  # [N, P]
    loss: torch.Tensor
    std: torch.Tensor
    actions_finite: torch.Tensor
    episodes: dict[str, torch.Tensor]  # EPISODE_KEYS -> [N, E]


class ReinforceUpdate:
    """The update of ``population`` with episodes from ``collector`` (either backend's, see :mod:`.collectors`).

    Two ways to the same gradient, tested equal (tests/test_kernels.py):

    - ``backend=fast``: one ``ops.reinforce`` call flies the episodes and returns every
      agent's loss and gradient (:class:`~drone_torchrl.kernels.modules.KernelReinforce`);
    - ``backend=reference``: the collector's ``EnvBase.rollout`` tensordicts, scored by
      :class:`~drone_torchrl.objectives.reinforce.ReinforceLoss` through the ``ProbabilisticActor``, and
      autograd.

    Args:
        cfg: the group's validated config (the loss's options).
        population: the agents trained (their state, Adam and gradient clip).
        collector: where the episodes come from (:class:`~.collectors.TorchRLCollector` or
            :class:`~.collectors.FastCollector`).
    """

    def __init__(self, cfg: DictConfig, population: Population, collector) -> None:
        self.collector = collector
        self.adam = population.adam
        self.max_grad_norm = population.max_grad_norm
        self.gamma = population.state["gamma"]
        algo = cfg.algo
        # Over [N, ...] batches, one discount per agent.
        self.loss = ReinforceLoss(
            collector.actor(),
            gamma=self.gamma,
            agent_dims=1,
            discount_weight=algo.discount_weight,
            normalize_returns=algo.normalize_returns,
            baseline=algo.baseline,
            log_prob_reduction=algo.log_prob_reduction,
        )
        self.kernel = None
        if getattr(collector, "kernel", None) is not None:  # backend=fast
            flags = {
                "baseline_mean": algo.baseline == "mean",
                "normalize_returns": algo.normalize_returns,
                "discount_weight": algo.discount_weight,
                "mean_log_prob": algo.log_prob_reduction == "mean",
            }
            self.kernel = KernelReinforce(collector.kernel, algo.episodes_per_update, flags)

    def begin(self, state: TensorDictBase, k: int) -> None:
        """Before ``k`` updates from ``state``: their random numbers are keyed by its update counters."""
        self._seeds, self._counters = state["seed"], state["counter"].clone()

    def gradient(self, state: TensorDictBase, j: int, active: torch.Tensor) -> Gradient:
        """Update ``j`` (of those announced to :meth:`begin`)'s episodes and gradient, without a step."""
        if self.kernel is None:
            return self._autograd_gradient(state, j, active)
        grad, loss, std, finite, length, counts = self.kernel(
            self._seeds, self._counters + j, self.gamma, active
        )
        return Gradient(
            grad, loss.to(grad.dtype), std.to(grad.dtype), finite, counted_metrics(length, counts)
        )

    def _autograd_gradient(self, state: TensorDictBase, j: int, active: torch.Tensor) -> Gradient:
        """The TorchRL rollout's (``[N, E, T]``) loss terms, episodes and mean policy std, and autograd."""
        params, batch = state["params"], self.collector.collect(j, active)
        terms = self.loss(batch)
        episodes = Episodes.from_rollout(batch)
        valid = episodes.valid().unsqueeze(-1)
        scale = batch.get("scale").detach()  # written by the actor while the loss scored the batch
        std = (scale * valid).sum((1, 2, 3)) / (valid.sum((1, 2, 3)) * scale.shape[-1])
        params.grad = None
        terms["loss_reinforce"].backward()
        grad, params.grad = params.grad, None
        finite = ~(~episodes.action.isfinite() & valid).flatten(1).any(1)
        stats = episode_stats(episodes)
        return Gradient(grad, terms["loss_per_agent"], std, finite, {key: stats[key] for key in EPISODE_KEYS})

    def __call__(
        self, state: TensorDictBase, k: int, active: torch.Tensor
    ) -> tuple[TensorDictBase, UpdateOutput]:
        """Run ``k`` updates of the ``active`` agents (``[N]`` bool); returns ``state`` and their output."""
        params, counter = state["params"], state["counter"]
        self.begin(state, k)
        metrics: list[dict[str, torch.Tensor]] = []
        stats: list[dict[str, torch.Tensor]] = []
        for j in range(k):
            g = self.gradient(state, j, active)
            grad_norms = clip_grad_norms(g.grad, self.max_grad_norm)
            checks = torch.stack([g.actions_finite, g.loss.isfinite(), grad_norms.isfinite()])
            self.adam.step(state, g.grad, active & checks.all(0))
            with torch.no_grad():
                checks = torch.cat([checks, params.isfinite().all(1).unsqueeze(0)])
            counter += active
            stats.append(g.episodes)
            metrics.append(
                {
                    "train/loss": g.loss,
                    "train/grad_norm": grad_norms,
                    "policy/std_mean": g.std,
                    "active": active,
                    "checks": checks.T,
                }
            )
            active = active & checks.all(0)
        stack = lambda rows: {key: torch.stack([row[key] for row in rows]) for key in rows[0]}  # noqa: E731
        return state, UpdateOutput(stack(metrics), stack(stats))
