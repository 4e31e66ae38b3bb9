"""Plain Monte-Carlo REINFORCE (Sutton & Barto, section 13.3), as a TorchRL ``LossModule``.

TorchRL's own ``ReinforceLoss`` needs a critic and a value estimator; the paper's algorithm has
neither, so this module is written here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

BASELINES = ("none", "mean")
LOG_PROB_REDUCTIONS = ("sum", "mean")


def discounted_returns(reward: torch.Tensor, done: torch.Tensor, gamma: float | torch.Tensor) -> torch.Tensor:
    """Return-to-go ``G_t = sum_{k>t} gamma^(k-t-1) R_k`` over ``[*B, T, 1]``, cut at ``done``.

    Several episodes may follow each other in a row: the sum restarts after every ``done``.
    ``gamma`` may be a float or a tensor broadcastable to ``[*B, 1]`` (one discount per row).
    Same result as ``torchrl.objectives.value.functional.reward2go``, which is about 20x slower
    on ``[4096, 300]`` and takes only a scalar discount.
    """
    returns = torch.empty_like(reward)
    running = torch.zeros_like(reward[..., -1, :])
    keep = (~done).to(reward.dtype)
    for t in range(reward.shape[-2] - 1, -1, -1):
        running = reward[..., t, :] + gamma * running * keep[..., t, :]
        returns[..., t, :] = running
    return returns


def valid_steps(done: torch.Tensor) -> torch.Tensor:
    """Mask of the steps up to and including each row's first ``done`` (``[*B, T, 1]``).

    ``EnvBase.rollout(..., break_when_all_done=True)`` repeats finished rows' last step until every
    row is done; those repeats must not count.
    """
    done_before = done.cumsum(-2) - done.to(torch.int64)
    return done_before == 0


class ReinforceLoss(LossModule):
    """``loss = -sum_t w_t * G_t * log pi(A_t | S_t)``, averaged over the episodes of the batch.

    Args:
        actor_network: a ``ProbabilisticActor`` (its ``get_dist`` scores the STORED actions; the
            loss never resamples).
        gamma: discount of the return-to-go (paper: 0.99).
        discount_weight: multiply step ``t`` by ``gamma^t`` as in Sutton & Barto's pseudo-code
            (``w_t``; the paper's code and preset leave it off, ``w_t = 1``).
        normalize_returns: standardise ``G_t`` over the valid steps of the batch.
        baseline: ``"none"`` (paper) or ``"mean"``: subtract the batch mean of ``G_t``.
        log_prob_reduction: ``"sum"`` (the paper's text: the joint log-probability of the two
            motors) or ``"mean"`` (the paper's public code: their mean, half the gradient).
        agent_dims: leading batch dims that index independent agents (fused training): every
            reduction (episode mean, baseline, normalisation) is then per agent, and
            ``loss_reinforce`` is the sum of the agents' losses. ``gamma`` may then be a tensor
            with one discount per agent.

    Input: a ``[*B, T]`` tensordict with ``observation``, ``action``, ``step_count`` and
    ``("next", "reward" | "done")``. Padded steps are excluded through ``("collector", "mask")``
    when present (TorchRL collectors), otherwise through :func:`valid_steps`.

    Output keys: ``loss_reinforce`` (to minimise), and detached diagnostics ``loss_per_agent``,
    ``return_mean`` (mean ``G_0`` per episode), ``log_prob_mean``, ``episodes`` (per agent when
    ``agent_dims > 0``, scalars otherwise).
    """

    @dataclass
    class _AcceptedKeys:
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        step_count: NestedKey = "step_count"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_reinforce"]

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        gamma: float | torch.Tensor = 0.99,
        discount_weight: bool = False,
        normalize_returns: bool = False,
        baseline: str = "none",
        agent_dims: int = 0,
        log_prob_reduction: str = "sum",
    ) -> None:
        if baseline not in BASELINES:
            raise ValueError(f"algo.baseline={baseline!r} is not allowed; expected one of {BASELINES}")
        if log_prob_reduction not in LOG_PROB_REDUCTIONS:
            raise ValueError(
                f"algo.log_prob_reduction={log_prob_reduction!r} is not allowed; expected one of {LOG_PROB_REDUCTIONS}"
            )
        super().__init__()
        self.actor_network = actor_network
        self.gamma = gamma
        self.discount_weight = discount_weight
        self.normalize_returns = normalize_returns
        self.baseline = baseline
        self.agent_dims = agent_dims
        self.log_prob_reduction = log_prob_reduction

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        reward = tensordict.get(("next", keys.reward))
        done = tensordict.get(("next", keys.done))
        mask = tensordict.get(("collector", "mask"), default=None)
        mask = valid_steps(done) if mask is None else mask.reshape(done.shape)
        n_agent = self.agent_dims
        gamma = self.gamma
        if isinstance(gamma, torch.Tensor):  # one discount per agent: [*A] -> [*A, 1, ..., 1]
            gamma = gamma.reshape(*gamma.shape, *([1] * (reward.ndim - n_agent - 1)))
        returns = discounted_returns(reward, done & mask, gamma).squeeze(-1)
        mask = mask.squeeze(-1)
        step = tensordict.get(keys.step_count).squeeze(-1)
        # Sums over everything but the agent dims: each agent's loss is its own episodes' mean,
        # and the total is the sum over agents, so each agent's gradient is exactly its own.
        dims = tuple(range(n_agent, returns.ndim))

        def per_agent(x: torch.Tensor) -> torch.Tensor:
            return torch.where(mask, x, 0.0).sum(dims)

        def broadcast(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(*x.shape, *([1] * len(dims)))

        starts = (step == 0) & mask
        episodes = starts.sum(dims).clamp_min(1)
        steps = mask.sum(dims).clamp_min(1)
        episode_return = per_agent(torch.where(starts, returns, 0.0)) / episodes

        weight = returns
        if self.baseline == "mean" or self.normalize_returns:
            weight = weight - broadcast(per_agent(returns) / steps)
        if self.normalize_returns:
            std = (per_agent(weight**2) / steps).sqrt()
            weight = weight / broadcast(std + torch.finfo(returns.dtype).eps)
        if self.discount_weight:
            weight = weight * gamma ** step.to(returns.dtype)

        dist = self.actor_network.get_dist(tensordict)
        action = tensordict.get(keys.action)
        log_prob = dist.log_prob(action)  # the motors' log-probabilities, summed
        if self.log_prob_reduction == "mean":
            log_prob = log_prob / action.shape[-1]
        loss_per_agent = per_agent(-(weight.detach() * log_prob)) / episodes
        return TensorDict(
            {
                "loss_reinforce": loss_per_agent.sum(),
                "loss_per_agent": loss_per_agent.detach(),
                "return_mean": episode_return.detach(),
                "log_prob_mean": (per_agent(log_prob) / steps).detach(),
                "episodes": episodes.detach(),
            },
            batch_size=[],
        )
