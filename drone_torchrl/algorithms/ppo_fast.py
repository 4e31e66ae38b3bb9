"""``backend=fast``'s PPO, beside the reference in :mod:`drone_torchrl.algorithms.ppo`.

As LeanRL keeps its compiled variants apart: the C++ engine's batches (:class:`~drone_torchrl.training.segments.FusedSegments`),
Adam's fused kernel, and, without an entropy bonus, :class:`PlainMinibatches`, the twin of the
reference's :class:`~drone_torchrl.algorithms.ppo.Minibatches` that
:meth:`~drone_torchrl.algorithms.ppo.PPO.make_minibatches` picks: plain-tensor minibatches scored by
:func:`clip_ppo_losses` (what ``ClipPPOLoss`` computes, without TensorDict's machinery). Tested
equal: tests/test_ppo.py, test_segments.py.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.nn import functional

from drone_torchrl.modules.policy import distribution_head

# log(sqrt(2 pi)), the Normal log-density's constant, as torch.distributions.Normal writes it.
LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


def pre_image(head: tuple[type, dict], action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Normal sample that ``head`` squashes into ``action``, and the squashing's log-determinant.

    ``head`` is the distribution class and its kwargs; the log-determinant is summed over the
    action. Both depend on the action only, so a batch's are computed once, and each minibatch's
    log-probability is then the Normal's (what ``TransformedDistribution.log_prob`` computes,
    without its objects).
    """
    dist_class, kwargs = head
    dist = dist_class(torch.zeros_like(action), torch.ones_like(action), **kwargs)
    log_det = torch.zeros_like(action)
    for transform in reversed(getattr(dist, "transforms", ())):  # none for a Normal head
        normal = transform.inv(action)
        log_det = log_det + transform.log_abs_det_jacobian(normal, action)
        action = normal
    return action, log_det.sum(-1)


def clip_ppo_losses(
    policy: nn.Module,
    value: nn.Module,
    minibatch: list[torch.Tensor],
    clip_epsilon: torch.Tensor,
    critic_coeff: torch.Tensor,
    dual_clip: float | None = None,
) -> dict[str, torch.Tensor]:
    """What ``ClipPPOLoss(normalize_advantage=True, entropy_bonus=False)`` computes, in plain torch.

    The minibatch is ``[observation, pre-image and log-determinant of the action (pre_image), its
    log-probability when flown, advantage, value target]``: ``policy`` maps observations to the
    Normal's ``(loc, scale)``, ``value`` to state values. Returns its losses, ``clip_fraction`` and
    ``kl_approx``: the same values and gradients to float rounding (tests/test_ppo.py).

    ``dual_clip`` (Ye et al. 2020, "Mastering Complex Control in MOBA Games with Deep RL"): the
    log importance ratio is clamped at ``log(dual_clip)`` before the clipped objective, which bounds a
    negative advantage's term by ``dual_clip x advantage`` and, for ``dual_clip >= 1 + clip_epsilon``,
    leaves the rest of it as it is (a positive advantage's ratio above ``1 + clip_epsilon`` is
    clipped anyway; below that, a positive advantage's ratio is bounded by ``dual_clip`` too).
    None: ClipPPOLoss's objective. The reference twin is
    :class:`~drone_torchrl.algorithms.ppo.DualClipPPOLoss`.
    """
    observation, normal, log_det, flown_log_prob, advantage, value_target = minibatch
    # TorchRL's standardisation: the minibatch's mean and (unbiased) std, the std floored at float32's resolution.
    advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(
        torch.finfo(torch.float).resolution
    )
    loc, scale = policy(observation)
    log_density = -((normal - loc) ** 2) / (2 * scale**2) - scale.log() - LOG_SQRT_2PI
    log_prob = log_density.sum(-1) - log_det
    log_weight = (log_prob - flown_log_prob).unsqueeze(-1)
    if dual_clip is not None:
        log_weight = log_weight.clamp(max=math.log(dual_clip))
    clipped = log_weight.clamp((-clip_epsilon).log1p(), clip_epsilon.log1p())
    gain = torch.minimum(log_weight.exp() * advantage, clipped.exp() * advantage)
    loss_critic = functional.smooth_l1_loss(value_target, value(observation), reduction="none")
    return {
        "loss_objective": -gain.mean(),
        "loss_critic": critic_coeff * loss_critic.mean(),
        "clip_fraction": (clipped != log_weight).to(log_weight.dtype).mean(),
        "kl_approx": (flown_log_prob - log_prob).detach().mean(),
    }


class PlainMinibatches:
    """Plain-tensor replay buffer and ``ClipPPOLoss`` of a run (``cfg``, ``loss``, ``actor``, ``critic``).

    Minibatches are drawn without replacement within an epoch and scored by :func:`clip_ppo_losses`;
    the same three methods as the reference's :class:`~drone_torchrl.algorithms.ppo.Minibatches`.
    """

    def __init__(self, cfg: Any, loss: nn.Module, actor: nn.Module, critic: nn.Module) -> None:
        self.device, self.head = cfg.device, distribution_head(cfg.model.distribution, cfg.env.max_thrust)
        self.policy, self.value = actor.module[0].module, critic.module  # observation -> (loc, scale), value
        self.clip_epsilon, self.critic_coeff = loss.clip_epsilon, loss.critic_coeff
        self.dual_clip = cfg.algo.get("dual_clip")
        k = loss.tensor_keys
        self.frame_keys = ("observation", k.action, k.sample_log_prob, k.advantage, k.value_target)

    def hold(self, batch: TensorDictBase) -> int:
        """Keep the batch's frames (``[frames]``); how many there are."""
        observation, action, *rest = (batch.get(key) for key in self.frame_keys)
        with torch.no_grad():
            self.held = [observation, *pre_image(self.head, action), *rest]
        self.order = torch.empty(0, dtype=torch.long)
        return batch.numel()

    def sample(self, size: int) -> list[torch.Tensor]:
        """``size`` of the held frames."""
        if len(self.order) < size:  # an epoch's permutation is spent: the next epoch's
            self.order = torch.randperm(len(self.held[0]), device=self.device)
        index, self.order = self.order[:size], self.order[size:]
        return [held[index] for held in self.held]

    def losses(self, minibatch: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """:func:`clip_ppo_losses` of the minibatch."""
        return clip_ppo_losses(
            self.policy, self.value, minibatch, self.clip_epsilon, self.critic_coeff, self.dual_clip
        )
