"""The training loop: collect -> loss -> optimizer -> record, for one agent or a population.

The loop is the same for both engines (``engine=torchrl``: the TorchRL reference collector;
``engine=fused``: the vectorised one, see :mod:`.collectors`). Each update:

1. the collector flies ``algo.episodes_per_update`` episodes for every active agent:
   a ``[A, E, T]`` batch;
2. :class:`~drone_torchrl.objectives.ReinforceLoss` with ``agent_dims=1`` scores the stored actions;
   each agent's loss is the mean over its own episodes and the total is their sum, so each agent's
   gradient is exactly its own;
3. each agent clips its gradient norm and takes its Adam step;
4. each agent's :class:`~.run.RunRecord` books the finished episodes and metrics; agents due for an
   evaluation are flown together by the evaluator; checkpoints are written when due.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from drone_torchrl.config import ConfigError, env_kwargs
from drone_torchrl.episodes import EPISODE_KEYS, episode_stats
from drone_torchrl.evaluation import evaluate
from drone_torchrl.objectives.reinforce import ReinforceLoss, valid_steps
from drone_torchrl.training.collectors import make_collector
from drone_torchrl.training.jobs import Job, group_key, prepare, record_failure
from drone_torchrl.training.memory import keep_freed_memory
from drone_torchrl.training.population import Population
from drone_torchrl.training.run import FAILED_FILE, Progress, RunRecord, TrainingDiverged


@dataclass
class Outcome:
    """How one job ended: its final metrics, or the error that stopped it."""

    run_dir: Path
    final: dict[str, float] | None = None
    error: BaseException | None = None

    @property
    def final_return(self) -> float | None:
        return None if self.final is None else self.final["final_return"]


def make_loss(cfg: DictConfig, actor, gamma: torch.Tensor) -> ReinforceLoss:
    """The config's REINFORCE loss over ``[A, ...]`` batches, one discount per agent."""
    return ReinforceLoss(
        actor,
        gamma=gamma,
        discount_weight=cfg.algo.discount_weight,
        normalize_returns=cfg.algo.normalize_returns,
        baseline=cfg.algo.baseline,
        agent_dims=1,
        log_prob_reduction=cfg.algo.log_prob_reduction,
    )


# What _finite_checks tests, in its row order (then the weights after the step).
CHECKS = ("actions", "loss", "gradients", "weights")


def _finite_checks(batch: TensorDictBase, loss: torch.Tensor, grad_norms: torch.Tensor) -> torch.Tensor:
    """``[3, A]`` bool: each agent's actions (on its valid steps), loss and gradient are finite."""
    valid = valid_steps(batch.get(("next", "done")))
    bad_action = (~batch.get("action").isfinite() & valid).flatten(1).any(1)
    return torch.stack([~bad_action, loss.isfinite(), grad_norms.isfinite()])


def _policy_std(batch: TensorDictBase) -> torch.Tensor:
    """Mean policy std per agent over the update's valid steps (the loss wrote ``"scale"``)."""
    scale = batch.get("scale").detach()
    valid = valid_steps(batch.get(("next", "done")))
    dims = tuple(range(1, scale.ndim))
    return (scale * valid).sum(dims) / (valid.sum(dims) * scale.shape[-1])


def _to_host(tensors: dict[str, torch.Tensor]) -> dict[str, list]:
    """``tensor.tolist()`` of each tensor (of at least one dim), all copied to the host at once:
    in float64, which holds every float32, int below 2**53 and bool exactly; ints and bools come
    back as such."""
    flat = torch.cat([t.detach().reshape(-1).to(torch.float64) for t in tensors.values()]).tolist()
    out: dict[str, list] = {}
    start = 0
    for key, tensor in tensors.items():
        values = flat[start : start + tensor.numel()]
        start += tensor.numel()
        if tensor.dtype == torch.bool:
            values = [bool(v) for v in values]
        elif not tensor.is_floating_point():
            values = [int(v) for v in values]
        for size in reversed(tensor.shape[1:]):  # regroup the trailing dims, innermost first
            values = [values[i : i + size] for i in range(0, len(values), size)]
        out[key] = values
    return out


