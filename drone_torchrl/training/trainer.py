"""The one training loop, every algorithm's, and the books its runs keep.

A learner (an algorithm's :class:`~drone_torchrl.registry.Learner`, see :mod:`drone_torchrl.algorithms`)
updates its agents behind one contract, ``update(state, k, active) -> (state, UpdateOutput)`` (see
:class:`~drone_torchrl.registry.UpdateOutput`): ``k`` updates of every active agent, their metrics and finished episodes handed back at once. The loop copies them to the
host in one go (one sync per call) and books them, update by update, in each agent's book of its
record (:class:`~.run.Record`: a :class:`~.run.RunRecord` per job folder, or one
:class:`~.population_record.PopulationRecord`; a single run is a population of one, with the same
hooks); an agent whose checks fail stops (a run with ``FAILED.txt``). ``k`` is the number
of updates until the next evaluation, checkpoint or end of budget of any agent (at most
:data:`MAX_UPDATES_PER_CALL`; 1 for a learner whose updates end a varying number of episodes), so
evaluations and checkpoints fall exactly where a one-update loop would put them. Agents due for an
evaluation are flown together by the evaluator, then shown to the learner's ``after_evaluation``
(PPO's and A2C's ``eval.rollback_drop``). A run killed between its last checkpoint and its
final evaluation is finished on resume.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import compress
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from drone_torchrl.config import ConfigError, check_memory, env_kwargs, per_agent_keys
from drone_torchrl.episodes import RUNNING_MEAN_WINDOW
from drone_torchrl.evaluation import evaluate, reference_optimum
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError, load_checkpoint
from drone_torchrl.io.storage import StorageError
from drone_torchrl.io.streams import about, console
from drone_torchrl.kernels.modules import KernelRollout
from drone_torchrl.kernels.ops import AGENTS_PER_EVALUATION
from drone_torchrl.optimum import Optimum
from drone_torchrl.registry import ALGORITHMS
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.jobs import Job, group_key, kept_changes, next_steps, prepare, record_failure
from drone_torchrl.training.memory import keep_freed_memory
from drone_torchrl.training.pbt import FRESH, ReplaySettings, SearchSettings
from drone_torchrl.training.population_record import PopulationRecord, is_population
from drone_torchrl.training.run import FAILED_FILE, AgentBook, Progress, Record, RunRecord, TrainingDiverged
from drone_torchrl.training.signals import TrainingStopped, stop_on_signals

#: The most updates per call of a learner's update; the loop copies a call's metrics and episodes to
#: the host at once, so this bounds what they hold in memory; results do not depend on it (a call
#: never runs past an evaluation, checkpoint or the end of a budget). It was the config key
#: updates_per_call.
MAX_UPDATES_PER_CALL = 100

log = logging.getLogger(__name__)


@dataclass
class Outcome:
    """How one job ended: its final metrics, or the error that stopped it."""

    run_dir: Path
    final: dict[str, float] | None = None
    error: BaseException | None = None

    @property
    def final_return(self) -> float | None:
        """The final running-mean return, or None if the job did not finish."""
        return None if self.final is None else self.final["final_return"]

    @classmethod
    def of(cls, run_dir: Path, final: dict[str, float] | None, failure: str | None) -> Outcome:
        """How an agent ended: its ``final`` metrics, or the ``failure`` of its divergence."""
        return cls(run_dir, final, None if failure is None else TrainingDiverged(failure))


def _to_host(tensors: dict[str, torch.Tensor]) -> dict[str, list]:
    """``tensor.tolist()`` of each tensor, all copied to the host at once (one sync).

    In float64, which holds every float32, int below 2**53 and bool exactly; ints and bools come back as such.
    """
    # numpy on the host: one device sync for the copy, none per tensor.
    flat = torch.cat([t.detach().reshape(-1).to(torch.float64) for t in tensors.values()]).cpu().numpy()
    parts = np.split(flat, np.cumsum([t.numel() for t in tensors.values()])[:-1])
    kind = {torch.bool: bool}
    return {
        key: part.reshape(t.shape)
        .astype(float if t.is_floating_point() else kind.get(t.dtype, np.int64))
        .tolist()
        for (key, t), part in zip(tensors.items(), parts, strict=True)
    }


class Trainer:
    """The jobs of one group (see :func:`~.jobs.group_key`) trained together by one learner."""

    def __init__(
        self,
        jobs: Sequence[Job] | AgentTable,
        population_dir: Path | None = None,
        names: Sequence[str] | None = None,
        checkpoint: dict | None = None,
        search: SearchSettings | None = None,
    ) -> None:
        """Train the jobs, each in its own run folder (a :class:`~.run.RunRecord`), or together as one population run.

        ``population_dir``: the population run's folder (a :class:`~.population_record.PopulationRecord`;
        the jobs may be an :class:`~.agents.AgentTable`); ``names``: the agents' names; ``checkpoint``:
        the population checkpoint to continue from; ``search``: train it with population-based
        training (:mod:`.pbt`).
        """
        self.cfg = cfg = jobs.cfg if isinstance(jobs, AgentTable) else jobs[0].cfg
        torch.set_num_threads(cfg.threads)
        if torch.device(cfg.device).type == "cpu":
            keep_freed_memory()
        self.learner = ALGORITHMS.get(cfg.algo.name).learner(jobs)
        #: The run folders' records (a run's per job, or the population run's).
        self.records: list[Record] = []
        try:
            if population_dir is not None:
                names = names or [str(i) for i in range(len(jobs))]
                state = self.learner.state
                record = PopulationRecord(jobs, names, population_dir, cfg.backend, checkpoint, state)
                self.records.append(record)
                if search is not None:
                    record.search = search.make(cfg, record.values, checkpoint and checkpoint["search"])
                    if checkpoint is None:
                        record.search.start(state)
            for job in jobs if population_dir is None else ():
                self.records.append(
                    RunRecord(job.cfg, job.run_dir, cfg.backend, job.checkpoint, job.parent_dir)
                )
        except BaseException:  # e.g. a logger that cannot start: the runs made so far close their loggers
            self.progress = Progress([], False)
            self.close(quietly=True)
            raise
        self.runs: list[AgentBook] = [agent for record in self.records for agent in record.agents]
        self.search = self.records[0].search
        # A finished search given a larger budget: the step due at its last update was skipped (no
        # step at the end of a budget); taken first, the schedule goes on as if the run had had the
        # larger budget from the start.
        self._search_step_pending = (
            self.search is not None
            and checkpoint is not None
            and all(
                f is not None or e is not None
                for f, e in zip(checkpoint["final"], checkpoint["failure"], strict=True)
            )
        )
        self.progress = Progress(self.runs, cfg.progress)

    @functools.cached_property
    def optimum(self) -> Optimum | None:
        """The best achievable return of the evaluation episodes (bounded thrust only), kept.

        Found at the first evaluation and kept, since the env is the same for every evaluation of
        the run.
        """
        return reference_optimum(env_kwargs(self.cfg))

    @property
    def population(self):
        """The REINFORCE learner's population (its agents' stacked state)."""
        return self.learner.population

    def train(self) -> list[dict[str, float] | None]:
        """Run every agent to its own ``algo.episodes``; returns each one's final metrics (None: it failed).

        SIGTERM or SIGUSR1 stop it after the update in flight, with a checkpoint of every active
        agent (:mod:`.signals`).
        """
        try:
            with stop_on_signals() as stop:
                # Killed after its last checkpoint but before the final evaluation: finish it now.
                if at_budget := [i for i, run in enumerate(self.runs) if run.finished and run.final is None]:
                    self.evaluate(at_budget)
                    self.save(at_budget)
                if self._search_step_pending and (
                    active := [i for i, run in enumerate(self.runs) if not (run.finished or run.failed)]
                ):
                    self.search_step(active)
                while active := [i for i, run in enumerate(self.runs) if not (run.finished or run.failed)]:
                    self.step(active)
                    if stop.signum is not None:  # after the update: a checkpoint of each active agent
                        active = [i for i in active if not self.runs[i].failed]
                        self.save(active)
                        dirs = list(dict.fromkeys(self.runs[i].run_dir for i in active))
                        raise TrainingStopped(stop.signum, dirs)
        except BaseException:
            self.close(quietly=True)  # the error in flight is the one to report, not a second one
            raise
        self.close()
        return [run.final for run in self.runs]

    def step(self, active: list[int], k: int | None = None) -> int:
        """Run ``k`` updates of the ``active`` agents, booked, then the evaluations and checkpoints due.

        ``k`` defaults to as many as nothing falls due in (at most :data:`MAX_UPDATES_PER_CALL`; one
        where the learner cannot tell). Returns the env steps the agents took.
        """
        runs, learner, search = self.runs, self.learner, self.search
        per_update = learner.episodes_per_update
        if k is None:
            k = (
                1
                if per_update is None
                else min(MAX_UPDATES_PER_CALL, *(runs[i].updates_until_due(per_update) for i in active))
            )
            if search is not None:
                k = min(k, search.updates_until_due(max(runs[i].updates_done for i in active)))
        mask = torch.zeros(len(runs), dtype=torch.bool, device=self.cfg.device)
        mask[active] = True
        _, out = learner.update(learner.state, k, mask)
        host = _to_host({**out.metrics, **out.episodes})  # one copy (one sync) per call
        trained, checks, valid = host.pop("active"), host.pop("checks"), host.pop("valid", None)
        episodes = {key: host.pop(key) for key in out.episodes if key != "valid"}
        steps = 0
        for j in range(k):
            booked = []
            for i in active:
                if not trained[j][i]:
                    continue
                failed = [what for what, ok in zip(learner.checks, checks[j][i], strict=True) if not ok]
                if failed:
                    what = " and ".join(failed)
                    runs[i].fail(
                        f"training diverged at episode {runs[i].episodes_done}: non-finite {what}; {learner.advice}"
                    )
                    continue
                ended = {key: values[j][i] for key, values in episodes.items()}
                if valid is not None:  # a learner whose updates end different numbers of episodes
                    ended = {key: list(compress(values, valid[j][i])) for key, values in ended.items()}
                runs[i].record(ended, {key: values[j][i] for key, values in host.items()})
                steps += sum(ended["length"])
                booked.append((runs[i], len(ended["length"])))
            if booked:
                self.progress.update(sum(n for _, n in booked), [run for run, _ in booked])
                for record in self.records:
                    record.after_update()
        active = [i for i in active if not runs[i].failed]
        if search is not None and active and not any(runs[i].finished for i in active):
            self.search_step(active)
        if due := [i for i in active if runs[i].eval_due]:
            self.evaluate(due)
        if due := [i for i in active if runs[i].checkpoint_due]:
            self.save(due)
        return steps

    def search_step(self, active: list[int]) -> None:
        """The population's search step (:mod:`.pbt`) if one is due after the ``active`` agents' updates."""
        search, runs = self.search, self.runs
        assert search is not None
        done = max(runs[i].updates_done for i in active)
        if search.due(done):
            scores = [run.running_return for run in runs]
            for agent, parent in search.step(self.learner.state, scores, [not r.failed for r in runs], done):
                runs[agent].take_window(None if parent == FRESH else runs[parent])

    def save(self, agents: list[int]) -> None:
        """A checkpoint of each of ``agents``' records (a population run's: one of every agent)."""
        for record, i in {self.runs[i].owner: i for i in agents}.items():
            record.save(record.learner_state(self.learner, i))

    def evaluate(self, agents: list[int]) -> None:
        """Fly the agents' deterministic policies on the evaluation seeds, all at once, and book it."""
        cfg, learner = self.cfg, self.learner
        policy, n = learner.eval_policy(), learner.eval_agents
        # A population's agents a slice at a time (ops.AGENTS_PER_EVALUATION): the episodes of
        # one slice are held at once, whatever the population's size.
        flown = [(policy, n)]
        if isinstance(policy, KernelRollout):  # the fast engine's: a slice of the population at a time
            rows = [slice(i, min(n, i + AGENTS_PER_EVALUATION)) for i in range(0, n, AGENTS_PER_EVALUATION)]
            flown = [(policy.rows(r), r.stop - r.start) for r in rows]
        parts = [
            evaluate(p, env_kwargs(cfg), cfg.eval.episodes, cfg.eval.seed, cfg.device, agents=count)[0]
            for p, count in flown
        ]
        stats = {key: torch.cat([part[key] for part in parts]) for key in parts[0]}
        means = {
            k: stats[k].float().mean(-1).reshape(-1).tolist() for k in ("return", "length", "time_in_zone")
        }
        if self.optimum is not None:
            means["pct_of_optimum"] = [100.0 * r / self.optimum.best_return for r in means["return"]]
        for i in agents:
            best_before = self.runs[i].best_eval
            self.runs[i].record_eval(
                {name: values[i] for name, values in means.items()},
                lambda i=i: learner.checkpoint_entries(i),
                lambda i=i: learner.actor(i),
            )
            learner.after_evaluation(self.runs[i], best_before)
        for record in self.records:
            record.after_eval()

    def close(self, quietly: bool = False) -> None:
        """Flush and close every run.

        ``quietly``: while another error stops training, a run whose files cannot be written (the same full
        disk, say) is left as its last checkpoint has it.
        """
        self.progress.close()
        self.learner.close()
        for record in self.records:
            try:
                record.close(quietly)
            except Exception:  # noqa: BLE001  (a logger's own error, when another one is reported)
                if not quietly:
                    raise


