"""PPO on the drone (``algo=ppo``), as TorchRL's ``sota-implementations/ppo`` runs it.

Top to bottom: :class:`OneRun`, what PPO, A2C and SAC share (one job, ``algo.num_envs`` drones flown
by one actor, its update: a batch flown, cut at the budget and learned from); :class:`OnPolicy`
builds the critic, the loss (``ClipPPOLoss`` here, ``A2CLoss`` in :mod:`.a2c`), TorchRL's
:class:`~torchrl.objectives.value.GAE`, one Adam and the collector (one batched, auto-resetting
:class:`~drone_torchrl.envs.drone_env.DroneEnv`, ``algo.steps_per_batch`` steps a batch), and learns
from a batch (``OnPolicy.learn``: GAE, then ``algo.epochs`` passes of minibatch steps: loss,
backward, clip, step). The loop is every algorithm's
(:class:`~drone_torchrl.training.trainer.Trainer`): it books each batch in the
:class:`~drone_torchrl.training.run.RunRecord` (``episodes.csv``, TensorBoard), evaluates (then
``eval.rollback_drop``: :meth:`OnPolicy.after_evaluation`) and checkpoints on the schedule, stops
on a non-finite loss or gradient, or on SIGTERM with a checkpoint. The minibatches and their
losses are :class:`Minibatches` (TorchRL's replay buffer and the loss module); ``backend=fast``
flies the batches on the C++ engine, steps a fused Adam and, for PPO without an entropy bonus,
takes :class:`~.ppo_fast.PlainMinibatches` instead (:meth:`PPO.make_minibatches`).

On ``backend=fast`` a checkpoint keeps the drones' episodes in flight, so a resumed run flies the
episodes an uninterrupted one would; on ``backend=reference`` TorchRL's collector starts them afresh
(they were not booked, so no episode is lost or counted twice).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss, LossModule
from torchrl.objectives.value import GAE

from drone_torchrl import schema
from drone_torchrl.algorithms import Algorithm, Learner, register
from drone_torchrl.algorithms.ppo_fast import PlainMinibatches, clip_ppo_losses, pre_image  # noqa: F401
from drone_torchrl.checks import ConfigError
from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.episodes import EPISODE_KEYS, EpisodeTracker
from drone_torchrl.io.streams import about, console
from drone_torchrl.memory_estimate import on_policy_parts
from drone_torchrl.migrations import FAST
from drone_torchrl.modules.factory import build_actor, build_critic, build_policy
from drone_torchrl.registry import UpdateOutput
from drone_torchrl.training.segments import FusedSegments

if TYPE_CHECKING:
    from drone_torchrl.training.run import AgentBook

# Added to the advantages' standard deviation: a batch whose advantages are all equal stays finite.
ADVANTAGE_EPS = 1e-8
# TorchRL's storages announce their first allocation at INFO level, on stdout: not a run's news.
logging.getLogger("torchrl").addFilter(
    lambda record: not record.getMessage().startswith("Initialized LazyTensorStorage")
)
# A batch's epochs stop where the approximate KL divergence exceeds this many times ``algo.target_kl``
# (Stable-Baselines3's rule).
KL_MARGIN = 1.5


def within_budget(batch: TensorDictBase, remaining: int) -> TensorDictBase:
    """A collector batch ``[drones, steps]`` cut at the step the budget's last episode ends.

    A batch of 64 drones x 64 steps can finish dozens of short episodes, so without this cut a
    budget of 20 would train 43. The steps after the cut are dropped (the run ends there: the
    drones' next episodes are not booked), and episodes that end on that same step are booked too,
    so the budget may be passed by those.
    """
    done = batch.get(("next", "done")).reshape(batch.shape[0], batch.shape[1])  # [drones, steps]
    ended_by = done.sum(0).cumsum(0)
    if remaining <= 0 or ended_by[-1] <= remaining:
        return batch
    last_step = int(torch.searchsorted(ended_by, remaining))  # first step with >= remaining ended
    return batch[:, : last_step + 1]


def one_env(cfg: Mapping[str, Any]) -> None:
    """``env.num_workers`` 0: a run's drones are one batched env (PPO's, A2C's and SAC's rule)."""
    if cfg.env.num_workers:
        raise ConfigError.of(
            "env.num_workers",
            cfg.env.num_workers,
            f"0 with algo.name={cfg.algo.name} (algo.num_envs drones in one env)",
        )


class OneRun(Learner):
    """What PPO, A2C and SAC share: one job (no population), ``algo.num_envs`` drones flown by one actor.

    Each update flies one batch, cut at the budget (:func:`within_budget`), books its ended
    episodes and learns from it (a subclass's :meth:`learn`); the batches end a varying number of
    episodes, so the loop takes one update per call. A subclass builds its loss and optimizer, names
    what its checkpoints keep of them in :attr:`parts`, then calls :meth:`start`.

    Args:
        jobs: the one job trained, fresh or resumed.
    """

    advice = "lower algo.lr"

    def __init__(self, jobs) -> None:
        (job,) = jobs
        self.cfg = cfg = job.cfg
        self.net = build_policy(cfg, cfg.seed)
        self.actor_module = build_actor(cfg, self.net, return_log_prob=True)
        self.tracker = EpisodeTracker(cfg.algo.num_envs, cfg.device)
        self.episodes_done = 0 if job.checkpoint is None else job.checkpoint["episodes_done"]
        # False after a batch cut at the budget: its drones flew on past the cut, unbooked.
        self.carried_on = True
        self.fused = cfg.backend == FAST
        #: What a checkpoint keeps by ``state_dict()`` (and rollback puts back), by entry.
        self.parts: dict[str, Any] = {"actor": self.actor_module}

    def start(self, checkpoint: Mapping[str, Any] | None) -> None:
        """Make the drones' batches (the C++ engine's, or TorchRL's collector over one batched env); resume."""
        cfg, algo = self.cfg, self.cfg.algo
        if self.fused:
            self.collector = FusedSegments(cfg, self.actor_module, self.net)
            self.generator = self.collector.generator
        else:
            self.env = DroneEnv(batch_size=[algo.num_envs], device=cfg.device, **env_kwargs(cfg))
            self.env.set_seed(cfg.seed)
            self.generator = self.env._generator
        if checkpoint is not None:
            self.restore(checkpoint)
        if not self.fused:  # made after the checkpoint: it resets the env from the restored generator
            self.collector = Collector(
                self.env,
                self.actor_module,
                frames_per_batch=algo.num_envs * algo.steps_per_batch,
                total_frames=-1,
                device=cfg.device,
                auto_register_policy_transforms=False,
            )
        self._batches = iter(self.collector)

    def update(self, state: None, k: int, active: torch.Tensor) -> tuple[None, UpdateOutput]:
        """Run ``k`` updates (fly a batch, cut it at the budget, learn); returns ``state`` and their output."""
        metrics: list[dict[str, float]] = []
        episodes: list[dict[str, list]] = []
        for _ in range(k):
            flown = next(self._batches)
            batch = within_budget(flown, self.cfg.algo.episodes - self.episodes_done)
            self.carried_on = batch.shape[1] == flown.shape[1]
            episodes.append(self.tracker.update(batch))
            metrics.append(self.learn(batch))
            self.episodes_done += len(episodes[-1]["return"])
        # The contract's layout: the updates' episodes padded to the most any ended, with a "valid"
        # mask; each of ``checks`` in float64, which holds it exactly, as ``float()`` gave it.
        most = max(1, *(len(e["return"]) for e in episodes))
        padded = {
            key: torch.as_tensor(np.array([[e[key] + [0] * (most - len(e[key]))] for e in episodes]))
            for key in EPISODE_KEYS
        }
        valid = [[[True] * len(e["return"]) + [False] * (most - len(e["return"]))] for e in episodes]
        values = torch.tensor([[[m[name] for name in self.checks]] for m in metrics], dtype=torch.float64)
        out = {name: values[..., i] for i, name in enumerate(self.checks)}
        out.update(active=active.reshape(1, 1).expand(k, 1), checks=values.isfinite())
        return state, UpdateOutput(out, {**padded, "valid": torch.tensor(valid)})

    def learn(self, batch: TensorDictBase) -> dict[str, float]:
        """Learn from one batch; what to book of it, each of ``checks``."""
        raise NotImplementedError

    def actor(self, agent: int):
        """The actor of the run's only agent (for videos)."""
        return self.actor_module

    def eval_policy(self):
        """The policy the evaluator flies: the actor."""
        return self.actor_module

    def load_parts(self, state: Mapping[str, Any]) -> None:
        """Load each of :attr:`parts` from its entry of ``state`` (a checkpoint, or rollback's best state)."""
        for key, part in self.parts.items():
            part.load_state_dict(state[key])

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Resume from ``checkpoint``: the parts, the random states, the drones' episodes in flight.

        On the C++ engine the drones fly on from a checkpoint's ``drones`` entry, or start afresh if
        it kept none (an older checkpoint, or a batch cut at the budget).
        """
        self.load_parts(checkpoint)
        torch.set_rng_state(checkpoint["rng"]["torch"])
        self.generator.set_state(checkpoint["rng"]["env"])
        if not self.fused:
            return
        drones = checkpoint.get("drones")
        if drones is None or drones["carried"] is None:
            self.collector.restart()
        else:
            self.collector.carry_on(drones["carried"])
            self.tracker.load_state(drones["episodes"])

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """The checkpoint entries the run record does not own: the parts, the random states, the drones.

        The drones' episodes in flight on the C++ engine only (the reference's TorchRL collector starts
        its drones afresh on resume); none carried after a batch cut at the budget.
        """
        entries = {key: part.state_dict() for key, part in self.parts.items()}
        entries["rng"] = {"torch": torch.get_rng_state(), "env": self.generator.get_state(), "agent": None}
        if self.fused:
            carried = self.collector.carried() if self.carried_on else None
            entries["drones"] = {"carried": carried, "episodes": self.tracker.state()}
        return entries

    def close(self) -> None:
        """Shut TorchRL's collector down (the fast engine's batches need none)."""
        if not self.fused:
            self.collector.shutdown()


class Minibatches(ReplayBuffer):
    """The reference's minibatches: a batch's frames in TorchRL's replay buffer, scored by ``losses``.

    ``frames`` frames at most, drawn without replacement within an epoch (``sample(size)``). The
    fast twin, with the same ``hold``, ``sample`` and ``losses``, is :class:`~.ppo_fast.PlainMinibatches`.
    """

    def __init__(self, loss: LossModule, frames: int, device: Any) -> None:
        super().__init__(
            storage=LazyTensorStorage(frames, device=device), sampler=SamplerWithoutReplacement()
        )
        self.losses = loss

    def hold(self, batch: TensorDictBase) -> int:
        """Keep the batch's frames (``[frames]``) for this update's minibatches; how many there are."""
        self.empty()  # a batch cut at the budget is smaller than the storage
        self.extend(batch)
        return len(self)


class OnPolicy(OneRun):
    """One actor-critic run: ``__init__`` builds it, :meth:`OnPolicy.learn` is one batch's update.

    A subclass gives :meth:`make_loss` and the :attr:`diagnostics` to book of what its loss reports;
    the losses summed and booked are the loss's ``loss_*`` outputs. It may also change what the loss
    sees of the batch's advantages (:meth:`scale_advantage`), how the gradients are clipped before
    each step (:meth:`clip_gradients`) and the minibatches (:meth:`make_minibatches`).

    Args:
        jobs: the one job trained (an actor-critic run trains no population), fresh or resumed.
    """

    #: What the loss reports besides its losses, booked as train/<name> where the loss has it
    #: (A2CLoss reports no entropy without an entropy bonus).
    diagnostics: tuple[str, ...] = ()

    takes_rollback_drop = True

    def __init__(self, jobs) -> None:
        super().__init__(jobs)
        cfg, algo = self.cfg, self.cfg.algo
        self.critic = build_critic(cfg)
        self.loss = self.make_loss(self.actor_module, self.critic)
        self.advantage = GAE(
            gamma=algo.gamma, lmbda=algo.gae_lambda, value_network=self.critic, average_gae=False
        )
        self.eval_agents = 1 if self.fused else None  # the kernel's rows: one agent
        # Listed once: the loss module's parameters() walks its modules on each call.
        self.params = list(self.loss.parameters())
        self.optimizer = torch.optim.Adam(
            self.params, lr=algo.lr, eps=algo.adam_eps, fused=self.fused or None
        )
        self.parts.update(critic=self.critic, optimizer=self.optimizer)
        self.rollback_drop = cfg.eval.get("rollback_drop")
        # eval.rollback_drop's best state (see after_evaluation) and whether it was returned to.
        self.best_state: dict[str, Any] | None = None
        self.returned_to_best = False
        self.start(jobs[0].checkpoint)
        self.minibatches = self.make_minibatches()
        reported = self.loss.out_keys
        self.loss_keys = tuple(k for k in reported if k.startswith("loss_"))
        self.reported = (*self.loss_keys, *(k for k in self.diagnostics if k in reported))
        self.checks = tuple(f"train/{k}" for k in (*self.reported, "grad_norm"))

    def restore(self, checkpoint: Mapping[str, Any]) -> None:
        """Resume as :meth:`OneRun.restore` does, with ``eval.rollback_drop``'s best state."""
        self._load_best_state(checkpoint)
        super().restore(checkpoint)

    def after_evaluation(self, run: AgentBook, best_before: float) -> None:
        """``eval.rollback_drop``: keep the state of the best evaluation; go back to it after a collapse.

        An evaluation better than every earlier one has its actor, critic and optimizer state kept.
        One more than ``eval.rollback_drop`` below the best (the run not finished) puts that state
        back, once per best: training goes on from the best policy with the random streams where
        they are, so its next batches are new ones. A policy that collapses again from the same
        state is left to recover by itself.
        """
        if self.rollback_drop is None:
            return
        last = run.last_eval_return
        if last > best_before:
            state = {key: part.state_dict() for key, part in self.parts.items()}
            self.best_state = {"return": last, **copy.deepcopy(state)}
            self.returned_to_best = False
        elif (
            self.best_state is not None
            and not self.returned_to_best
            and not run.finished
            and self.best_state["return"] - last > self.rollback_drop
        ):
            self.load_parts(copy.deepcopy(self.best_state))
            self.returned_to_best = True
            console.info(
                f"{run.run_dir}: episode {run.episodes_done}: evaluation return {last:.1f} is more than "
                f"eval.rollback_drop={self.rollback_drop:g} below the best, {self.best_state['return']:.1f}: "
                "training goes on from the best evaluation's policy, critic and optimizer",
                **about(run.run_dir),
            )

    def _load_best_state(self, checkpoint: Mapping[str, Any]) -> None:
        """eval.rollback_drop's best state and whether it was returned to, as ``checkpoint`` keeps them.

        A checkpoint whose best evaluation is above the kept one holds the best state itself: ``best.pt``
        (written before its evaluation's state is kept), or a run whose final evaluation was its best.
        A fork starts with no best (its first evaluation is one).
        """
        saved = checkpoint.get("rollback")
        best = checkpoint["best_eval_return"]
        if self.rollback_drop is None or saved is None or best == -math.inf:
            return
        self.best_state, self.returned_to_best = saved["state"], saved["returned"]
        if self.best_state is None or best > self.best_state["return"]:
            # A copy: Adam's load_state_dict keeps CPU tensors as they are, and steps them in place.
            own = copy.deepcopy({k: checkpoint[k] for k in ("actor", "critic", "optimizer")})
            self.best_state = {"return": best, **own}
            self.returned_to_best = False

    def learn(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE on the batch, then ``algo.epochs`` passes of minibatch steps; the last pass's ``train/*`` means.

        Each step: the minibatch's losses (``self.minibatches``), their sum's backward pass, the
        gradients clipped (:meth:`clip_gradients`), Adam's step.
        """
        algo = self.cfg.algo
        if algo.anneal_lr:  # linearly to 0 at the budget, as TorchRL's and CleanRL's PPO do (by frames there)
            for group in self.optimizer.param_groups:
                group["lr"] = algo.lr * max(0.0, 1.0 - self.episodes_done / algo.episodes)
        batch = batch.clone(False)
        batch.set(("next", "reward"), batch.get(("next", "reward")) * algo.reward_scale)
        with torch.no_grad():
            self.advantage(batch)
            batch.set("advantage", self.scale_advantage(batch.get("advantage")))
        frames = self.minibatches.hold(batch.reshape(-1))
        # A batch cut at the budget may hold fewer frames than one minibatch: then one of all of them.
        size = min(algo.minibatch_size, frames)
        steps = frames // size
        target_kl = algo.get("target_kl")  # PPO's (A2C has none)
        limit = None if target_kl is None else KL_MARGIN * target_kl
        means, stepped = {}, 0
        for _ in range(algo.epochs):
            sums: dict[str, torch.Tensor] = {}
            done = 0
            for _ in range(steps):
                losses = self.minibatches.losses(self.minibatches.sample(size))
                # Stable-Baselines3's early stop: before a step that would move the policy further
                # from the one that flew the batch (never before the batch's first step).
                if limit is not None and stepped and float(losses["kl_approx"]) > limit:
                    return means or {f"train/{k}": (v / done).item() for k, v in sums.items()}
                total = sum(losses[k] for k in self.loss_keys)
                self.optimizer.zero_grad()
                total.backward()
                norm = self.clip_gradients()
                self.optimizer.step()
                stepped, done = stepped + 1, done + 1
                for key, value in (*((k, losses[k]) for k in self.reported), ("grad_norm", norm)):
                    sums[key] = sums.get(key, 0) + value.detach()
            means = {f"train/{k}": (v / steps).item() for k, v in sums.items()}
        return means

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        """The algorithm's TorchRL loss over ``actor`` and ``critic``, from ``self.cfg.algo``."""
        raise NotImplementedError

    def make_minibatches(self) -> Minibatches | PlainMinibatches:
        """Where :meth:`learn` keeps a batch's frames and scores its minibatches: :class:`Minibatches`."""
        algo = self.cfg.algo
        return Minibatches(self.loss, algo.num_envs * algo.steps_per_batch, self.cfg.device)

    def scale_advantage(self, advantage: torch.Tensor) -> torch.Tensor:
        """The batch's advantages as the loss sees them.

        As GAE gave them here (ClipPPOLoss standardises each minibatch itself); A2C standardises the batch's.
        """
        return advantage

    def clip_gradients(self) -> torch.Tensor:
        """Clip the loss's gradients before the optimizer's step; returns the norm, ``train/grad_norm``.

        The bound is ``algo.max_grad_norm``, on the norm of all of the loss's parameters together.
        """
        limit = self.cfg.algo.max_grad_norm
        return nn.utils.clip_grad_norm_(self.params, math.inf if limit is None else limit)

    def eval_policy(self):
        """What evaluations fly: the actor, or with ``backend=fast`` its episodes on the C++ engine.

        The fast engine flies the same start states by the arithmetic of training, without TorchRL's
        per-step overhead (``tests/test_segments.py`` checks they agree).
        """
        return self.collector.eval_policy() if self.fused else self.actor_module

    def checkpoint_entries(self, agent: int) -> dict[str, Any]:
        """:meth:`OneRun.checkpoint_entries`, with ``eval.rollback_drop``'s best state."""
        entries = super().checkpoint_entries(agent)
        if self.rollback_drop is not None:
            entries["rollback"] = {"state": self.best_state, "returned": self.returned_to_best}
        return entries


class DualClipPPOLoss(ClipPPOLoss):
    """``ClipPPOLoss`` with dual-clip PPO's bound (Ye et al. 2020): the reference twin of ``algo.dual_clip``.

    The log importance ratio is clamped at ``log(dual_clip)`` before ``ClipPPOLoss``'s clipped
    objective, as :func:`~.ppo_fast.clip_ppo_losses` does: a negative advantage's term is then at
    least ``dual_clip x advantage`` (its gradient 0 past the bound), however far the ratio went.
    Written by hand because TorchRL 0.14.1 has no dual clip: ``max_importance_ratio`` caps the
    ratio by lifting the behaviour log-probability, which keeps a rescaled gradient and scales the
    clipped term too. Only ``_log_weight`` is overridden, so the entropy bonus, critic and
    diagnostics are ``ClipPPOLoss``'s (``kl_approx`` from the unclamped log-probabilities).

    Args:
        *args: ``ClipPPOLoss``'s.
        dual_clip: the ratio's bound, > 1.
        **kwargs: ``ClipPPOLoss``'s.
    """

    def __init__(self, *args: Any, dual_clip: float, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.log_dual_clip = math.log(dual_clip)

    def _log_weight(self, tensordict: TensorDictBase, adv_shape: torch.Size) -> tuple:
        log_weight, *rest = super()._log_weight(tensordict, adv_shape)
        return (log_weight.clamp(max=self.log_dual_clip), *rest)


class PPO(OnPolicy):
    """PPO: TorchRL's ``ClipPPOLoss`` (clipped ratio, normalised advantages).

    Args:
        jobs: the one job trained, as for :class:`OnPolicy`.
    """

    diagnostics = ("entropy", "kl_approx", "clip_fraction")

    def make_loss(self, actor: nn.Module, critic: nn.Module) -> LossModule:
        """TorchRL's ``ClipPPOLoss`` over ``actor`` and ``critic``, from ``algo.*``; with ``algo.dual_clip``, :class:`DualClipPPOLoss`."""
        algo = self.cfg.algo
        dual_clip = algo.get("dual_clip")
        loss, bound = (ClipPPOLoss, {}) if dual_clip is None else (DualClipPPOLoss, {"dual_clip": dual_clip})
        return loss(
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
            **bound,
        )

    def make_minibatches(self) -> Minibatches | PlainMinibatches:
        """The fast twin without an entropy bonus on ``backend=fast``; otherwise the reference's.

        The twin, :class:`~.ppo_fast.PlainMinibatches`, holds plain tensors and scores them by
        :func:`~.ppo_fast.clip_ppo_losses`.
        """
        if self.fused and not self.cfg.algo.entropy_coeff:
            return PlainMinibatches(self.cfg, self.loss, self.actor_module, self.critic)
        return super().make_minibatches()


def validate_on_policy(cfg: Mapping[str, Any]) -> None:
    """The rules of :class:`OnPolicy` that relate keys.

    Each key's bounds are its schema's: PPOConf here, A2CConf in a2c.py.
    """
    one_env(cfg)
    frames = cfg.algo.num_envs * cfg.algo.steps_per_batch
    if frames % cfg.algo.minibatch_size:
        raise ConfigError.of(
            "algo.minibatch_size",
            cfg.algo.minibatch_size,
            f"a divisor of algo.num_envs x algo.steps_per_batch = {frames} (the frames of a batch)",
        )


def on_policy(name: str, learner: type[OnPolicy], summary: str) -> Algorithm:
    """The registry's entry of an :class:`OnPolicy` learner: its checks, checkpoint entry and memory."""
    return Algorithm(
        name,
        learner,
        validate_on_policy,
        checkpoint_keys=("critic",),
        summary=summary,
        memory=on_policy_parts,
    )


@dataclass
class OnPolicyConf:
    """``algo.*`` every on-policy algorithm has (the update of ``drone_torchrl.algorithms.ppo.OnPolicy``)."""

    name: Any = schema.free()
    lr: Any = schema.LR.field()
    anneal_lr: Any = schema.ANNEAL_LR.field()
    gamma: Any = schema.GAMMA.field()
    gae_lambda: Any = schema.GAE_LAMBDA.field()
    episodes: Any = schema.EPISODES.field()
    num_envs: Any = schema.NUM_ENVS.field()
    steps_per_batch: Any = schema.STEPS_PER_BATCH.field()
    epochs: Any = schema.EPOCHS.field()
    minibatch_size: Any = schema.MINIBATCH_SIZE.field()
    entropy_coeff: Any = schema.ENTROPY_COEFF.field()
    critic_coeff: Any = schema.CRITIC_COEFF.field()
    reward_scale: Any = schema.REWARD_SCALE.field()
    max_grad_norm: Any = schema.MAX_GRAD_NORM.field()
    adam_eps: Any = schema.ADAM_EPS.field()
    value_hidden_sizes: Any = schema.VALUE_HIDDEN_SIZES.field()


@dataclass
class PPOConf(OnPolicyConf):
    """``algo.*`` of ``algo.name=ppo``: the on-policy keys and the clipping range."""

    clip_epsilon: Any = schema.a_number(low=0, low_open=True, high=1)
    # Stable-Baselines3's target_kl: a batch's epochs stop at the first minibatch whose approximate
    # KL divergence from the policy that flew the batch exceeds 1.5 target_kl (null: never).
    target_kl: Any = schema.a_number(low=0, low_open=True, optional=True, added=None)
    # Dual-clip PPO: the importance ratio bounded by this (> 1), so a minibatch whose ratios overflow
    # cannot throw the policy off (DualClipPPOLoss, and clip_ppo_losses on backend=fast).
    dual_clip: Any = schema.a_number(low=1, low_open=True, optional=True, added=None)


schema.store_plugin("algo", "ppo", PPOConf)
register(on_policy("ppo", PPO, "PPO on TorchRL's collector, GAE and ClipPPOLoss"))
