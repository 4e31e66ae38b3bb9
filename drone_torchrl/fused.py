"""Fused training: many independent REINFORCE agents in one process, stepped as one batch.

One-episode-per-update REINFORCE is sequential within a run, but the runs of a study are
independent. Here every agent keeps what it would have alone (its policy, its Adam, its RNG stream,
its run folder with CSV, TensorBoard and checkpoints in the standard format), while the per-step
work, policy forward and physics, runs once for all agents:

- policies: each agent owns a standard :class:`~drone_torchrl.modules.ThreeNetPolicy` (initialised
  after ``torch.manual_seed(seed)``, exactly like ``drone-train``); their parameters are stacked
  and applied with batched matrix products over a leading agent dim;
- physics: the shared pure functions of :mod:`drone_torchrl.envs.dynamics` on a ``[A, E, 6]`` state.
  The hot loop calls them directly rather than ``DroneEnv.step``: TorchRL's fixed cost per
  ``EnvBase.step`` (about 0.15-0.35 ms here) is larger than the rest of a fused step;
- randomness: each agent draws its start states and its whole episode's action noise from its own
  ``torch.Generator`` once per update (no per-step work that grows with the number of agents), so
  an agent's trajectory does not depend on which other agents share the batch;
- learning: :class:`~drone_torchrl.objectives.ReinforceLoss` with ``agent_dims=1`` (each agent's
  loss is its own episode mean, the total is their sum) and one ``torch.optim.Adam`` per agent, so
  learning rates and discounts can differ per agent.

An agent trained alone with this engine and the same agent inside a batch follow the same
trajectory (``tests/test_fused.py``). The engine draws its noise differently from the TorchRL
rollout engine, so the two engines give different (equally valid) runs for the same seed.
"""

from __future__ import annotations

import math
import sys
import time
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, TanhNormal
from tqdm import tqdm

from drone_torchrl.checkpoint import BEST, CHECKPOINT_DIR, LAST, save_checkpoint
from drone_torchrl.config import env_kwargs, physics_params
from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.evaluation import write_eval_video
from drone_torchrl.metrics import EpisodeCSV, episode_stats
from drone_torchrl.modules.policy import ACTIVATIONS, ThreeNetPolicy
from drone_torchrl.objectives.reinforce import ReinforceLoss, valid_steps
from drone_torchrl.tb_logger import RunLogger, log_update

ENGINE = "fused"
# Settings that may differ between agents of one batch; everything else must be equal.
PER_AGENT_KEYS = ("seed", "algo.lr", "algo.gamma")


def _linears(net: ThreeNetPolicy) -> list[nn.Linear]:
    return [m for m in net.shared if isinstance(m, nn.Linear)] + [net.mean, net.std]