def train_jobs(jobs: Sequence[Job]) -> list[Outcome]:
    """Train prepared jobs (:func:`~.jobs.prepare`), those that can share a population together.

    Finished jobs return at once; a group whose training raises is recorded as failed
    (``<run>/FAILED.txt``) and the other groups go on, but for a :class:`~drone_torchrl.io.storage.StorageError`
    (a full or read-only disk would refuse them too), which is raised. Each job's folder is let go when done
    (:mod:`drone_torchrl.io.run_lock`). A signal between two groups stops before the next one starts.
    """
    outcomes = [Outcome(job.run_dir) for job in jobs]
    groups: dict[str, list[int]] = {}
    for i, job in enumerate(jobs):
        if not job.already_finished:
            groups.setdefault(group_key(job.cfg), []).append(i)
            continue
        console.info(
            f"{job.run_dir}: already finished ({job.checkpoint['episodes_done']} episodes); nothing to do",
            **about(job.run_dir),
        )
        outcomes[i].final = job.checkpoint["final"]
        (job.run_dir / FAILED_FILE).unlink(missing_ok=True)  # left by a refused re-run
    # A learner trains up to max_agents jobs at once (PPO: one; REINFORCE: a whole group).
    batches = []
    for members in groups.values():
        cfg = jobs[members[0]].cfg
        size = ALGORITHMS.get(cfg.algo.name).learner.max_agents(cfg) or len(members)
        batches += [members[start : start + size] for start in range(0, len(members), size)]
    try:
        with stop_on_signals() as stop:
            for members in batches:
                if stop.signum is not None:  # the groups trained so far have written their checkpoints
                    raise TrainingStopped(stop.signum, [])
                try:
                    if len(members) > 1:  # each job's config fits; do they, trained together?
                        check_memory(jobs[members[0]].cfg, agents=len(members))
                    trainer = Trainer([jobs[i] for i in members])
                    trainer.train()
                except StorageError:  # the disk refuses, not this group: the groups after it would fail alike
                    raise
                except Exception as err:  # noqa: BLE001  (recorded per job; the other groups go on)
                    for i in members:
                        record_failure(jobs[i].run_dir, err)
                        outcomes[i].error = err
                    continue
                for i, run in zip(members, trainer.runs, strict=True):
                    outcomes[i] = Outcome.of(run.run_dir, run.final, run.failure)
                    _report(run, len(jobs) > 1)
    finally:
        for job in jobs:
            run_lock.release(job.run_dir)
    return outcomes


