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

    The recursion ``G_t = R_t + a_t G_{t+1}`` (``a_t = gamma``, or 0 at a ``done``) is solved as a
    parallel suffix scan: after round ``r`` each step holds the composition of the ``2^r`` steps from
    it, ``G_t = b_t + a_t G_{t+2^r}``, so ``ceil(log2 T)`` rounds of a few whole-tensor operations
    replace ``T`` sequential ones (9 rounds for 300 steps). Same result as
    ``torchrl.objectives.value.functional.reward2go`` up to float rounding (the sums are added in
    another order), which is about 20x slower and takes only a scalar discount.
    """
    gamma = torch.as_tensor(gamma, dtype=reward.dtype, device=reward.device)
    if gamma.ndim:  # broadcastable to [*B, 1]: add the time dim
        gamma = gamma.unsqueeze(-2)
    gain = torch.where(done, 0.0, gamma).expand_as(reward)
    total = reward
    steps, shift = reward.shape[-2], 1
    while shift < steps:
        # Beyond the last step the return is 0: pad the shifted sums with zeros (and the gains, so
        # that later rounds keep adding nothing).
        ahead = torch.nn.functional.pad(total[..., shift:, :], (0, 0, 0, shift))
        total = total + gain * ahead
        gain = gain * torch.nn.functional.pad(gain[..., shift:, :], (0, 0, 0, shift))
        shift *= 2
    return total


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

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The loss of a batch ``[*B, T]`` of episodes: ``loss_objective`` and the diagnostics."""
        keys = self.tensor_keys
        done = tensordict.get(("next", keys.done))
        mask = tensordict.get(("collector", "mask"), default=None)
        mask = valid_steps(done) if mask is None else mask.reshape(done.shape)
        action = tensordict.get(keys.action)
        log_prob = self.actor_network.get_dist(tensordict).log_prob(action)  # the motors', summed
        if self.log_prob_reduction == "mean":
            log_prob = log_prob / action.shape[-1]
        terms = reinforce_terms(
            log_prob,
            tensordict.get(("next", keys.reward)).squeeze(-1),
            done.squeeze(-1),
            mask.squeeze(-1),
            tensordict.get(keys.step_count).squeeze(-1),
            self.gamma,
            agent_dims=self.agent_dims,
            baseline=self.baseline,
            normalize_returns=self.normalize_returns,
            discount_weight=self.discount_weight,
        )
        return TensorDict(terms, batch_size=[])


def reinforce_terms(
    log_prob: torch.Tensor,
    reward: torch.Tensor,
    done: torch.Tensor,
    mask: torch.Tensor,
    step: torch.Tensor,
    gamma: float | torch.Tensor,
    *,
    agent_dims: int = 0,
    baseline: str = "none",
    normalize_returns: bool = False,
    discount_weight: bool = False,
) -> dict[str, torch.Tensor]:
    """The arithmetic of :class:`ReinforceLoss` on plain ``[*A, *B, T]`` tensors.

    ``A``: the ``agent_dims`` leading agent dims. The stored actions' ``log_prob`` (already reduced over the
    motors), ``reward``, ``done``, the ``mask`` of valid steps and each step's index in its episode.
    ``gamma``: a float or one discount per agent (``[*A]``). Returns :class:`ReinforceLoss`'s outputs.
    """
    if isinstance(gamma, torch.Tensor):  # one discount per agent: [*A] -> [*A, 1, ..., 1]
        gamma = gamma.reshape(*gamma.shape, *([1] * (reward.ndim - agent_dims)))
    returns = discounted_returns(reward.unsqueeze(-1), (done & mask).unsqueeze(-1), gamma).squeeze(-1)
    # Sums over everything but the agent dims: each agent's loss is its own episodes' mean,
    # and the total is the sum over agents, so each agent's gradient is exactly its own.
    dims = tuple(range(agent_dims, returns.ndim))

    def per_agent(x: torch.Tensor) -> torch.Tensor:
        return torch.where(mask, x, 0.0).sum(dims)

    def broadcast(x: torch.Tensor) -> torch.Tensor:
        return x.reshape(*x.shape, *([1] * len(dims)))

    starts = (step == 0) & mask
    episodes = starts.sum(dims).clamp_min(1)
    steps = mask.sum(dims).clamp_min(1)
    episode_return = per_agent(torch.where(starts, returns, 0.0)) / episodes

    weight = returns
    if baseline == "mean" or normalize_returns:
        weight = weight - broadcast(per_agent(returns) / steps)
    if normalize_returns:
        std = (per_agent(weight**2) / steps).sqrt()
        weight = weight / broadcast(std + torch.finfo(returns.dtype).eps)
    if discount_weight:
        weight = weight * gamma ** step.to(returns.dtype)

    loss_per_agent = per_agent(-(weight.detach() * log_prob)) / episodes
    return {
        "loss_reinforce": loss_per_agent.sum(),
        "loss_per_agent": loss_per_agent.detach(),
        "return_mean": episode_return.detach(),
        "log_prob_mean": (per_agent(log_prob) / steps).detach(),
        "episodes": episodes.detach(),
    }
