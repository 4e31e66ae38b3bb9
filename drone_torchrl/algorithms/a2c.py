"""A2C on the drone (``algo=a2c``): TorchRL's ``A2CLoss`` on the shared on-policy update.

The synchronous advantage actor-critic of Mnih et al. (2016), as TorchRL's sota-implementations
run it: ``algo.num_envs`` drones of one batched env fly ``algo.steps_per_batch`` steps, GAE gives
the advantages (``gae_lambda`` 1 would be plain n-step returns), and one gradient step of the
policy-gradient, value and entropy losses follows per batch (``epochs: 1``, one minibatch of the
whole batch; more of either turns it towards PPO without the clipping that makes that safe).
Everything but the loss (collector, GAE, the update, checkpoints, resume) is
:class:`~drone_torchrl.algorithms.ppo.OnPolicy`'s, shared with PPO. Three keys of its own change
the value loss (``algo.loss_critic_type``), what the loss sees of the batch's advantages
(``algo.advantage_scaling``) and whether the critic's gradients are clipped on their own
(``algo.critic_max_grad_norm``); their defaults are what A2C did before they existed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torchrl.objectives import A2CLoss, LossModule

from drone_torchrl.algorithms import register
from drone_torchrl.algorithms.ppo import ADVANTAGE_EPS, OnPolicy, OnPolicyConf, on_policy
from drone_torchrl.schema import a_number, one_of, store_plugin

# A2CLoss's value losses (torchrl.objectives.utils.distance_loss): |d|, d^2, Huber with delta 1.
CRITIC_LOSSES = ("l1", "l2", "smooth_l1")
# What the batch's advantages become before the loss: mean 0 and std 1, mean 0, or as GAE gave them.
ADVANTAGE_SCALINGS = ("standardize", "center", "none")


class A2C(OnPolicy):
    """A2C: TorchRL's ``A2CLoss`` (advantage-weighted log-probabilities, a value loss, an entropy bonus)."""

    diagnostics = ("entropy",)

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        """TorchRL's ``A2CLoss`` over ``actor`` and ``critic``, from ``algo.*``."""
        algo = self.cfg.algo
        return A2CLoss(
            actor,
            critic,
            entropy_coeff=algo.entropy_coeff,
            critic_coeff=algo.critic_coeff,
            loss_critic_type=algo.loss_critic_type,
        )

    def scale_advantage(self, advantage: torch.Tensor) -> torch.Tensor:
        """``algo.advantage_scaling``: A2CLoss weighs log-probabilities by these."""
        scaling = self.cfg.algo.advantage_scaling
        if scaling == "none":
            return advantage
        centred = advantage - advantage.mean()
        # advantage.std(), not centred.std(): the same number, rounded as A2C's updates before the key.
        return centred if scaling == "center" else centred / (advantage.std() + ADVANTAGE_EPS)

    def clip_gradients(self) -> torch.Tensor:
        """Clip the actor's and the critic's gradients, apart if configured so; returns the norm of both.

        ``algo.max_grad_norm`` on the actor and ``algo.critic_max_grad_norm`` on the critic, each on
        its own (null: ``max_grad_norm`` on both together, OnPolicy's); books the norm of both.
        """
        algo = self.cfg.algo
        if algo.critic_max_grad_norm is None:
            return super().clip_gradients()
        limit = math.inf if algo.max_grad_norm is None else algo.max_grad_norm
        actor = nn.utils.clip_grad_norm_(self.actor_module.parameters(), limit)
        critic = nn.utils.clip_grad_norm_(self.critic.parameters(), algo.critic_max_grad_norm)
        return torch.stack([actor, critic]).norm()


@dataclass
class A2CConf(OnPolicyConf):
    """``algo.*`` of ``algo.name=a2c``.

    The on-policy keys, the value loss, the advantages' scaling and the critic's own gradient clip.
    """

    # Each ``added=``: what runs saved before the key existed did (A2CLoss's default critic loss,
    # standardised advantages, one clip and one learning rate for both nets).
    loss_critic_type: Any = one_of(CRITIC_LOSSES, added="smooth_l1")
    advantage_scaling: Any = one_of(ADVANTAGE_SCALINGS, added="standardize")
    critic_max_grad_norm: Any = a_number(low=0, low_open=True, optional=True, added=None)


store_plugin("algo", "a2c", A2CConf)
register(on_policy("a2c", A2C, "A2C on TorchRL's collector, GAE and A2CLoss"))