def _report(run: AgentBook, several: bool) -> None:
    """Say how the run ended (a failure only where ``several`` jobs trained)."""
    run_dir, final = run.run_dir, run.final
    if final is None:  # the agent diverged (its run record wrote FAILED.txt)
        if several:
            console.info(f"{run_dir}: failed: {TrainingDiverged(run.failure)}", **about(run_dir))
        return
    # Finished short of its budget: an evaluation reached eval.stop_return.
    stopped = (
        "" if run.episodes_done >= run.budget else f" (an evaluation at eval.stop_return={run.stop_return:g})"
    )
    console.info(
        f"{run_dir}: {run.episodes_done} episodes{stopped}, running-mean({RUNNING_MEAN_WINDOW}) "
        f"return {final['final_return']:.1f}, length {final['final_length']:.1f}, "
        f"eval return {final['eval_return']:.1f}, {final['wall_clock_s']:.0f} s",
        **about(run_dir),
    )


def train(cfg: DictConfig, run_dir: str | Path | None = None, show_next_steps: bool = False) -> float:
    """Train one run; returns its final running-mean return (the metric sweepers optimise).

    ``run_dir`` defaults to the Hydra job's output folder; with ``resume`` of a run's last
    checkpoint, that run's folder. Raises the error that stopped it (a :class:`~.checks.ConfigError` for a
    bad config, with a one-line message). ``show_next_steps``: end with the commands that look at
    the run (:func:`~.jobs.next_steps`), as ``drone-train`` does.
    """
    outcome = train_job(prepare(cfg, run_dir))
    if show_next_steps:
        console.info(next_steps(outcome.run_dir), **about(outcome.run_dir))
    return outcome.final_return