class Trainer:
    """The jobs of one group (see :func:`~.jobs.group_key`) trained together: one agent or a population."""

    def __init__(self, jobs: Sequence[Job]) -> None:
        self.cfg = cfg = jobs[0].cfg
        torch.set_num_threads(cfg.threads)
        if torch.device(cfg.device).type == "cpu":
            keep_freed_memory()
        self.population = Population([job.cfg for job in jobs])
        self.collector = make_collector(cfg, self.population)
        for i, job in enumerate(jobs):
            if job.checkpoint is not None:
                self.population.load(i, job.checkpoint)
                self.collector.set_rng_state(i, job.checkpoint["rng"], job.checkpoint["episodes_done"])
        self.runs = [
            RunRecord(job.cfg, job.run_dir, cfg.engine, job.checkpoint, job.parent_dir) for job in jobs
        ]
        self.progress = Progress(self.runs, cfg.progress)
        self._loss: ReinforceLoss | None = None
        self._loss_agents: list[int] = []

    def train(self) -> list[dict[str, float]]:
        """Run every agent to its own ``algo.episodes``; returns each one's final metrics."""
        try:
            # Killed after its last checkpoint but before the final evaluation: finish it now.
            if at_budget := [i for i, run in enumerate(self.runs) if run.finished and run.final is None]:
                self.evaluate(at_budget)
                for i in at_budget:
                    self.runs[i].save(self.learner_state(i))
            while active := [i for i, run in enumerate(self.runs) if not (run.finished or run.failed)]:
                self.update(active)
        finally:
            self.close()
        return [run.final for run in self.runs]

    def update(self, active: list[int]) -> int:
        """One update of the ``active`` agents; returns the env steps they took."""
        population, runs = self.population, self.runs
        batch = self.collector.collect(active, [runs[i].updates_done for i in active])
        losses = self.loss_module(active)(batch)
        population.zero_grad()
        losses["loss_reinforce"].backward()
        grad_norms = population.clip(active)
        # An agent whose loss, gradient or actions are not finite does not step, and stops.
        checks = _finite_checks(batch, losses["loss_per_agent"], grad_norms)
        population.step(active, checks.all(0))
        checks = torch.cat([checks, population.finite(active).unsqueeze(0)])

        # Episodes and metrics of all agents come to the host together: one copy (one sync) per update.
        stats = {k: v for k, v in episode_stats(batch).items() if k in EPISODE_KEYS}
        metrics = {"loss": losses["loss_per_agent"], "norm": grad_norms, "std": _policy_std(batch)}
        host = _to_host({**stats, **metrics, "checks": checks})
        episodes = {k: host[k] for k in stats}
        loss, norm, std, checks = host["loss"], host["norm"], host["std"], host["checks"]
        for k, i in enumerate(active):
            failed = [what for what, ok in zip(CHECKS, (c[k] for c in checks), strict=True) if not ok]
            if failed:
                runs[i].fail(
                    f"training diverged at episode {runs[i].episodes_done}: non-finite {' and '.join(failed)}; "
                    "lower algo.lr (or set algo.max_grad_norm)"
                )
                continue
            metrics = {"train/loss": loss[k], "train/grad_norm": norm[k], "policy/std_mean": std[k]}
            runs[i].record({key: values[k] for key, values in episodes.items()}, metrics)
        active = [i for i in active if not runs[i].failed]
        if active:
            self.progress.update(len(active) * batch.shape[1], [runs[i] for i in active])

        due = [i for i in active if runs[i].eval_due]
        if due:
            self.evaluate(due)
        for i in active:
            if runs[i].checkpoint_due:
                runs[i].save(self.learner_state(i))
        return sum(sum(lengths) for lengths in episodes["length"])

    def loss_module(self, active: list[int]) -> ReinforceLoss:
        """The loss over the active agents' actor (rebuilt only when the set of agents changes)."""
        actor = self.collector.actor(active)
        if self._loss is None or self._loss.actor_network is not actor or self._loss_agents != active:
            self._loss = make_loss(self.cfg, actor, self.population.gamma[active])
            self._loss_agents = list(active)
        return self._loss

    def evaluate(self, agents: list[int]) -> None:
        """Fly the agents' deterministic policies on the evaluation seeds, all at once, and book it."""
        cfg = self.cfg
        stats, _ = evaluate(
            self.collector.eval_policy(agents),
            env_kwargs(cfg),
            cfg.eval.episodes,
            cfg.eval.seed,
            cfg.device,
            agents=len(agents),
        )
        means = {k: stats[k].float().mean(-1).tolist() for k in ("return", "length", "time_in_zone")}
        for k, i in enumerate(agents):
            self.runs[i].record_eval(
                {name: values[k] for name, values in means.items()},
                lambda i=i: self.learner_state(i),
                lambda i=i: self.population.actor(i),
            )

    def learner_state(self, agent: int) -> dict:
        """The agent's checkpoint entries that the run record does not own: policy, optimizer, RNG."""
        return {**self.population.state(agent), "rng": self.collector.rng_state(agent)}

    def close(self) -> None:
        self.progress.close()
        self.collector.close()
        for run in self.runs:
            run.close()


