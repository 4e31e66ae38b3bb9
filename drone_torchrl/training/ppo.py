"""PPO on the drone (``algo=ppo``): TorchRL's collector, GAE and ``ClipPPOLoss``, booked by the run record.

As in TorchRL's ``sota-implementations/ppo``: a :class:`torchrl.collectors.Collector` flies
``algo.num_envs`` drones of one batched :class:`~drone_torchrl.envs.DroneEnv` (auto-reset, so each
drone starts a new episode as soon as one ends) for ``algo.steps_per_batch`` steps; :class:`GAE`
computes advantages and value targets with the critic; ``algo.epochs`` passes of minibatches drawn
without replacement from a replay buffer train the three-net actor and the critic with one Adam.

Each finished episode goes to the same :class:`~.run.RunRecord` as in the REINFORCE loop
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
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.episodes import EpisodeTracker
from drone_torchrl.evaluation import evaluate
from drone_torchrl.modules.factory import build_actor, build_critic, build_policy
from drone_torchrl.training.jobs import Job
from drone_torchrl.training.run import Progress, RunRecord

LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy")


@contextlib.contextmanager
def _quiet(logger_name: str) -> Iterator[None]:
    logger = logging.getLogger(logger_name)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


class PPOTrainer:
    """One PPO run: collector, loss, optimizer and the run record of ``job``."""

    def __init__(self, job: Job) -> None:
        cfg = self.cfg = job.cfg
        algo = cfg.algo
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.actor = build_actor(cfg, build_policy(cfg, cfg.seed), return_log_prob=True)
        self.critic = build_critic(cfg)
        self.loss = ClipPPOLoss(
            self.actor,
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
            self.actor.load_state_dict(checkpoint["actor"])
            self.critic.load_state_dict(checkpoint["critic"])
            self.optimizer.load_state_dict(checkpoint["optimizer"])
            torch.set_rng_state(checkpoint["rng"]["torch"])
            self.env._generator.set_state(checkpoint["rng"]["env"])
        # PPO always runs TorchRL's collector; `engine` (a REINFORCE setting) is stored as given, so
        # a resume or a re-run under the population launcher finds the engine it expects.
        self.run = RunRecord(cfg, job.run_dir, cfg.engine, checkpoint, job.parent_dir)
        frames = algo.num_envs * algo.steps_per_batch
        self.collector = Collector(
            self.env,
            self.actor,
            frames_per_batch=frames,
            total_frames=-1,
            device=cfg.device,
            auto_register_policy_transforms=False,
        )
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(frames, device=cfg.device),
            sampler=SamplerWithoutReplacement(),
            batch_size=algo.minibatch_size,
        )
        self.tracker = EpisodeTracker(algo.num_envs, cfg.device)

    def train(self) -> dict[str, float] | None:
        """Train to ``algo.episodes`` finished episodes; returns the final metrics (None if it diverged)."""
        run = self.run
        progress = Progress([run], self.cfg.progress)
        try:
            if run.finished and run.final is None:  # killed between its last checkpoint and the end
                self.evaluate()
                run.save(self.learner_state())
            if run.finished:
                return run.final
            for batch in self.collector:
                episodes = self.tracker.update(batch)
                metrics = self.update(batch)
                if not all(math.isfinite(v) for v in metrics.values()):
                    bad = [k for k, v in metrics.items() if not math.isfinite(v)]
                    run.fail(
                        f"training diverged at episode {run.episodes_done}: non-finite {' and '.join(bad)}; "
                        "lower algo.lr"
                    )
                    break
                run.record(episodes, metrics)
                progress.update(len(episodes["return"]), [run])
                if run.eval_due:
                    self.evaluate()
                if run.checkpoint_due:
                    run.save(self.learner_state())
                if run.finished:
                    break
        finally:
            progress.close()
            self.collector.shutdown()
            run.close()
        return run.final

    def update(self, batch) -> dict[str, float]:
        """GAE on the batch, then ``algo.epochs`` passes of minibatches; the last pass's mean metrics."""
        algo = self.cfg.algo
        if algo.anneal_lr:  # linearly to 0 at the budget, as TorchRL's and CleanRL's PPO do (by frames there)
            for group in self.optimizer.param_groups:
                group["lr"] = algo.lr * max(0.0, 1.0 - self.run.episodes_done / self.run.budget)
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
                        *((k, losses[k]) for k in (*LOSS_KEYS, "entropy", "kl_approx", "clip_fraction")),
                        ("grad_norm", norm),
                    ):
                        sums[key] = sums.get(key, 0) + value.detach()
        return {f"train/{k}": (v / steps).item() for k, v in sums.items()}

    def evaluate(self) -> None:
        """Deterministic episodes on the evaluation seeds, booked by the run record."""
        cfg = self.cfg
        stats, _ = evaluate(self.actor, env_kwargs(cfg), cfg.eval.episodes, cfg.eval.seed, cfg.device)
        result = {k: stats[k].float().mean().item() for k in ("return", "length", "time_in_zone")}
        self.run.record_eval(result, self.learner_state, lambda: self.actor)

    def learner_state(self) -> dict[str, Any]:
        """The checkpoint entries the run record does not own: actor, critic, optimizer, RNG."""
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "rng": {"torch": torch.get_rng_state(), "env": self.env._generator.get_state(), "agent": None},
        }