def train_job(job: Job) -> Outcome:
    """Train one prepared job (:func:`~.jobs.prepare`); returns its outcome, with its final metrics.

    Raises the error that stopped it, as :func:`train` does (``drone_torchrl.train`` calls this too).
    """
    (outcome,) = train_jobs([job])
    if outcome.error is not None:
        raise outcome.error
    if outcome.final is None:  # neither metrics nor a failure: a run that ended and cannot say how
        raise ConfigError(f"{outcome.run_dir}: training ended without final metrics")
    return outcome


def train_population(
    agents: AgentTable | Sequence[DictConfig],
    names: Sequence[str],
    run_dir: Path,
    before_training: Callable[[], None] | None = None,
    search: SearchSettings | None = None,
) -> list[Outcome]:
    """Train validated agents of one group as ONE population run in ``run_dir``, or continue it.

    The group is a :func:`~.jobs.group_key`'s agents, as an :class:`~.agents.AgentTable` or their
    configs; the run is recorded by :mod:`.population_record` and continues from its
    ``checkpoints/last.pt``.

    Refused in one line (:class:`~.checks.ConfigError`) before anything is written: a learner that does not
    train populations, a population larger than this machine's free memory, a folder another
    process holds, a checkpoint of other agents or hyper-parameters. ``before_training``: called
    once the folder is this process's, when it holds no checkpoint yet (the launcher writes Hydra's
    record then); ``search``: train
    it with population-based training (:mod:`.pbt`). One outcome per agent; SIGTERM stops it with a
    checkpoint (:class:`~.signals.TrainingStopped`).
    """
    agents = AgentTable.of(agents)
    cfg = agents.cfg
    run_dir = Path(run_dir)
    check_population(agents, search)
    run_lock.hold(run_dir)
    try:
        checkpoint = _population_checkpoint(agents, run_dir, search)
        budget = cfg.algo.episodes
        if checkpoint is not None and all(
            (final is not None and done >= budget) or failure is not None
            for final, failure, done in zip(
                checkpoint["final"], checkpoint["failure"], checkpoint["episodes_done"], strict=True
            )
        ):
            console.info(
                f"{run_dir}: already finished ({len(agents)} agents); nothing to do (a larger "
                f"algo.episodes with hydra.sweep.dir={run_dir.parent} trains them on)",
                **about(run_dir),
            )
            return list(
                map(functools.partial(Outcome.of, run_dir), checkpoint["final"], checkpoint["failure"])
            )
        if before_training is not None and checkpoint is None:
            # A folder that holds a run keeps the record of how it was started, as a run folder's
            # .hydra/ does (drone_torchrl.io.folders.record_subdir).
            before_training()
        trainer = Trainer(agents, run_dir, names, checkpoint, search)
        log.info(f"{run_dir}: {len(agents)} agents set up; training")
        trainer.train()
        return [Outcome.of(run.run_dir, run.final, run.failure) for run in trainer.runs]
    finally:
        run_lock.release(run_dir)


