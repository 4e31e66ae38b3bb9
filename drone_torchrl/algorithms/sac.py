"""SAC on the drone (``algo=sac``): TorchRL's ``SACLoss``, a TorchRL replay buffer and ``SoftUpdate``.

Soft actor-critic (Haarnoja et al. 2018, with the learned temperature of their second paper), as
TorchRL's ``sota-implementations/sac`` runs it: ``algo.num_envs`` drones fly ``algo.steps_per_batch``
steps with the current TanhNormal actor (bounded thrust), the frames go into a
:class:`~torchrl.data.TensorDictReplayBuffer` of ``algo.buffer_size`` frames
(:class:`~torchrl.data.LazyTensorStorage`, oldest overwritten first), and ``algo.updates_per_batch``
gradient steps on minibatches of ``algo.batch_size`` frames drawn from it follow, each one also
moving the two target Q-networks ``algo.tau`` of the way (``SoftUpdate``). One-step TD targets
(``TD0``), or with ``algo.n_steps`` > 1 TorchRL's ``MultiStep`` sums that many rewards first
(:func:`n_step`): a crash (``terminated``) is not bootstrapped, a step-limit cut (``truncated``) is.

The batches are flown by the C++ engine (``backend=fast``, :class:`~.segments.FusedSegments`, as
PPO's fast path), whose drones' state a checkpoint keeps: a resumed run carries on the drones'
episodes where the checkpoint left them, with the buffer (as far as it is filled), the Q-networks,
their targets, the temperature, Adam's moments and both random generators, so it equals the
uninterrupted run. TorchRL's collector (``backend=reference``) does not expose its envs' running
state, so SAC refuses it in one line.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, MultiStep, RandomSampler, TensorDictReplayBuffer
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators

from drone_torchrl import schema
from drone_torchrl.algorithms import Algorithm, register
from drone_torchrl.algorithms.ppo import OneRun, one_env
from drone_torchrl.checks import ConfigError
from drone_torchrl.memory_estimate import sac_parts
from drone_torchrl.migrations import FAST
from drone_torchrl.modules.factory import build_critic

# Clipped double-Q: the target is the smaller of two Q-networks' (SACLoss's default).
NUM_QVALUE_NETS = 2
# What a frame of the replay buffer holds: the TD0 target and SACLoss need no more.
FRAME_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
)
# SACLoss's outputs booked as train/<name>; the losses among them are summed for one backward pass
# (each reaches only its own parameters: SACLoss detaches the others).
LOSSES = ("loss_actor", "loss_qvalue", "loss_alpha")
REPORTED = (*LOSSES, "alpha", "entropy")


def n_step(frames: TensorDictBase, gamma: float, n: int) -> TensorDictBase:
    """``[drones, steps]`` frames as ``n``-step transitions (TorchRL's ``MultiStep``).

    Each frame's reward becomes the discounted sum of up to ``n`` rewards, its next observation the one after
    the last of them, and ``"steps_to_next_obs"`` their number (TD0 discounts the bootstrap by ``gamma`` to
    that power). A window stops at its episode's end or the batch's; MultiStep leaves the done flags at the
    window's start, so they are set here to the window's last step: a window that ends in a crash is not
    bootstrapped.
    """
    out = MultiStep(gamma, n)(frames)
    last = (torch.arange(frames.shape[-1]) + out.get("steps_to_next_obs") - 1).unsqueeze(-1)
    for flag in ("done", "terminated"):
        out.set(("next", flag), frames.get(("next", flag)).gather(-2, last))
    return out.select(*FRAME_KEYS, "steps_to_next_obs")


class SAC(OneRun):
    """One SAC run behind the update contract (:meth:`drone_torchrl.registry.Learner.update`).

    Each update flies one batch, stores it and takes ``algo.updates_per_batch`` gradient steps.

    Args:
        jobs: the one job trained (SAC trains no population): its ``cfg``.
    """

    checks = tuple(f"train/{k}" for k in REPORTED)

    def __init__(self, jobs) -> None:
        super().__init__(jobs)
        cfg, algo = self.cfg, self.cfg.algo
        self.loss = SACLoss(
            self.actor_module,
            build_critic(cfg, q_value=True),
            num_qvalue_nets=NUM_QVALUE_NETS,
            loss_function="l2",
            alpha_init=algo.alpha_init,
            target_entropy=algo.target_entropy,
        )
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=algo.gamma)
        self.target_update = SoftUpdate(self.loss, tau=algo.tau)
        self.optimizer = torch.optim.Adam(
            [
                {"params": list(self.loss.actor_network_params.values(True, True))},
                {"params": list(self.loss.qvalue_network_params.values(True, True))},
                {"params": [self.loss.log_alpha], "lr": algo.alpha_lr},
            ],
            lr=algo.lr,
        )
        self.parts["optimizer"] = self.optimizer
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(algo.buffer_size, device=cfg.device),
            sampler=RandomSampler(),
            batch_size=algo.batch_size,
        )
        self.start(jobs[0].checkpoint)

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Resume as :meth:`~drone_torchrl.algorithms.ppo.OneRun.restore` does, with the Q-networks, their targets, the temperature and the buffer."""
        super().restore(checkpoint)
        self.loss.load_state_dict({**self.loss.state_dict(), **checkpoint["qvalue"]})
        saved = checkpoint["replay_buffer"]
        frames = TensorDict(saved["frames"]).auto_batch_size_(batch_dims=1)
        if len(frames):
            self.buffer.extend(frames.to(self.cfg.device))
        self.buffer.writer.load_state_dict(saved["writer"])

    def learn(self, batch: TensorDictBase) -> dict[str, float]:
        """The batch stored, then ``algo.updates_per_batch`` gradient steps of the actor, Q-networks and temperature.

        Each step is followed by the targets' soft update. Returns the steps' mean of what SACLoss
        reports.
        """
        algo = self.cfg.algo
        frames = batch.select(*FRAME_KEYS)
        frames.set(("next", "reward"), frames.get(("next", "reward")) * algo.reward_scale)
        if algo.n_steps > 1:
            frames = n_step(frames, algo.gamma, algo.n_steps)
        self.buffer.extend(frames.reshape(-1))
        steps = algo.updates_per_batch
        sums: dict[str, torch.Tensor] = {}
        for _ in range(steps):
            losses = self.loss(self.buffer.sample())
            self.optimizer.zero_grad()
            sum(losses[key] for key in LOSSES).backward()
            self.optimizer.step()
            self.target_update.step()
            for key in REPORTED:
                sums[key] = sums.get(key, 0) + losses[key].detach()
        return {f"train/{key}": (value / steps).item() for key, value in sums.items()}

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """Everything the next update depends on, as checkpoint entries.

        :meth:`~drone_torchrl.algorithms.ppo.OneRun.checkpoint_entries` (actor, Adam, both generators, the drones' running
        episodes), ``qvalue`` (SACLoss's Q-networks, their targets and the temperature) and the
        buffer's filled frames and its write cursor.
        """
        # A copy: the slice is a view, and torch.save writes a view's whole storage (the capacity).
        filled = self.buffer.storage[: len(self.buffer)].clone() if len(self.buffer) else TensorDict()
        return {
            **super().checkpoint_entries(agent),
            "qvalue": {k: v for k, v in self.loss.state_dict().items() if not k.startswith("actor_network")},
            "replay_buffer": {"frames": filled.cpu().to_dict(), "writer": self.buffer.writer.state_dict()},
        }


def validate(cfg: Mapping[str, Any]) -> None:
    """SAC's rules that relate keys (each key's bounds are SACConf's)."""
    if cfg.backend != FAST:
        raise ConfigError.of(
            "backend",
            cfg.backend,
            "'fast' with algo.name=sac (a resumed SAC run carries on its drones' episodes, which "
            "TorchRL's collector does not expose)",
        )
    one_env(cfg)
    if cfg.model.distribution != "tanh_normal":
        raise ConfigError.of(
            "model.distribution",
            cfg.model.distribution,
            "'tanh_normal' with algo.name=sac (bounded thrust: experiment=bounded algo=sac)",
        )
    if cfg.algo.n_steps > 1 and cfg.algo.gamma == 0:
        raise ConfigError.of("algo.gamma", 0, "> 0 with algo.n_steps > 1 (MultiStep's discount)")
    if cfg.algo.batch_size > cfg.algo.buffer_size:
        raise ConfigError.of(
            "algo.batch_size",
            cfg.algo.batch_size,
            f"at most algo.buffer_size = {cfg.algo.buffer_size} (the frames a minibatch is drawn from)",
        )


@dataclass
class SACConf:
    """``algo.*`` of ``algo.name=sac``."""

    name: Any = schema.free()
    lr: Any = schema.LR.field()
    alpha_lr: Any = schema.a_number(low=0, low_open=True, high=schema.MAX_LR)  # lr's bounds; one agent a run
    gamma: Any = schema.GAMMA.field()
    episodes: Any = schema.EPISODES.field()
    num_envs: Any = schema.NUM_ENVS.field()
    steps_per_batch: Any = schema.STEPS_PER_BATCH.field()
    buffer_size: Any = schema.an_integer(low=1)
    batch_size: Any = schema.an_integer(low=1)
    updates_per_batch: Any = schema.an_integer(low=1)
    n_steps: Any = schema.an_integer(low=1, high="env.max_steps")  # a longer window than an episode: no use
    tau: Any = schema.a_number(low=0, low_open=True, high=1)
    alpha_init: Any = schema.a_number(low=0, low_open=True)
    target_entropy: Any = schema.a_number()
    reward_scale: Any = schema.REWARD_SCALE.field()
    qvalue_hidden_sizes: Any = schema.VALUE_HIDDEN_SIZES.field()


schema.store_plugin("algo", "sac", SACConf)

register(
    Algorithm(
        "sac",
        SAC,
        validate,
        checkpoint_keys=("qvalue", "replay_buffer", "drones"),
        summary="SAC on the fast engine's batches, a TorchRL replay buffer and SACLoss",
        memory=sac_parts,
    )
)
