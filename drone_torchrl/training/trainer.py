"""The training loop, the same for one agent or a population and for both REINFORCE engines.

Each call of the update (:mod:`.update`) runs ``k`` updates of every active agent and hands back
their metrics and finished episodes; the loop copies them to the host at once (one sync per call)
and books them, update by update, in each agent's :class:`~.run.RunRecord`. ``k`` is the number of
updates until the next evaluation, checkpoint or end of budget of any agent (at most
``updates_per_call``), so evaluations and checkpoints fall exactly where a one-update loop would
put them. Agents due for an evaluation are flown together by the evaluator.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from drone_torchrl.config import ConfigError, env_kwargs
from drone_torchrl.evaluation import evaluate
from drone_torchrl.training.collectors import make_collector
from drone_torchrl.training.jobs import Job, group_key, prepare, record_failure
from drone_torchrl.training.memory import keep_freed_memory
from drone_torchrl.training.population import Population
from drone_torchrl.training.run import FAILED_FILE, Progress, RunRecord, TrainingDiverged
from drone_torchrl.training.update import CHECKS, ReinforceUpdate


@dataclass
class Outcome:
    """How one job ended: its final metrics, or the error that stopped it."""

    run_dir: Path
    final: dict[str, float] | None = None
    error: BaseException | None = None

    @property
    def final_return(self) -> float | None:
        return None if self.final is None else self.final["final_return"]


def _to_host(tensors: dict[str, torch.Tensor]) -> dict[str, list]:
    """``tensor.tolist()`` of each tensor, all copied to the host at once (one sync): in float64,
    which holds every float32, int below 2**53 and bool exactly; ints and bools come back as such."""
    flat = torch.cat([t.detach().reshape(-1).to(torch.float64) for t in tensors.values()]).cpu().numpy()
    out: dict[str, list] = {}
    start = 0
    for key, tensor in tensors.items():
        values = flat[start : start + tensor.numel()].reshape(tensor.shape)
        start += tensor.numel()
        if tensor.dtype == torch.bool:
            values = values.astype(bool)
        elif not tensor.is_floating_point():
            values = values.astype(np.int64)
        out[key] = values.tolist()
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
        self.update = ReinforceUpdate(cfg, self.population, self.collector)
        self.runs = [
            RunRecord(job.cfg, job.run_dir, cfg.engine, job.checkpoint, job.parent_dir) for job in jobs
        ]
        self.progress = Progress(self.runs, cfg.progress)
        self.updates_per_call = int(cfg.updates_per_call)
        self.episodes_per_update = int(cfg.algo.episodes_per_update)

    def train(self) -> list[dict[str, float]]:
        """Run every agent to its own ``algo.episodes``; returns each one's final metrics."""
        try:
            # Killed after its last checkpoint but before the final evaluation: finish it now.
            if at_budget := [i for i, run in enumerate(self.runs) if run.finished and run.final is None]:
                self.evaluate(at_budget)
                for i in at_budget:
                    self.runs[i].save(self.learner_state(i))
            while active := [i for i, run in enumerate(self.runs) if not (run.finished or run.failed)]:
                self.step(active)
        finally:
            self.close()
        return [run.final for run in self.runs]

    def step(self, active: list[int], k: int | None = None) -> int:
        """``k`` updates of the ``active`` agents (default: as many as nothing falls due in, at most
        ``updates_per_call``), booked; then the evaluations and checkpoints that are due. Returns
        the env steps the agents took."""
        runs = self.runs
        if k is None:
            k = min(
                self.updates_per_call, *(runs[i].updates_until_due(self.episodes_per_update) for i in active)
            )
        mask = torch.zeros(len(runs), dtype=torch.bool, device=self.population.state.device)
        mask[active] = True
        _, out = self.update(self.population.state, k, mask)
        host = _to_host({**out.metrics, **out.episodes})  # one copy (one sync) per call
        trained = host.pop("active")
        checks = host.pop("checks")
        episodes = {key: host.pop(key) for key in out.episodes}
        steps = 0
        for j in range(k):
            booked = []
            for i in active:
                if not trained[j][i]:
                    continue
                failed = [what for what, ok in zip(CHECKS, checks[j][i], strict=True) if not ok]
                if failed:
                    runs[i].fail(
                        f"training diverged at episode {runs[i].episodes_done}: non-finite "
                        f"{' and '.join(failed)}; lower algo.lr (or set algo.max_grad_norm)"
                    )
                    continue
                runs[i].record(
                    {key: values[j][i] for key, values in episodes.items()},
                    {key: values[j][i] for key, values in host.items()},
                )
                steps += sum(episodes["length"][j][i])
                booked.append(runs[i])
            if booked:
                self.progress.update(len(booked) * self.episodes_per_update, booked)
        active = [i for i in active if not runs[i].failed]
        if due := [i for i in active if runs[i].eval_due]:
            self.evaluate(due)
        for i in active:
            if runs[i].checkpoint_due:
                runs[i].save(self.learner_state(i))
        return steps

    def evaluate(self, agents: list[int]) -> None:
        """Fly the agents' deterministic policies on the evaluation seeds, all at once, and book it."""
        cfg = self.cfg
        stats, _ = evaluate(
            self.collector.eval_policy(),
            env_kwargs(cfg),
            cfg.eval.episodes,
            cfg.eval.seed,
            cfg.device,
            agents=len(self.runs),
        )
        means = {k: stats[k].float().mean(-1).tolist() for k in ("return", "length", "time_in_zone")}
        for i in agents:
            self.runs[i].record_eval(
                {name: values[i] for name, values in means.items()},
                lambda i=i: self.learner_state(i),
                lambda i=i: self.population.actor(i),
            )

    def learner_state(self, agent: int) -> dict:
        """The agent's checkpoint entries that the run record does not own: policy, optimizer, RNG."""
        return {**self.population.checkpoint_entries(agent), "rng": self.collector.rng_state(agent)}

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