def check_population(agents: AgentTable, search: SearchSettings | None = None) -> None:
    """What :func:`train_population` refuses of a group before any folder: its learner, budget and memory.

    Raises :class:`~.checks.ConfigError` (one line): a learner that trains one agent at a time,
    ``eval.stop_return``, a population larger than this machine's free memory, a search the budget
    or the population's size cannot hold (``search.check``).
    """
    cfg = agents.cfg
    if ALGORITHMS.get(cfg.algo.name).learner.max_agents(cfg) is not None:
        raise ConfigError(
            f"algo={cfg.algo.name} is not allowed with hydra/launcher=population (with backend={cfg.backend} it "
            "trains one agent at a time); expected algo=reinforce (or reinforce_plus) with backend=fast, "
            "or hydra/launcher=fused"
        )
    if cfg.eval.get("stop_return") is not None:
        raise ConfigError.of(
            "eval.stop_return",
            cfg.eval.stop_return,
            "null with hydra/launcher=population (its agents train their whole budget together)",
        )
    try:
        check_memory(cfg, agents=len(agents))
    except ConfigError as err:  # say that it is the population's size, not one agent's
        raise ConfigError(f"{len(agents)} agents trained together in one population run: {err}") from None
    if search is not None:
        search.check(cfg, len(agents))


