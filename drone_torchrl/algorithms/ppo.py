"""PPO on the drone (``algo=ppo``): TorchRL's collector, GAE and ``ClipPPOLoss``, booked by the run record.

:class:`OnPolicy` is the loop every actor-critic algorithm here shares (collector, GAE, minibatch
epochs, checkpoint entries, the budget); :class:`PPO` gives it ``ClipPPOLoss``, and
:class:`~drone_torchrl.algorithms.a2c.A2C` gives it ``A2CLoss``.

As in TorchRL's ``sota-implementations/ppo``: a :class:`torchrl.collectors.Collector` flies
``algo.num_envs`` drones of one batched :class:`~drone_torchrl.envs.drone_env.DroneEnv` (auto-reset, so each
drone starts a new episode as soon as one ends) for ``algo.steps_per_batch`` steps;
:class:`~torchrl.objectives.value.GAE` computes advantages and value targets with the critic; ``algo.epochs``
passes of minibatches drawn without replacement from a replay buffer train the three-net actor and the critic
with one Adam.
With ``backend=fast`` the same batches are flown by the C++ engine
(:class:`~drone_torchrl.training.segments.FusedSegments`), collected 8-19x faster (docs/beyond.md: "A
learned policy at the optimum").

It runs in the same training loop as REINFORCE (:class:`~drone_torchrl.training.trainer.Trainer`,
behind the update contract of :mod:`drone_torchrl.training.update`): each finished episode goes to the same :class:`~.run.RunRecord`
(``episodes.csv``, TensorBoard, evaluations, ``best.pt``/``last.pt``, resume). Only the drones'
current episodes are not in a checkpoint: a resumed run starts them afresh (they were not booked,
so no episode is lost or counted twice, but the run does not replay the interrupted one exactly).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torch.nn import functional
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss, LossModule
from torchrl.objectives.value import GAE

from drone_torchrl.algorithms import Algorithm, register
from drone_torchrl.checks import ConfigError
from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.episodes import EPISODE_KEYS, EpisodeTracker
from drone_torchrl.migrations import FAST
from drone_torchrl.modules.factory import build_actor, build_critic, build_policy
from drone_torchrl.modules.policy import distribution_head
from drone_torchrl.schema import (
    ADAM_EPS,
    ANNEAL_LR,
    CRITIC_COEFF,
    ENTROPY_COEFF,
    EPISODES,
    EPOCHS,
    GAE_LAMBDA,
    GAMMA,
    LR,
    MAX_GRAD_NORM,
    MINIBATCH_SIZE,
    NUM_ENVS,
    REWARD_SCALE,
    STEPS_PER_BATCH,
    VALUE_HIDDEN_SIZES,
    a_number,
    free,
    store_plugin,
)
from drone_torchrl.training.memory_estimate import on_policy_parts
from drone_torchrl.training.segments import FusedSegments
from drone_torchrl.training.update import UpdateOutput

# Added to the advantages' standard deviation: a batch whose advantages are all equal stays finite.
ADVANTAGE_EPS = 1e-8


@contextlib.contextmanager
def quiet(logger_name: str) -> Iterator[None]:
    """Raise logger ``logger_name`` to WARNING inside the block (no INFO messages), then restore it."""
    logger = logging.getLogger(logger_name)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def within_budget(batch: TensorDictBase, remaining: int) -> TensorDictBase:
    """A collector batch ``[drones, steps]`` cut at the step the budget's last episode ends.

    A collector batch (``[drones, steps]``) up to the step at which the budget's last episode ends: a batch of 64 drones x 64
    steps can finish dozens of short episodes, so without this a budget of 20 would train 43. The
    steps after it are dropped (the run ends there: the drones' next episodes are not booked), and
    episodes that end on that same step are booked too, so the budget may be passed by those.
    """
    done = batch.get(("next", "done")).reshape(batch.shape[0], batch.shape[1])  # [drones, steps]
    ended_by = done.sum(0).cumsum(0)
    if remaining <= 0 or ended_by[-1] <= remaining:
        return batch
    last_step = int(torch.searchsorted(ended_by, remaining))  # first step with >= remaining ended
    return batch[:, : last_step + 1]


def update_output(
    metrics: list[dict[str, float]],
    episodes: list[dict[str, list]],
    checks: tuple[str, ...],
    active: torch.Tensor,
) -> UpdateOutput:
    """One agent's ``k`` updates in the update contract's layout.

    One agent's ``k`` updates (``metrics`` and ``episodes``, one of each per update) in the update
    contract's layout: metrics ``[k, 1]``, each update's episodes padded to the most any ended, with
    a ``"valid"`` mask.
    """
    k = len(metrics)
    most = max(1, *(len(e["return"]) for e in episodes))
    padded = {key: [[e[key] + [0] * (most - len(e[key]))] for e in episodes] for key in EPISODE_KEYS}
    valid = [[[True] * len(e["return"]) + [False] * (most - len(e["return"]))] for e in episodes]
    values = torch.tensor([[[m[name] for name in checks]] for m in metrics], dtype=torch.float64)
    out = {name: values[..., i] for i, name in enumerate(checks)}
    out["active"] = active.reshape(1, 1).expand(k, 1)
    out["checks"] = values.isfinite()
    stats = {key: torch.tensor(padded[key]) for key in EPISODE_KEYS}
    return UpdateOutput(out, {**stats, "valid": torch.tensor(valid)})


class OnPolicy:
    """One actor-critic run as the training loop drives it: collector, GAE, loss, optimizer.

    The training loop is :class:`~drone_torchrl.training.trainer.Trainer`. :meth:`update` follows the engines' contract
    (:mod:`drone_torchrl.training.update`): ``k`` collector batches, each followed by ``algo.epochs``
    passes of minibatches; its episodes are those that ended in each batch (any number: padded, with
    a ``"valid"`` mask). A subclass gives :meth:`make_loss` and the :attr:`diagnostics` to book of
    what its loss reports; the losses summed and booked are the loss's ``loss_*`` outputs. It may
    also change what the loss sees of the batch's advantages (:meth:`scale_advantage`) and how the
    gradients are clipped before each step (:meth:`clip_gradients`).

    Args:
        jobs: the one job trained (an actor-critic run trains no population): its ``cfg``.
    """

    @staticmethod
    def max_agents(cfg) -> int:
        """One run per learner: it is a batch of drones already."""
        return 1

    advice = "lower algo.lr"
    episodes_per_update = None  # the episodes a batch finishes vary: one update per call
    eval_agents = None
    #: What the loss reports besides its losses, booked as train/<name> where the loss has it
    #: (A2CLoss reports no entropy without an entropy bonus).
    diagnostics: tuple[str, ...] = ()

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        """The algorithm's TorchRL loss over ``actor`` and ``critic``, from ``self.cfg.algo``."""
        raise NotImplementedError

    def scale_advantage(self, advantage: torch.Tensor) -> torch.Tensor:
        """The batch's advantages as the loss sees them.

        As GAE gave them here (ClipPPOLoss standardises each minibatch itself); A2C standardises the batch's.
        """
        return advantage

    def hold_frames(self, batch: TensorDictBase) -> int:
        """Keep the batch's frames (``[frames]``) for this update's minibatches; how many there are."""
        self.buffer.empty()  # a batch cut at the budget is smaller than the storage
        with quiet("torchrl"):  # its storage announces its first allocation at INFO level
            self.buffer.extend(batch)
        return len(self.buffer)

    def minibatch(self, size: int) -> Any:
        """``size`` of the held frames, drawn without replacement within an epoch."""
        return self.buffer.sample(size)

    def losses(self, minibatch: Any) -> Mapping[str, torch.Tensor]:
        """The loss's outputs on one minibatch."""
        return self.loss(minibatch)

    def clip_gradients(self) -> torch.Tensor:
        """Clip the loss's gradients before the optimizer's step; returns the norm, ``train/grad_norm``.

        Clip the loss's gradients before the optimizer's step (``algo.max_grad_norm`` on all of
        its parameters together); the norm returned is booked as ``train/grad_norm``.
        """
        limit = self.cfg.algo.max_grad_norm
        return nn.utils.clip_grad_norm_(self.params, math.inf if limit is None else limit)

    def __init__(self, jobs) -> None:
        (job,) = jobs
        cfg = self.cfg = job.cfg
        algo = cfg.algo
        torch.manual_seed(cfg.seed)
        net = build_policy(cfg, cfg.seed)
        self.actor_module = build_actor(cfg, net, return_log_prob=True)
        self.critic = build_critic(cfg)
        self.loss = self.make_loss(self.actor_module, self.critic)
        self.advantage = GAE(
            gamma=algo.gamma, lmbda=algo.gae_lambda, value_network=self.critic, average_gae=False
        )
        self.fused = cfg.backend == FAST
        # Listed once: the loss module's parameters() walks its modules on each call.
        self.params = list(self.loss.parameters())
        # backend=fast: Adam's fused kernel, a fifth of the per-parameter loop's time on these nets.
        self.optimizer = torch.optim.Adam(
            self.params, lr=algo.lr, eps=algo.adam_eps, fused=self.fused or None
        )
        frames = algo.num_envs * algo.steps_per_batch
        if self.fused:
            self.collector = FusedSegments(cfg, self.actor_module, net)
            self._generator = self.collector.generator
        else:
            self.env = DroneEnv(batch_size=[algo.num_envs], device=cfg.device, **env_kwargs(cfg))
            self.env.set_seed(cfg.seed)
            self._generator = self.env._generator
        checkpoint = job.checkpoint
        if checkpoint is not None:
            self.actor_module.load_state_dict(checkpoint["actor"])
            self.critic.load_state_dict(checkpoint["critic"])
            self.optimizer.load_state_dict(checkpoint["optimizer"])
            torch.set_rng_state(checkpoint["rng"]["torch"])
            self._generator.set_state(checkpoint["rng"]["env"])
            if self.fused:
                self.collector.restart()
        # The loop's state: the episodes booked (for the learning-rate schedule). The weights and
        # Adam's moments live in TorchRL's loss module and torch.optim.Adam.
        done = 0 if checkpoint is None else checkpoint["episodes_done"]
        self.state = TensorDict({"episodes_done": torch.tensor([done])}, batch_size=[1])
        self.budget = algo.episodes
        if not self.fused:  # made after the checkpoint: it resets the env from the restored generator
            self.collector = Collector(
                self.env,
                self.actor_module,
                frames_per_batch=frames,
                total_frames=-1,
                device=cfg.device,
                auto_register_policy_transforms=False,
            )
        self._batches = iter(self.collector)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(frames, device=cfg.device),
            sampler=SamplerWithoutReplacement(),
        )
        self.tracker = EpisodeTracker(algo.num_envs, cfg.device)
        reported = self.loss.out_keys
        self.loss_keys = tuple(k for k in reported if k.startswith("loss_"))
        self.reported = (*self.loss_keys, *(k for k in self.diagnostics if k in reported))
        self.checks = tuple(f"train/{k}" for k in (*self.reported, "grad_norm"))

    def update(
        self, state: TensorDictBase, k: int, active: torch.Tensor
    ) -> tuple[TensorDictBase, UpdateOutput]:
        """Train on ``k`` collector batches, each followed by ``algo.epochs`` passes of minibatches.

        Returns ``state`` (its ``"episodes_done"`` advanced) and the batches' metrics and episodes.
        """
        metrics: list[dict[str, float]] = []
        episodes: list[dict[str, list]] = []
        for _ in range(k):
            batch = within_budget(next(self._batches), self.budget - int(state["episodes_done"]))
            ended = self.tracker.update(batch)
            metrics.append(self._learn(batch, int(state["episodes_done"])))
            state["episodes_done"] += len(ended["return"])
            episodes.append(ended)
        return state, update_output(metrics, episodes, self.checks, active)

    def _learn(self, batch, episodes_done: int) -> dict[str, float]:
        """GAE on the batch, then ``algo.epochs`` passes of minibatches; the last pass's mean metrics."""
        algo = self.cfg.algo
        if algo.anneal_lr:  # linearly to 0 at the budget, as TorchRL's and CleanRL's PPO do (by frames there)
            for group in self.optimizer.param_groups:
                group["lr"] = algo.lr * max(0.0, 1.0 - episodes_done / self.budget)
        batch = batch.clone(False)
        batch.set(("next", "reward"), batch.get(("next", "reward")) * algo.reward_scale)
        with torch.no_grad():
            self.advantage(batch)
            batch.set("advantage", self.scale_advantage(batch.get("advantage")))
        frames = self.hold_frames(batch.reshape(-1))
        # A batch cut at the budget may hold fewer frames than one minibatch: then one of all of them.
        size = min(algo.minibatch_size, frames)
        steps = frames // size
        sums: dict[str, torch.Tensor] = {}
        for epoch in range(algo.epochs):
            for _ in range(steps):
                losses = self.losses(self.minibatch(size))
                total = sum(losses[k] for k in self.loss_keys)
                self.optimizer.zero_grad()
                total.backward()
                norm = self.clip_gradients()
                self.optimizer.step()
                if epoch == algo.epochs - 1:
                    for key, value in (
                        *((k, losses[k]) for k in self.reported),
                        ("grad_norm", norm),
                    ):
                        sums[key] = sums.get(key, 0) + value.detach()
        return {f"train/{k}": (v / steps).item() for k, v in sums.items()}

    def eval_policy(self):
        """The actor, for evaluations."""
        return self.actor_module

    def actor(self, agent: int):
        """The actor (a run is one agent), for videos."""
        return self.actor_module

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """The checkpoint entries the run record does not own: actor, critic, optimizer, RNG."""
        return {
            "actor": self.actor_module.state_dict(),
            "critic": self.critic.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": {"torch": torch.get_rng_state(), "env": self._generator.get_state(), "agent": None},
        }

    def close(self) -> None:
        """Shut the collector down (the fused engine has none)."""
        if not self.fused:
            self.collector.shutdown()


