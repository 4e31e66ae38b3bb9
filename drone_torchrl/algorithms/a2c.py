"""A2C on the drone (``algo=a2c``): TorchRL's ``A2CLoss`` on the shared on-policy loop.

The synchronous advantage actor-critic of Mnih et al. (2016), as TorchRL's sota-implementations
run it: ``algo.num_envs`` drones of one batched env fly ``algo.steps_per_batch`` steps, GAE gives
the advantages (``gae_lambda`` 1 would be plain n-step returns), and one gradient step of the
policy-gradient, value and entropy losses follows per batch (``epochs: 1``, one minibatch of the
whole batch; more of either turns it towards PPO without the clipping that makes that safe).
Everything but the loss (collector, GAE, the episode budget, checkpoints, resume) is
:class:`~drone_torchrl.algorithms.ppo.OnPolicy`'s, shared with PPO.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from torch import nn
from torchrl.objectives import A2CLoss, LossModule

from drone_torchrl.algorithms import Algorithm, register
from drone_torchrl.algorithms.ppo import OnPolicy, OnPolicyConf, validate_on_policy
from drone_torchrl.schema import store_plugin


class A2C(OnPolicy):
    """A2C: TorchRL's ``A2CLoss`` (advantage-weighted log-probabilities, a value loss, an entropy bonus)."""

    diagnostics = ("entropy",)
    # A2CLoss weighs log-probabilities by the raw advantages; standardised per batch (as SB3's A2C
    # offers and PPO does per minibatch) the step size no longer follows the returns' scale.
    normalize_batch_advantage = True

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        algo = self.cfg.algo
        return A2CLoss(actor, critic, entropy_coeff=algo.entropy_coeff, critic_coeff=algo.critic_coeff)


def validate(cfg: Mapping[str, Any]) -> None:
    """A2C's rules that relate keys are the on-policy loop's."""
    validate_on_policy(cfg)


@dataclass
class A2CConf(OnPolicyConf):
    """``algo.*`` of ``algo.name=a2c``: the on-policy keys."""


store_plugin("algo", "a2c", A2CConf)

register(
    Algorithm(
        "a2c",
        A2C,
        validate,
        checkpoint_keys=("critic",),
        summary="A2C on TorchRL's collector, GAE and A2CLoss (algo=a2c)",
    )
)
