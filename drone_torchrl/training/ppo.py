"""PPO on the drone (``algo=ppo``): TorchRL's collector, GAE and ``ClipPPOLoss``, booked by the run record.

As in TorchRL's ``sota-implementations/ppo``: a :class:`torchrl.collectors.Collector` flies
``algo.num_envs`` drones of one batched :class:`~drone_torchrl.envs.DroneEnv` (auto-reset, so each
drone starts a new episode as soon as one ends) for ``algo.steps_per_batch`` steps; :class:`GAE`
computes advantages and value targets with the critic; ``algo.epochs`` passes of minibatches drawn
without replacement from a replay buffer train the three-net actor and the critic with one Adam.

It runs in the same training loop as REINFORCE (:class:`~.trainer.Trainer`, behind the update
contract of :mod:`.update`): each finished episode goes to the same :class:`~.run.RunRecord`
(``episodes.csv``, TensorBoard, evaluations, ``best.pt``/``last.pt``, resume). Only the drones'
current episodes are not in a checkpoint: a resumed run starts them afresh (they were not booked,
so no episode is lost or counted twice, but the run does not replay the interrupted one exactly).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Iterator
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.episodes import EPISODE_KEYS, EpisodeTracker
from drone_torchrl.modules.factory import build_actor, build_critic, build_policy
from drone_torchrl.training.update import UpdateOutput

LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy")
# What ClipPPOLoss reports besides its losses (booked as train/<name>).
DIAGNOSTICS = ("entropy", "kl_approx", "clip_fraction")


@contextlib.contextmanager
def _quiet(logger_name: str) -> Iterator[None]:
    logger = logging.getLogger(logger_name)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


class PPO:
    """One PPO run as the training loop (:class:`~.trainer.Trainer`) drives it: collector, loss,
    optimizer. :meth:`update` follows the engines' contract (:mod:`.update`): ``k`` collector batches,
    each followed by ``algo.epochs`` passes of minibatches; its episodes are those that ended in
    each batch (any number: padded, with a ``"valid"`` mask)."""

    max_agents = 1  # one run per learner: it is a batch of drones already
    advice = "lower algo.lr"
    episodes_per_update = None  # the episodes a batch finishes vary: one update per call
    eval_agents = None

    def __init__(self, jobs) -> None:
        (job,) = jobs
        cfg = self.cfg = job.cfg
        algo = cfg.algo
        torch.manual_seed(cfg.seed)
        self.actor_module = build_actor(cfg, build_policy(cfg, cfg.seed), return_log_prob=True)
        self.critic = build_critic(cfg)
        self.loss = ClipPPOLoss(
            self.actor_module,
            self.critic,
            clip_epsilon=algo.clip_epsilon,
            entropy_coeff=algo.entropy_coeff,
            critic_coeff=algo.critic_coeff,
            normalize_advantage=True,
        )
        self.advantage = GAE(
            gamma=algo.gamma, lmbda=algo.gae_lambda, value_network=self.critic, average_gae=False
        )
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=algo.lr, eps=algo.adam_eps)
        self.env = DroneEnv(batch_size=[algo.num_envs], device=cfg.device, **env_kwargs(cfg))
        self.env.set_seed(cfg.seed)
        checkpoint = job.checkpoint
        if checkpoint is not None:
            self.actor_module.load_state_dict(checkpoint["actor"])
            self.critic.load_state_dict(checkpoint["critic"])
            self.optimizer.load_state_dict(checkpoint["optimizer"])
            torch.set_rng_state(checkpoint["rng"]["torch"])
            self.env._generator.set_state(checkpoint["rng"]["env"])
        # The loop's state: the episodes booked (for the learning-rate schedule). The weights and
        # Adam's moments live in TorchRL's loss module and torch.optim.Adam.
        done = 0 if checkpoint is None else checkpoint["episodes_done"]
        self.state = TensorDict({"episodes_done": torch.tensor([done])}, batch_size=[1])
        self.budget = algo.episodes
        frames = algo.num_envs * algo.steps_per_batch
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
            batch_size=algo.minibatch_size,
        )
        self.tracker = EpisodeTracker(algo.num_envs, cfg.device)
        self.checks = tuple(f"train/{k}" for k in (*LOSS_KEYS, *DIAGNOSTICS, "grad_norm"))

    def update(
        self, state: TensorDictBase, k: int, active: torch.Tensor
    ) -> tuple[TensorDictBase, UpdateOutput]:
        metrics: list[dict[str, float]] = []
        episodes: list[dict[str, list]] = []
        for _ in range(k):
            batch = next(self._batches)
            ended = self.tracker.update(batch)
            metrics.append(self._learn(batch, int(state["episodes_done"])))
            state["episodes_done"] += len(ended["return"])
            episodes.append(ended)
        most = max(1, *(len(e["return"]) for e in episodes))
        padded = {key: [[e[key] + [0] * (most - len(e[key]))] for e in episodes] for key in EPISODE_KEYS}
        valid = [[[True] * len(e["return"]) + [False] * (most - len(e["return"]))] for e in episodes]
        values = torch.tensor([[[m[name] for name in self.checks]] for m in metrics], dtype=torch.float64)
        out = {name: values[..., i] for i, name in enumerate(self.checks)}
        out["active"] = active.reshape(1, 1).expand(k, 1)
        out["checks"] = values.isfinite()
        stats = {key: torch.tensor(padded[key]) for key in EPISODE_KEYS}
        return state, UpdateOutput(out, {**stats, "valid": torch.tensor(valid)})

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
        with _quiet("torchrl"):  # its storage announces its first allocation at INFO level
            self.buffer.extend(batch.reshape(-1))
        steps = len(self.buffer) // algo.minibatch_size
        sums: dict[str, torch.Tensor] = {}
        for epoch in range(algo.epochs):
            for _ in range(steps):
                losses = self.loss(self.buffer.sample())
                total = sum(losses[k] for k in LOSS_KEYS)
                self.optimizer.zero_grad()
                total.backward()
                norm = nn.utils.clip_grad_norm_(
                    self.loss.parameters(), algo.max_grad_norm if algo.max_grad_norm is not None else math.inf
                )
                self.optimizer.step()
                if epoch == algo.epochs - 1:
                    for key, value in (
                        *((k, losses[k]) for k in (*LOSS_KEYS, *DIAGNOSTICS)),
                        ("grad_norm", norm),
                    ):
                        sums[key] = sums.get(key, 0) + value.detach()
        return {f"train/{k}": (v / steps).item() for k, v in sums.items()}

    def eval_policy(self):
        return self.actor_module

    def actor(self, agent: int):
        return self.actor_module

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """The checkpoint entries the run record does not own: actor, critic, optimizer, RNG."""
        return {
            "actor": self.actor_module.state_dict(),
            "critic": self.critic.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": {"torch": torch.get_rng_state(), "env": self.env._generator.get_state(), "agent": None},
        }

    def close(self) -> None:
        self.collector.shutdown()