class StackedThreeNet(nn.Module):
    """Applies A :class:`ThreeNetPolicy` nets at once to ``[A, ..., 6]`` observations.

    The parameters stay the agents' own leaves; they are stacked on every call (once per update
    with gradients for the loss, once per update without for the rollout via :meth:`frozen`).
    """

    def __init__(self, nets: list[ThreeNetPolicy], activation: str) -> None:
        super().__init__()
        self.nets = nn.ModuleList(nets)
        self.activation = ACTIVATIONS[activation]()
        self.min_std = nets[0].min_std
        self.n_hidden = len(_linears(nets[0])) - 2

    def stacked(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``[(W^T [A, in, out], b [A, 1, out]), ...]`` for the hidden layers, then mean and std heads."""
        layers = zip(*(_linears(net) for net in self.nets), strict=True)
        return [
            (
                torch.stack([m.weight for m in group]).transpose(1, 2),
                torch.stack([m.bias for m in group]).unsqueeze(1),
            )
            for group in layers
        ]

    def apply_stacked(
        self, layers: list[tuple[torch.Tensor, torch.Tensor]], observation: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        shape = observation.shape
        h = observation.reshape(shape[0], -1, shape[-1])
        for weight, bias in layers[: self.n_hidden]:
            h = self.activation(torch.baddbmm(bias, h, weight))
        (w_mean, b_mean), (w_std, b_std) = layers[self.n_hidden :]
        loc = torch.baddbmm(b_mean, h, w_mean)
        scale = nn.functional.softplus(torch.baddbmm(b_std, h, w_std)) + self.min_std
        out_shape = (*shape[:-1], loc.shape[-1])
        return loc.reshape(out_shape), scale.reshape(out_shape)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.apply_stacked(self.stacked(), observation)


def _stacked_actor(net: StackedThreeNet, distribution: str, max_thrust: float | None) -> ProbabilisticActor:
    """The same distribution head as :func:`~drone_torchrl.modules.make_actor`, over the stacked nets."""
    if distribution == "normal":
        dist_class, dist_kwargs = IndependentNormal, {}
    else:
        dist_class, dist_kwargs = TanhNormal, {"low": 0.0, "high": float(max_thrust), "tanh_loc": False}
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module, in_keys=["loc", "scale"], distribution_class=dist_class, distribution_kwargs=dist_kwargs
    )


class _Sampler:
    """``action = f(loc + scale * noise)``: the actor's distribution, sampled with given noise."""

    def __init__(self, distribution: str, max_thrust: float | None) -> None:
        self.squash = None
        if distribution == "tanh_normal":
            # TorchRL's own tanh + affine transform, so samples match what TanhNormal.log_prob inverts.
            probe = TanhNormal(torch.zeros(2), torch.ones(2), low=0.0, high=float(max_thrust), tanh_loc=False)
            self.squash = probe.transforms[0]

    def __call__(self, loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        pre = loc if noise is None else loc + scale * noise
        return pre if self.squash is None else self.squash(pre)


@dataclass
class Agent:
    """Everything one agent owns; the same things a single ``drone-train`` run owns."""

    cfg: DictConfig
    run_dir: Path
    policy: ThreeNetPolicy
    optimizer: torch.optim.Adam
    generator: torch.Generator
    logger: RunLogger
    csv: EpisodeCSV
    recent_returns: deque
    recent_lengths: deque
    episodes_done: int = 0
    updates_done: int = 0
    wall_clock_before: float = 0.0
    best_eval: float = -math.inf
    next_checkpoint: int = 0
    next_eval: int | None = None
    final: dict[str, float] = field(default_factory=dict)

    def standalone_actor(self) -> ProbabilisticActor:
        """This agent's policy as the standard actor (for evaluation, videos and checkpoints)."""
        from drone_torchrl.train import build_actor

        actor = build_actor(self.cfg)
        actor.module[0].module.load_state_dict(self.policy.state_dict())
        return actor

    def checkpoint_state(self, wall_clock: float) -> dict[str, Any]:
        return {
            "engine": ENGINE,
            "actor": self.standalone_actor().state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "episodes_done": self.episodes_done,
            "updates_done": self.updates_done,
            "wall_clock_s": wall_clock,
            "best_eval_return": self.best_eval,
            "recent_returns": list(self.recent_returns),
            "recent_lengths": list(self.recent_lengths),
            "agent_rng": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "env_rng": None,
            "config": OmegaConf.to_container(self.cfg, resolve=True),
        }


def group_key(cfg: DictConfig) -> str:
    """Jobs whose configs agree on everything but the per-agent keys can share one batch."""
    container = OmegaConf.to_container(cfg, resolve=True)
    for dotted in (*PER_AGENT_KEYS, "resume", "progress"):
        node = container
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.get(part, {})
        node.pop(leaf, None)
    container.pop("hydra", None)
    return OmegaConf.to_yaml(OmegaConf.create(container))


class FusedTrainer:
    """Train the agents of ``jobs`` (``[(cfg, run_dir), ...]``, one group, see :func:`group_key`)."""

    def __init__(self, jobs: list[tuple[DictConfig, Path]], checkpoints: list[dict | None]) -> None:
        base = jobs[0][0]
        self.base = base
        self.params = physics_params(env_kwargs(base))
        self.max_steps = base.env.max_steps
        self.reset_mode = base.env.reset_mode
        self.episodes_per_update = base.algo.episodes_per_update
        self.device = torch.device(base.device)
        self.sampler = _Sampler(base.model.distribution, base.env.max_thrust)
        # compile=true fuses the step's ~40 small kernels (policy, sampling, physics) into a few;
        # it costs a one-off compilation per batch shape and changes float rounding slightly.
        self._step = self._compiled_step if base.compile else self._policy_and_physics
        self._compiled = torch.compile(self._policy_and_physics) if base.compile else None
        self.agents = [
            self._make_agent(cfg, Path(run_dir), ckpt)
            for (cfg, run_dir), ckpt in zip(jobs, checkpoints, strict=True)
        ]
        self.start = time.perf_counter()
        progress = base.progress
        self.bar = tqdm(
            total=sum(a.cfg.algo.episodes for a in self.agents),
            initial=sum(a.episodes_done for a in self.agents),
            disable=not (sys.stderr.isatty() if progress == "auto" else bool(progress)),
            unit="ep",
            dynamic_ncols=True,
        )

    # ------------------------------------------------------------------ set-up
    def _make_agent(self, cfg: DictConfig, run_dir: Path, ckpt: dict | None) -> Agent:
        torch.manual_seed(cfg.seed)  # the same initial weights as a drone-train run of this seed
        policy = ThreeNetPolicy(list(cfg.model.hidden_sizes), cfg.model.activation, cfg.model.min_std).to(
            self.device
        )
        optimizer = torch.optim.Adam(policy.parameters(), lr=cfg.algo.lr, eps=cfg.algo.adam_eps)
        generator = torch.Generator(device=self.device)
        generator.manual_seed(cfg.seed)
        window = cfg.metrics.running_mean_window
        (run_dir / CHECKPOINT_DIR).mkdir(parents=True, exist_ok=True)
        OmegaConf.save(cfg, run_dir / "config.yaml")
        done = ckpt["episodes_done"] if ckpt else 0
        agent = Agent(
            cfg=cfg,
            run_dir=run_dir,
            policy=policy,
            optimizer=optimizer,
            generator=generator,
            logger=RunLogger(cfg.logger.exp_name, run_dir, purge_step=done if ckpt else None),
            csv=EpisodeCSV(run_dir / "episodes.csv", keep_episodes=done),
            recent_returns=deque(maxlen=window),
            recent_lengths=deque(maxlen=window),
        )
        if ckpt is not None:
            policy_state = {k.removeprefix("module.0.module."): v for k, v in ckpt["actor"].items()}
            policy.load_state_dict(policy_state)
            optimizer.load_state_dict(ckpt["optimizer"])
            generator.set_state(ckpt["agent_rng"])
            agent.episodes_done, agent.updates_done = done, ckpt["updates_done"]
            agent.wall_clock_before, agent.best_eval = ckpt["wall_clock_s"], ckpt["best_eval_return"]
            agent.recent_returns.extend(ckpt["recent_returns"])
            agent.recent_lengths.extend(ckpt["recent_lengths"])
        agent.next_checkpoint = agent.episodes_done + cfg.checkpoint.every_episodes
        if cfg.eval.every_episodes:
            agent.next_eval = agent.episodes_done + cfg.eval.every_episodes
        return agent

    # ------------------------------------------------------------------ rollout
    def _compiled_step(self, *args) -> tuple[torch.Tensor, ...]:
        try:
            return self._compiled(*args)
        except Exception as err:  # noqa: BLE001  (no compiler, unsupported platform, ...)
            warnings.warn(f"compile=true failed ({type(err).__name__}: {err}); running eager", stacklevel=2)
            self._step = self._policy_and_physics
            return self._step(*args)

    def _policy_and_physics(
        self, net: StackedThreeNet, layers: list, state: torch.Tensor, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, ...]:
        """One step of every agent's every episode: ``(action, next_state, reward, cause)``."""
        loc, scale = net.apply_stacked(layers, state)
        action = self.sampler(loc, scale, noise)
        return (action, *dynamics.step(state, action, self.params))

    @torch.no_grad()
    def rollout(self, net: StackedThreeNet, start: torch.Tensor, noise: torch.Tensor | None) -> TensorDict:
        """Fly ``start`` (``[A, E, 6]``) until every episode has ended; ``noise`` ``[T, A, E, 2]`` or None
        (deterministic). Returns a ``[A, E, T]`` tensordict in the layout of ``EnvBase.rollout``."""
        layers = net.stacked()
        state = start
        observations, actions, rewards, causes = [], [], [], []
        alive = torch.ones(start.shape[:-1], dtype=torch.bool, device=start.device)
        for t in range(self.max_steps):
            observations.append(state)
            action, state, reward, cause = self._step(net, layers, state, None if noise is None else noise[t])
            actions.append(action)
            rewards.append(reward)
            causes.append(cause)
            alive = alive & (cause == int(TerminationCause.NONE))
            if not bool(alive.any()):
                break
        n = len(rewards)
        cause = torch.stack(causes, -1)
        terminated = cause != int(TerminationCause.NONE)
        truncated = torch.zeros_like(terminated)
        if n == self.max_steps:
            truncated[..., -1] = ~terminated[..., -1]
        obs = torch.stack(observations, -2)
        next_obs = torch.cat([obs[..., 1:, :], state.unsqueeze(-2)], -2)
        steps = torch.arange(n, device=start.device).expand(*start.shape[:-1], n)
        return TensorDict(
            {
                "observation": obs,
                "action": torch.stack(actions, -2),
                "step_count": steps.unsqueeze(-1),
                "next": {
                    "observation": next_obs,
                    "reward": torch.stack(rewards, -1).unsqueeze(-1),
                    "terminated": terminated.unsqueeze(-1),
                    "truncated": truncated.unsqueeze(-1),
                    "done": (terminated | truncated).unsqueeze(-1),
                    "termination_cause": cause.unsqueeze(-1),
                },
            },
            batch_size=[*start.shape[:-1], n],
        )

    # ------------------------------------------------------------------ training
    def train(self) -> list[dict[str, float]]:
        """Run every agent to its own ``algo.episodes``; returns each agent's final metrics."""
        while True:
            active = [a for a in self.agents if a.episodes_done < a.cfg.algo.episodes]
            if not active:
                break
            self.update(active)
        self.bar.close()
        return [a.final for a in self.agents]

    def update(self, active: list[Agent]) -> int:
        """One REINFORCE update of every agent in ``active``; returns the env steps they took."""
        episodes = self.episodes_per_update
        net = StackedThreeNet([a.policy for a in active], self.base.model.activation)
        start = torch.stack(
            [dynamics.initial_state((episodes,), self.reset_mode, a.generator, self.device) for a in active]
        )
        noise = torch.stack(
            [
                torch.randn((self.max_steps, episodes, 2), generator=a.generator, device=self.device)
                for a in active
            ],
            dim=1,
        )
        batch = self.rollout(net, start, noise)
        gamma = torch.tensor([a.cfg.algo.gamma for a in active], device=self.device)
        loss_module = ReinforceLoss(
            _stacked_actor(net, self.base.model.distribution, self.base.env.max_thrust),
            gamma=gamma,
            discount_weight=self.base.algo.discount_weight,
            normalize_returns=self.base.algo.normalize_returns,
            baseline=self.base.algo.baseline,
            agent_dims=1,
        )
        losses = loss_module(batch)
        for agent in active:
            agent.optimizer.zero_grad(set_to_none=True)
        losses["loss_reinforce"].backward()
        max_norm = self.base.algo.max_grad_norm
        grad_norms = [
            float(
                torch.nn.utils.clip_grad_norm_(
                    a.policy.parameters(), math.inf if max_norm is None else max_norm
                )
            )
            for a in active
        ]
        for agent in active:
            agent.optimizer.step()
        self._record(active, batch, losses, grad_norms)
        return int(valid_steps(batch.get(("next", "done"))).sum())

    def _record(
        self, active: list[Agent], batch: TensorDict, losses: TensorDict, grad_norms: list[float]
    ) -> None:
        stats = {k: v.tolist() for k, v in episode_stats(batch.reshape(-1, batch.shape[-1])).items()}
        per_agent = self.episodes_per_update
        scale = self._policy_std(batch)
        loss_values = losses["loss_per_agent"].tolist()
        now = time.perf_counter() - self.start
        for i, agent in enumerate(active):
            agent.updates_done += 1
            wall = round(agent.wall_clock_before + now, 3)
            rows = []
            for j in range(i * per_agent, (i + 1) * per_agent):
                row = {name: stats[name][j] for name in stats}
                row["termination_cause"] = TerminationCause(row["termination_cause"]).name
                row.update(episode=agent.episodes_done, update=agent.updates_done, wall_clock_s=wall)
                rows.append(row)
                agent.recent_returns.append(row["return"])
                agent.recent_lengths.append(row["length"])
                agent.episodes_done += 1
            agent.csv.write(rows)
            if agent.updates_done % agent.cfg.logger.every_updates == 0:
                train_metrics = {
                    "train/loss": loss_values[i],
                    "train/grad_norm": grad_norms[i],
                    "policy/std_mean": scale[i],
                    "train/running_mean_return": float(np.mean(agent.recent_returns)),
                    "train/running_mean_length": float(np.mean(agent.recent_lengths)),
                }
                log_update(agent.logger, rows, train_metrics, step=agent.episodes_done)
        self.bar.update(len(active) * per_agent)
        returns = [float(np.mean(a.recent_returns)) for a in active]
        window = active[0].cfg.metrics.running_mean_window
        if len(active) == 1:
            lengths = float(np.mean(active[0].recent_lengths))
            self.bar.set_postfix_str(f"return({window})={returns[0]:.0f} length={lengths:.0f}", refresh=False)
        else:
            self.bar.set_postfix_str(
                f"{len(active)} agents, return({window}) mean={np.mean(returns):.0f} best={max(returns):.0f}",
                refresh=False,
            )
        # Agents due for an evaluation are flown together, in one batched rollout.
        due = [
            a
            for a in active
            if a.episodes_done >= a.cfg.algo.episodes
            or (a.next_eval is not None and a.episodes_done >= a.next_eval)
        ]
        if due:
            for agent, result in zip(due, self.evaluate(due), strict=True):
                self._after_eval(agent, result)
        for agent in active:
            self._checkpoint_or_finish(agent)

    @staticmethod
    def _policy_std(batch: TensorDict) -> list[float]:
        """Mean policy std per agent over the update's valid steps (the loss wrote ``"scale"``)."""
        scale = batch.get("scale").detach()
        valid = valid_steps(batch.get(("next", "done")))
        return ((scale * valid).sum((1, 2, 3)) / (valid.sum((1, 2, 3)) * scale.shape[-1])).tolist()

    # ------------------------------------------------------------------ evaluation, checkpoints
    def _wall(self, agent: Agent) -> float:
        return agent.wall_clock_before + time.perf_counter() - self.start

    def evaluate(self, agents: list[Agent]) -> list[dict[str, float]]:
        """Deterministic mean return, length and time in zone of each agent on ``eval.episodes`` episodes seeded with ``eval.seed``.

        Same start states as :func:`drone_torchrl.evaluation.evaluate` (a ``DroneEnv`` seeded with
        ``eval.seed`` draws them with the same generator calls), flown for all agents at once.
        """
        cfg = agents[0].cfg
        generator = torch.Generator(device=self.device)
        generator.manual_seed(cfg.eval.seed)
        start = dynamics.initial_state((cfg.eval.episodes,), self.reset_mode, generator, self.device)
        net = StackedThreeNet([a.policy for a in agents], self.base.model.activation)
        batch = self.rollout(net, start.expand(len(agents), *start.shape).clone(), None)
        stats = episode_stats(batch.reshape(-1, batch.shape[-1]))
        means = {
            k: stats[k].reshape(len(agents), -1).float().mean(-1).tolist()
            for k in ("return", "length", "time_in_zone")
        }
        return [{k: v[i] for k, v in means.items()} for i in range(len(agents))]

    def _after_eval(self, agent: Agent, result: dict[str, float]) -> None:
        cfg = agent.cfg
        agent.logger.log_metrics({f"eval/{k}": v for k, v in result.items()}, step=agent.episodes_done)
        mean_return = result["return"]
        if cfg.checkpoint.keep_best and mean_return > agent.best_eval:
            agent.best_eval = mean_return
            save_checkpoint(agent.checkpoint_state(self._wall(agent)), agent.run_dir / CHECKPOINT_DIR / BEST)
        if cfg.eval.video:
            write_eval_video(agent.standalone_actor(), cfg, agent.run_dir, agent.episodes_done, agent.logger)
        if agent.next_eval is not None:
            agent.next_eval += cfg.eval.every_episodes
        if agent.episodes_done >= cfg.algo.episodes:
            agent.final = {
                "final_return": float(np.mean(agent.recent_returns)),
                "final_length": float(np.mean(agent.recent_lengths)),
                "eval_return": mean_return,
                "wall_clock_s": self._wall(agent),
            }

    def _checkpoint_or_finish(self, agent: Agent) -> None:
        cfg = agent.cfg
        finished = agent.episodes_done >= cfg.algo.episodes
        if finished:
            agent.csv.flush()
            save_checkpoint(
                {**agent.checkpoint_state(self._wall(agent)), "final": agent.final},
                agent.run_dir / CHECKPOINT_DIR / LAST,
            )
            agent.logger.log_final_hparams(cfg, agent.final)
            agent.logger.experiment.close()
            agent.csv.close()
        elif agent.episodes_done >= agent.next_checkpoint:
            agent.csv.flush()
            save_checkpoint(agent.checkpoint_state(self._wall(agent)), agent.run_dir / CHECKPOINT_DIR / LAST)
            agent.next_checkpoint += cfg.checkpoint.every_episodes

    def close(self) -> None:
        self.bar.close()
        for agent in self.agents:
            if not agent.final:
                agent.csv.close()
                agent.logger.experiment.close()


def train_fused(jobs: list[tuple[DictConfig, Path]]) -> list[float | None]:
    """Train every job (``(validated config, run folder)``), fusing compatible ones into batches.

    Each job continues from its folder's checkpoint if there is one (finished jobs return at once).
    A job whose config or checkpoint is bad is recorded as failed (``<run>/FAILED.txt``) and left
    out; the others go on. Returns each job's final running-mean return (None if it failed).
    """
    from drone_torchrl.checkpoint import load_checkpoint
    from drone_torchrl.config import ConfigError, validate
    from drone_torchrl.sweep import clear_failure, record_failure

    results: list[float | None] = [None] * len(jobs)
    groups: dict[str, list[tuple[int, DictConfig, Path, dict | None]]] = {}
    for i, (cfg, run_dir) in enumerate(jobs):
        run_dir = Path(run_dir)
        try:
            validate(cfg)
            last = run_dir / CHECKPOINT_DIR / LAST
            ckpt = load_checkpoint(last) if last.is_file() else None
            if ckpt is not None and ckpt.get("engine") != ENGINE:
                raise ConfigError(
                    f"engine={ENGINE!r} cannot continue {last}: it was written by engine={ckpt.get('engine')!r}"
                )
        except Exception as err:  # noqa: BLE001  (recorded per job; the others go on)
            print(f"{run_dir}: job failed: {record_failure(run_dir, err)}")
            continue
        clear_failure(run_dir)
        if ckpt is not None and "final" in ckpt and ckpt["episodes_done"] >= cfg.algo.episodes:
            print(f"{run_dir}: already finished ({ckpt['episodes_done']} episodes); nothing to do")
            results[i] = ckpt["final"]["final_return"]
            continue
        groups.setdefault(group_key(cfg), []).append((i, cfg, run_dir, ckpt))
    for members in groups.values():
        torch.set_num_threads(members[0][1].threads)
        trainer = FusedTrainer([(cfg, run_dir) for _, cfg, run_dir, _ in members], [c for *_, c in members])
        try:
            finals = trainer.train()
        except Exception as err:
            for _, _, run_dir, _ in members:
                record_failure(run_dir, err)
            trainer.close()
            raise
        for (i, _, run_dir, _), final in zip(members, finals, strict=True):
            results[i] = final["final_return"]
            print(
                f"{run_dir}: {final['final_return']:.1f} running-mean return, {final['final_length']:.1f} length, "
                f"eval {final['eval_return']:.1f}, {final['wall_clock_s']:.0f} s"
            )
    return results