class PPO(OnPolicy):
    """PPO: TorchRL's ``ClipPPOLoss`` (clipped ratio, normalised advantages).

    With ``backend=fast`` the minibatches are plain tensors and their losses :func:`clip_ppo_losses`' (the
    same values and gradients, without TensorDict's and TorchRL's machinery around a small network).

    Args:
        jobs: the one job trained, as for :class:`OnPolicy`.
    """

    diagnostics = ("entropy", "kl_approx", "clip_fraction")

    def __init__(self, jobs) -> None:
        super().__init__(jobs)
        self.fused_loss = self.fused and not self.cfg.algo.entropy_coeff
        self.policy_net = self.actor_module.module[0].module  # observation -> (loc, scale)
        self.head = distribution_head(self.cfg.model.distribution, self.cfg.env.max_thrust)
        keys = self.loss.tensor_keys
        self.frame_keys = (
            "observation",
            keys.action,
            keys.sample_log_prob,
            keys.advantage,
            keys.value_target,
        )
        self.held: list[torch.Tensor] = []
        self.order = torch.empty(0, dtype=torch.long)

    def hold_frames(self, batch: TensorDictBase) -> int:
        """Keep the batch's ``[frames]`` for this update's minibatches; returns how many there are."""
        if not self.fused_loss:
            return super().hold_frames(batch)
        observation, action, *rest = (batch.get(key) for key in self.frame_keys)
        with torch.no_grad():
            self.held = [observation, *pre_image(self.head, action), *rest]
        self.order = torch.empty(0, dtype=torch.long)
        return batch.numel()

    def minibatch(self, size: int) -> Any:
        """``size`` of the held frames, drawn without replacement within an epoch."""
        if not self.fused_loss:
            return super().minibatch(size)
        if len(self.order) < size:  # an epoch's permutation is spent: the next epoch's
            self.order = torch.randperm(len(self.held[0]), device=self.cfg.device)
        index, self.order = self.order[:size], self.order[size:]
        return [held[index] for held in self.held]

    def losses(self, minibatch: Any) -> Mapping[str, torch.Tensor]:
        """The loss's outputs on one minibatch."""
        if not self.fused_loss:
            return super().losses(minibatch)
        return clip_ppo_losses(
            self.policy_net,
            self.critic.module,
            minibatch,
            self.loss.clip_epsilon,
            self.loss.critic_coeff,
        )

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        """TorchRL's ``ClipPPOLoss`` over ``actor`` and ``critic``, from ``algo.*``."""
        algo = self.cfg.algo
        return ClipPPOLoss(
            actor,
            critic,
            clip_epsilon=algo.clip_epsilon,
            # Without a bonus the entropy (a sampled estimate for TanhNormal) only costs time: a
            # fifth of each minibatch's forward and backward. train/entropy is then not booked.
            entropy_bonus=algo.entropy_coeff > 0,
            entropy_coeff=algo.entropy_coeff,
            critic_coeff=algo.critic_coeff,
            normalize_advantage=True,
            # The actor's and critic's own parameters, not functional copies of them: the same
            # loss and gradients (tests/test_ppo.py), without TensorDict's parameter swapping on
            # each call; checkpoints and Adam's state keep their order.
            functional=False,
        )