def train_jobs(jobs: Sequence[Job]) -> list[Outcome]:
    """Train prepared jobs (:func:`~.jobs.prepare`), those that can share a population together.

    Finished jobs return at once; a group whose training raises is recorded as failed
    (``<run>/FAILED.txt``) and the other groups go on.
    """
    outcomes = [Outcome(job.run_dir) for job in jobs]
    groups: dict[str, list[int]] = {}
    for i, job in enumerate(jobs):
        if job.already_finished:
            print(
                f"{job.run_dir}: already finished ({job.checkpoint['episodes_done']} episodes); nothing to do"
            )
            outcomes[i].final = job.checkpoint["final"]
            (job.run_dir / FAILED_FILE).unlink(missing_ok=True)  # left by a refused re-run
        else:
            groups.setdefault(group_key(job.cfg), []).append(i)
    for members in groups.values():
        try:
            if jobs[members[0]].cfg.algo.name == "ppo":
                _train_ppo(jobs, members, outcomes)
                continue
            trainer = Trainer([jobs[i] for i in members])
            finals = trainer.train()
        except Exception as err:  # noqa: BLE001  (recorded per job; the other groups go on)
            for i in members:
                record_failure(jobs[i].run_dir, err)
                outcomes[i].error = err
            continue
        for i, final in zip(members, finals, strict=True):
            if final is None:  # the agent diverged (its run record wrote FAILED.txt)
                outcomes[i].error = TrainingDiverged(trainer.runs[members.index(i)].failure)
                if len(jobs) > 1:
                    print(f"{jobs[i].run_dir}: failed: {outcomes[i].error}")
                continue
            outcomes[i].final = final
            _report(jobs[i], final)
    return outcomes


def _report(job: Job, final: dict[str, float]) -> None:
    cfg = job.cfg
    print(
        f"{job.run_dir}: {cfg.algo.episodes} episodes, running-mean({cfg.metrics.running_mean_window}) "
        f"return {final['final_return']:.1f}, length {final['final_length']:.1f}, "
        f"eval return {final['eval_return']:.1f}, {final['wall_clock_s']:.0f} s"
    )


def _train_ppo(jobs: Sequence[Job], members: list[int], outcomes: list[Outcome]) -> None:
    """PPO jobs train one after another (each one is a batch of drones already)."""
    from drone_torchrl.training.ppo import PPOTrainer

    for i in members:
        trainer = PPOTrainer(jobs[i])
        final = trainer.train()
        if final is None:
            outcomes[i].error = TrainingDiverged(trainer.run.failure)
        else:
            outcomes[i].final = final
            _report(jobs[i], final)


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> float:
    """Train one run; returns its final running-mean return (the metric sweepers optimise).

    ``run_dir`` defaults to the Hydra job's output folder; with ``resume`` of a run's last
    checkpoint, that run's folder. Raises the error that stopped it (a :class:`ConfigError` for a
    bad config, with a one-line message).
    """
    (outcome,) = train_jobs([prepare(cfg, run_dir)])
    if outcome.error is not None:
        raise outcome.error
    if outcome.final is None:
        raise ConfigError(f"{outcome.run_dir}: training ended without final metrics")
    return outcome.final_return