def _population_checkpoint(
    agents: AgentTable, run_dir: Path, search: SearchSettings | None = None
) -> dict | None:
    """The population run's last checkpoint, if it has one, checked against the sweep's agents.

    The hyper-parameters are checked too, as a continued run's: only the budget, logging and
    process settings may change.
    """
    path = run_dir / CHECKPOINT_DIR / LAST
    if not path.is_file():
        return None
    try:
        checkpoint = load_checkpoint(path)
    except CheckpointError as err:
        raise ConfigError(f"{run_dir} cannot be continued: {err}") from None
    if not is_population(checkpoint):
        raise ConfigError(
            f"{run_dir} holds a single run's checkpoint, not a population's: use another hydra.sweep.dir"
        )
    # The agents are their per-agent values, in order. Their names are their jobs' whole overrides,
    # which hold the budget and process settings too: a raised algo.episodes names them anew
    # (agents.parquet then does), as the other keys a continued run may change are checked below.
    saved_values = {key: values for key, values in checkpoint["agents"].items() if key != "name"}
    if saved_values != agents.values:
        raise ConfigError(
            f"{path} holds {len(checkpoint['agents']['name'])} other agents (per-agent values differ "
            "from this sweep's): run the sweep that wrote it, or use another hydra.sweep.dir"
        )
    per_agent = set(per_agent_keys())
    changed = kept_changes(checkpoint["config"], agents.cfg, lambda key: key not in per_agent)
    if changed:
        raise ConfigError(
            f"resume: {path} was trained with other values ({'; '.join(changed)}); a continued population keeps "
            "its hyper-parameters: drop those overrides or use another hydra.sweep.dir"
        )
    saved_search = checkpoint.get("search")
    if isinstance(search, ReplaySettings) and saved_search:  # it keeps following its saved schedule
        search.check_resume(saved_search["settings"])
    now_search = None if search is None else search.record()
    if saved_search and now_search and "schedule" not in saved_search["settings"]:
        now_search.pop("schedule", None)  # a replay from before replays kept their schedule
    if (saved_search and saved_search["settings"]) != now_search:
        raise ConfigError(
            f"resume: {path} was trained with {_search_text(saved_search and saved_search['settings'])}, "
            f"this command asks for {_search_text(now_search)}; a continued population keeps its search: "
            "run the command that wrote it, or use another hydra.sweep.dir"
        )
    done = max(checkpoint["episodes_done"])
    if agents.cfg.algo.episodes < done:
        raise ConfigError.of(
            "algo.episodes",
            agents.cfg.algo.episodes,
            f">= {done}: {path} has already trained {done} episodes",
        )
    return checkpoint


def _search_text(settings: dict | None) -> str:
    if settings is None:
        return "no search (hydra/launcher=population)"
    keys = (f"hydra.launcher.{k}={v}" for k, v in settings.items() if k not in ("launcher", "schedule"))
    return f"hydra/launcher={settings['launcher']} {' '.join(keys)}"