# log(sqrt(2 pi)), the Normal log-density's constant, as torch.distributions.Normal writes it.
LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


def pre_image(head: tuple[type, dict], action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Normal sample that ``head`` squashes into ``action``, and the squashing's log-determinant.

    The Normal sample the ``head`` (distribution class, kwargs) squashes into ``action``, and
    the log-determinant of that squashing summed over the action: both depend on the action only, so
    a batch's are computed once, and each minibatch's log-probability is then the Normal's (what
    ``TransformedDistribution.log_prob`` computes, without its objects).
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
) -> dict[str, torch.Tensor]:
    """What ``ClipPPOLoss(normalize_advantage=True, entropy_bonus=False)`` computes, in plain torch.

    What ``ClipPPOLoss(normalize_advantage=True, entropy_bonus=False)`` computes, in plain torch,
    on a minibatch of ``[observation, pre-image and log-determinant of the action (pre_image),
    its log-probability when flown, advantage, value target]``: ``policy`` maps observations to the
    Normal's ``(loc, scale)``, ``value`` to state values. Its losses, ``clip_fraction`` and
    ``kl_approx``, the same values and gradients to float rounding (tests/test_ppo.py).
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
    clipped = log_weight.clamp((-clip_epsilon).log1p(), clip_epsilon.log1p())
    gain = torch.minimum(log_weight.exp() * advantage, clipped.exp() * advantage)
    loss_critic = functional.smooth_l1_loss(value_target, value(observation), reduction="none")
    return {
        "loss_objective": -gain.mean(),
        "loss_critic": critic_coeff * loss_critic.mean(),
        "clip_fraction": (clipped != log_weight).to(log_weight.dtype).mean(),
        "kl_approx": (flown_log_prob - log_prob).detach().mean(),
    }


def validate_on_policy(cfg: Mapping[str, Any]) -> None:
    """The rules of :class:`OnPolicy` that relate keys.

    Each key's bounds are its schema's: PPOConf here, A2CConf in a2c.py.
    """
    name = cfg.algo.name
    if cfg.env.num_workers:
        raise ConfigError.of(
            "env.num_workers",
            cfg.env.num_workers,
            f"0 with algo.name={name} (algo.num_envs drones in one env)",
        )
    frames = cfg.algo.num_envs * cfg.algo.steps_per_batch
    if frames % cfg.algo.minibatch_size:
        raise ConfigError.of(
            "algo.minibatch_size",
            cfg.algo.minibatch_size,
            f"a divisor of algo.num_envs x algo.steps_per_batch = {frames} (the frames of a batch)",
        )


def validate(cfg: Mapping[str, Any]) -> None:
    """PPO's rules that relate keys: the on-policy loop's."""
    validate_on_policy(cfg)


@dataclass
class OnPolicyConf:
    """``algo.*`` every on-policy algorithm has (the loop of ``drone_torchrl.algorithms.ppo.OnPolicy``)."""

    name: Any = free()
    lr: Any = LR.field()
    anneal_lr: Any = ANNEAL_LR.field()
    gamma: Any = GAMMA.field()
    gae_lambda: Any = GAE_LAMBDA.field()
    episodes: Any = EPISODES.field()
    num_envs: Any = NUM_ENVS.field()
    steps_per_batch: Any = STEPS_PER_BATCH.field()
    epochs: Any = EPOCHS.field()
    minibatch_size: Any = MINIBATCH_SIZE.field()
    entropy_coeff: Any = ENTROPY_COEFF.field()
    critic_coeff: Any = CRITIC_COEFF.field()
    reward_scale: Any = REWARD_SCALE.field()
    max_grad_norm: Any = MAX_GRAD_NORM.field()
    adam_eps: Any = ADAM_EPS.field()
    value_hidden_sizes: Any = VALUE_HIDDEN_SIZES.field()


@dataclass
class PPOConf(OnPolicyConf):
    """``algo.*`` of ``algo.name=ppo``: the on-policy keys and the clipping range."""

    clip_epsilon: Any = a_number(low=0, low_open=True, high=1)


store_plugin("algo", "ppo", PPOConf)

register(
    Algorithm(
        "ppo",
        PPO,
        validate,
        checkpoint_keys=("critic",),
        summary="PPO on TorchRL's collector, GAE and ClipPPOLoss",
        memory=on_policy_parts,
    )
)
