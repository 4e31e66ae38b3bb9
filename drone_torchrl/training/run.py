"""The run record: everything one agent's run keeps on disk, in one place for every engine.

A :class:`RunRecord` owns a run folder: the episode counters, ``episodes.csv``, the TensorBoard
run, the evaluation schedule and its videos, ``best.pt`` and ``last.pt``, the final metrics, and
what a resumed run picks up again. It is fed finished episodes (however many an update brings,
from however many envs) and the update's training metrics; it never sees a policy or a batch, so
every collector and every algorithm shares it. A population run's folder
(:mod:`.population_record`) is written through the same :class:`Record` interface: the set-up,
``config.yaml``, the logger, the flushes that renew the folder's lock, ``last.pt`` after the rows it
counts, and the close that tells the logger how the run ended.

The learner's own state (policy, optimizer, RNG streams) is handed in as a dict when a checkpoint
is written: the record adds its counters and the config (see :mod:`drone_torchrl.io.checkpoint`).
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from drone_torchrl.config import env_kwargs
from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.episodes import EPISODE_KEYS, RUNNING_MEAN_WINDOW
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import (
    BEST,
    CHECKPOINT_DIR,
    LAST,
    RUN,
    agent_counters,
    record_state,
    save_checkpoint,
)
from drone_torchrl.io.episodes_csv import CSV_NAME, EpisodeCSV
from drone_torchrl.io.storage import writing
from drone_torchrl.io.streams import about, console
from drone_torchrl.io.video import VIDEO_DIR, record_video, save_mp4
from drone_torchrl.io.yaml_text import save_yaml
from drone_torchrl.loggers import FAILED, FINISHED, STOPPED, log_update, make_logger

CONFIG_NAME = "config.yaml"
FAILED_FILE = "FAILED.txt"
# TerminationCause code -> name, as the CSV rows hold it.
_CAUSE_NAMES = {int(cause): cause.name for cause in TerminationCause}


def _mean(values: deque[float]) -> float:
    """The mean of ``values`` (nan when empty).

    math.fsum, not np.mean: read per update by every run of a population, and np.mean copies the
    deque into an array first.
    """
    if not values:
        return math.nan
    try:
        return math.fsum(values) / len(values)
    except ValueError:  # inf and -inf: no sum
        return math.nan


class TrainingDiverged(RuntimeError):
    """A run whose loss, gradients, weights or actions became non-finite (one-line message)."""


@dataclass(frozen=True)
class Schedule:
    """The numbers of a config that an agent's counters read at every update."""

    budget: int
    every_updates: int
    checkpoint_every: int
    eval_every: int
    window: int
    stop_return: float | None

    @classmethod
    def of(cls, cfg: DictConfig) -> Schedule:
        """The schedule of a run's config (budget, logging, checkpoint and evaluation periods, window)."""
        return cls(
            budget=int(cfg.algo.episodes),
            every_updates=int(cfg.logger.every_updates),
            checkpoint_every=int(cfg.checkpoint.every_episodes),
            eval_every=int(cfg.eval.every_episodes),
            window=RUNNING_MEAN_WINDOW,
            stop_return=cfg.eval.get("stop_return"),
        )


def trained_out(episodes_done: int, budget: int, stopped_at: float | None, stop_return: float | None) -> bool:
    """Whether an agent is done: its budget trained, or an evaluation at ``stop_return`` or above.

    ``stopped_at``: the return of the evaluation that stopped it (None: none did). A continued run
    whose ``eval.stop_return`` is raised above it, or set to null, trains on, as one whose budget
    is raised does.
    """
    reached = stop_return is not None and stopped_at is not None and stopped_at >= stop_return
    return reached or episodes_done >= budget


class AgentBook:
    """One agent's counters: episodes and updates done, running means, schedule and outcome.

    What it books goes to its record's files (its ``owner``, a :class:`Record`): a
    :class:`RunRecord` is its own one agent; a population run's record has one per agent
    (:mod:`.population_record`).

    Args:
        cfg: the agent's validated config.
        checkpoint: the record's checkpoint it continues from (its counters: :func:`~drone_torchrl.io.checkpoint.agent_counters`), or None.
        schedule: the config's :class:`Schedule`, read once for all the agents of a population
            (None: read from ``cfg``).
        owner: the record that writes its files (None: itself, a :class:`RunRecord`).
        index: the agent's index in its record.
    """

    def __init__(
        self,
        cfg: DictConfig,
        checkpoint: dict[str, Any] | None = None,
        schedule: Schedule | None = None,
        owner: Record | None = None,
        index: int = 0,
    ) -> None:
        self.cfg, self.index = cfg, index
        self.owner: Record = self if owner is None else owner  # type: ignore[assignment]
        if owner is not None:
            self.run_dir = owner.run_dir
        # Read per update by every agent of a population: plain numbers, not OmegaConf lookups;
        # a population reads them once for all its agents.
        s = Schedule.of(cfg) if schedule is None else schedule
        self.budget, self.every_updates, self.window = s.budget, s.every_updates, s.window
        self.checkpoint_every, self.eval_every = s.checkpoint_every, s.eval_every
        self.stop_return = s.stop_return
        counters = {} if checkpoint is None else agent_counters(checkpoint, index)  # {}: a fresh agent's
        self.episodes_done: int = counters.get("episodes_done", 0)
        self.updates_done: int = counters.get("updates_done", 0)
        self.wall_clock_before: float = counters.get("wall_clock_s", 0.0)
        self.best_eval: float = counters.get("best_eval_return", -math.inf)
        self.recent_returns: deque[float] = deque(counters.get("recent_returns", ()), maxlen=s.window)
        self.recent_lengths: deque[float] = deque(counters.get("recent_lengths", ()), maxlen=s.window)
        # The return of the evaluation that ended it early.
        self.stopped_at: float | None = counters.get("stopped_at_return")
        # A finished agent given a larger budget trains on.
        self.final: dict[str, float] | None = counters.get("final") if self.finished else None
        self.failure: str | None = counters.get("failure")
        self.last_eval_episode: int | None = None
        self.last_eval_return = -math.inf  # this process's last evaluation's mean return
        self.next_checkpoint = self.episodes_done + self.checkpoint_every
        self.next_eval = self.episodes_done + self.eval_every if self.eval_every else None
        self.start = time.perf_counter()

    @property
    def finished(self) -> bool:
        """Whether the agent has trained its budget of episodes, or reached ``eval.stop_return``."""
        return trained_out(self.episodes_done, self.budget, self.stopped_at, self.stop_return)

    def take_window(self, other: AgentBook | None) -> None:
        """Take ``other``'s running-mean windows; None empties them.

        An agent that took ``other``'s weights is scored by its windows; one restarted from fresh
        weights gets None.
        """
        self.recent_returns = deque([] if other is None else other.recent_returns, maxlen=self.window)
        self.recent_lengths = deque([] if other is None else other.recent_lengths, maxlen=self.window)

    @property
    def failed(self) -> bool:
        """Whether the agent failed (diverged)."""
        return self.failure is not None

    def fail(self, reason: str) -> None:
        """Stop the agent: it failed for ``reason``; its record keeps its last finite state."""
        self.failure = reason
        self.owner.agent_failed(self)

    def record(self, episodes: dict[str, Sequence], train_metrics: dict[str, float]) -> None:
        """Book one update: its finished episodes and its training metrics, written by the record.

        The episodes are ``EPISODE_KEYS`` -> one value per episode, in the order they finished; the
        record gets their rows as columns: ``episode``, ``update``, ``wall_clock_s`` and ``EPISODE_KEYS``.
        """
        count, first = len(episodes["return"]), self.episodes_done
        self.updates_done += 1
        self.recent_returns.extend(episodes["return"])
        self.recent_lengths.extend(episodes["length"])
        self.episodes_done += count
        rows = {
            "episode": range(first, first + count),
            "update": [self.updates_done] * count,
            "wall_clock_s": [round(self.wall_clock, 3)] * count,
            **{key: episodes[key] for key in EPISODE_KEYS},
        }
        self.owner.add_rows(self, rows, train_metrics)

    def record_eval(
        self,
        result: dict[str, float],
        learner_state: Callable[[], dict[str, Any]] | None = None,
        actor: Callable[[], Any] | None = None,
    ) -> None:
        """Book an evaluation (its ``return``, ``length``, ``time_in_zone`` means), logged by the record.

        ``learner_state`` and ``actor`` give its state and policy, for a record that keeps them. The
        schedule moves on; the final metrics are set at the end.
        """
        self.owner.log_eval(self, result, learner_state, actor)
        self.last_eval_return = result["return"]
        self.best_eval = max(self.best_eval, result["return"])
        if self.stop_return is not None and result["return"] >= self.stop_return:
            self.stopped_at = result["return"]
        self.last_eval_episode = step = self.episodes_done
        if self.next_eval is not None:
            while self.next_eval <= step:
                self.next_eval += self.eval_every
        if self.finished:
            self.final = {
                "final_return": self.running_return,
                "final_length": self.running_length,
                "eval_return": result["return"],
                "wall_clock_s": self.wall_clock,
            }

    @property
    def wall_clock(self) -> float:
        """Seconds the agent has trained, over all its processes."""
        return self.wall_clock_before + time.perf_counter() - self.start

    @property
    def running_return(self) -> float:
        """The running mean of the last ``window`` episodes' returns."""
        return _mean(self.recent_returns)

    @property
    def running_length(self) -> float:
        """The running mean of the last ``window`` episodes' lengths."""
        return _mean(self.recent_lengths)

    @property
    def eval_due(self) -> bool:
        """Every ``eval.every_episodes`` episodes, and once at the end (not twice when they coincide)."""
        if self.last_eval_episode == self.episodes_done:
            return False
        periodic = self.next_eval is not None and self.episodes_done >= self.next_eval
        return periodic or self.finished

    def updates_until_due(self, episodes_per_update: int) -> int:
        """Updates of ``episodes_per_update`` episodes until an evaluation, checkpoint or the end is due.

        The end is the budget's; at least 1.
        """
        targets = [self.next_checkpoint, self.budget]
        if self.next_eval is not None:
            targets.append(self.next_eval)
        episodes = min(target - self.episodes_done for target in targets)
        return max(1, -(-episodes // episodes_per_update))

    @property
    def checkpoint_due(self) -> bool:
        """Whether a checkpoint is due (or the budget is done)."""
        return self.finished or self.episodes_done >= self.next_checkpoint

    def counters(self) -> dict[str, Any]:
        """What a checkpoint keeps of these counters (:data:`~drone_torchrl.io.checkpoint.COUNTERS`)."""
        return {
            "episodes_done": self.episodes_done,
            "updates_done": self.updates_done,
            "wall_clock_s": self.wall_clock,
            "best_eval_return": self.best_eval,
            "recent_returns": list(self.recent_returns),
            "recent_lengths": list(self.recent_lengths),
            "stopped_at_return": self.stopped_at,
            "final": self.final,
            "failure": self.failure,
        }


class Record:
    """A run folder's record, one writer interface for both kinds: its config, logger, lock, rows and checkpoint.

    :class:`RunRecord` (one agent: ``episodes.csv``, TensorBoard, ``best.pt``, videos) and
    :class:`~.population_record.PopulationRecord` (N agents: Parquet parts, population summaries).
    Both write ONE checkpoint layout (:func:`~drone_torchrl.io.checkpoint.record_state`: the
    learner's state, then every agent's counters). A subclass sets ``agents`` and ``kind``, writes
    its rows (``add_rows``, ``write_rows``), logs evaluations (``log_eval``), says what a failed
    agent leaves (``agent_failed``) and gives its final hparams (``final_metrics``). The trainer
    calls every record's hooks alike (:meth:`learner_state`, :meth:`after_update`,
    :meth:`after_eval`: no-ops or a run's one agent where it has nothing more to do).
    """

    agents: Sequence[AgentBook]
    kind = RUN
    search: Any = None  # a population run's search (:mod:`.pbt`)

    def open(self, cfg: DictConfig, run_dir: Path, backend: str, resumed_at: int | None) -> None:
        """Make the folder (``checkpoints/``, no ``FAILED.txt``), write ``config.yaml``, start the logger."""
        # The resolved config as plain data, for checkpoints and the logger's hparams (made once:
        # OmegaConf.to_container is slow to repeat, and the config does not change during a run).
        self.config = OmegaConf.to_container(cfg, resolve=True)
        self.run_dir = run_dir = Path(run_dir)
        self.backend = backend
        self.flush_every_s = float(cfg.logger.flush_every_s)
        self._closed = False
        with writing(run_dir / CHECKPOINT_DIR):
            (run_dir / CHECKPOINT_DIR).mkdir(parents=True, exist_ok=True)
            (run_dir / FAILED_FILE).unlink(missing_ok=True)
        save_yaml(cfg, run_dir / CONFIG_NAME)
        self.logger = make_logger(cfg, run_dir, resumed_at)
        self._last_flush = time.perf_counter()

    def learner_state(self, learner: Any, agent: int) -> dict[str, Any]:
        """What the ``learner`` (training agent ``agent`` of the record's) gives the record's checkpoint."""
        return learner.checkpoint_entries(agent)

    def after_update(self) -> None:
        """After an update of the trainer's agents is booked: nothing by default."""

    def after_eval(self) -> None:
        """After an evaluation of the trainer's agents is booked: nothing by default."""

    def checkpoint_state(self, learner: dict[str, Any]) -> dict[str, Any]:
        """The record's checkpoint: ``learner``'s state (actor, optimizer, RNG streams...), config, counters."""
        counters = [agent.counters() for agent in self.agents]
        return record_state(self.kind, self.backend, learner, self.config, counters, self.agents[0].window)

    def write_last(self, learner: Any) -> None:
        """Write ``checkpoints/last.pt`` of the learner's state, after the rows it counts."""
        self.flush()
        save_checkpoint(self.checkpoint_state(learner), self.run_dir / CHECKPOINT_DIR / LAST)

    def save(self, learner: Any) -> None:
        """Write ``last.pt`` (:meth:`write_last`); once every agent has ended, the final hparams too, and close.

        The final hparams are ``final_metrics`` (none when no agent finished).
        """
        self.write_last(learner)
        for agent in self.agents:  # the next checkpoint falls due checkpoint.every_episodes later
            while agent.next_checkpoint <= agent.episodes_done:
                agent.next_checkpoint += agent.checkpoint_every
        if all(a.failed or a.final is not None for a in self.agents):
            if metrics := self.final_metrics():
                self.logger.log_final_hparams(self.config, metrics)
            self.close()

    def flush_if_due(self) -> None:
        """:meth:`flush` every ``logger.flush_every_s`` seconds."""
        if time.perf_counter() - self._last_flush > self.flush_every_s:
            self.flush()

    def flush(self) -> None:
        """Write the buffered rows and logger scalars, and renew the run folder's lock.

        Files are open only while this runs. The renewed lock is what another host reads as "its
        owner is alive".
        """
        self.write_rows()
        self.logger.flush()
        run_lock.renew(self.run_dir)
        self._last_flush = time.perf_counter()

    def close(self, quietly: bool = False) -> None:
        """Write what is buffered and close the logger, once, telling it how the run ended.

        Failed when every agent failed, finished when every other one did, else stopped: a backend
        with a service or open run, as W&B and MLflow have, records that outcome. ``quietly``:
        while another error stops training, rows the disk refuses are left unwritten.
        """
        if self._closed:
            return
        self._closed = True
        try:
            self.write_rows()
        except OSError:
            if not quietly:
                raise
        failed = all(a.failed for a in self.agents)
        done = all(a.failed or a.final is not None for a in self.agents)
        self.logger.close(FAILED if failed else FINISHED if done else STOPPED)
        run_lock.renew(self.run_dir)


class RunRecord(AgentBook, Record):
    """One agent's run folder and its bookkeeping.

    Args:
        cfg: the run's validated config.
        run_dir: the folder to write (created if needed).
        backend: the backend that trains it (stored in checkpoints; a run continues with it).
        checkpoint: the loaded checkpoint to continue from, or None for a fresh run.
        parent_dir: for a fork (resuming from a checkpoint that is not ``run_dir``'s last), the
            folder it came from: its ``episodes.csv`` rows up to the checkpoint are copied; the
            parent is left untouched.
    """

    def __init__(
        self,
        cfg: DictConfig,
        run_dir: Path,
        backend: str,
        checkpoint: dict[str, Any] | None = None,
        parent_dir: Path | None = None,
    ) -> None:
        super().__init__(cfg, checkpoint)
        self.agents = (self,)
        resumed = checkpoint is not None
        self.open(cfg, run_dir, backend, self.episodes_done if resumed else None)
        self.csv = EpisodeCSV(
            self.run_dir / CSV_NAME,
            keep_episodes=self.episodes_done,
            source=None if parent_dir is None else Path(parent_dir) / CSV_NAME,
        )
        for note in self.csv.notes:
            console.warning(f"resume: {note}", **about(self.run_dir))
        if resumed and not self.finished:
            console.info(
                f"{self.run_dir}: continuing from episode {self.episodes_done} (the checkpoint's); "
                f"{self.csv.dropped} episode(s) logged after it are trained again",
                **about(self.run_dir),
            )
        self.start = self._last_flush = time.perf_counter()

    def agent_failed(self, agent: AgentBook) -> None:
        """``FAILED.txt`` says why the run stopped; its last checkpoint (all finite) is kept as it is."""
        path = self.run_dir / FAILED_FILE
        with writing(path):
            path.write_text(f"{TrainingDiverged.__name__}: {self.failure}\n")
        self.close()

    def write_rows(self) -> None:
        """Append the buffered rows to ``episodes.csv``."""
        self.csv.flush()

    def add_rows(self, agent: AgentBook, columns: dict[str, Sequence], metrics: dict[str, float]) -> None:
        """Buffer an update's episode rows; its training ``metrics`` go to TensorBoard every ``logger.every_updates``."""
        columns["termination_cause"] = [_CAUSE_NAMES[int(cause)] for cause in columns["termination_cause"]]
        rows = [dict(zip(columns, values, strict=True)) for values in zip(*columns.values(), strict=True)]
        self.csv.write(rows)
        if self.updates_done % self.every_updates == 0:
            metrics = {
                **metrics,
                "train/running_mean_return": self.running_return,
                "train/running_mean_length": self.running_length,
            }
            log_update(self.logger, rows, metrics, step=self.episodes_done)
        self.flush_if_due()

    def log_eval(self, agent: AgentBook, result: dict[str, float], learner_state: Any, actor: Any) -> None:
        """Log an evaluation: TensorBoard, ``best.pt`` when it is the best so far, and a video.

        The video, of ``actor()``, only with ``eval.video``. The video is
        ``<run>/videos/episode_<step>.mp4`` and TensorBoard's ``eval/video``: ``logger.video_stride``
        thins the frames (the playback rate is divided alike, so it stays real time) and, for
        TensorBoard only, the pixels (a GIF there, 4x smaller).
        """
        cfg = self.cfg
        step = self.episodes_done
        self.logger.log_metrics({f"eval/{k}": v for k, v in result.items()}, step=step)
        if cfg.checkpoint.keep_best and result["return"] > self.best_eval:
            self.best_eval = result["return"]
            save_checkpoint(self.checkpoint_state(learner_state()), self.run_dir / CHECKPOINT_DIR / BEST)
        if cfg.eval.video:
            stride = cfg.logger.video_stride
            frames = record_video(actor(), env_kwargs(cfg), cfg.eval.seed, cfg.device, frame_stride=stride)
            fps = 1 / (cfg.env.dt * stride)
            save_mp4(frames, self.run_dir / VIDEO_DIR / f"episode_{step:06d}.mp4", fps)
            self.logger.log_frames("eval/video", frames[:, ::stride, ::stride], step=step, fps=fps)

    def final_metrics(self) -> dict[str, float] | None:
        """The final hparams' metrics: the run's final metrics."""
        return self.final


class Progress:
    """One progress bar over the episodes of every run trained together, with the running mean.

    Args:
        runs: the runs trained together.
        setting: ``progress``: True, False or ``"auto"`` (shown when stderr is a terminal).
    """

    def __init__(self, runs: Sequence[RunRecord], setting: bool | str) -> None:
        show = sys.stderr.isatty() if setting == "auto" else bool(setting)
        self.bar = tqdm(
            total=sum(r.budget for r in runs),
            initial=sum(r.episodes_done for r in runs),
            disable=not show,
            unit="ep",
            dynamic_ncols=True,
        )

    def update(self, episodes: int, active: Sequence[RunRecord]) -> None:
        """Advance the progress bar by ``episodes`` and show the ``active`` runs' running means."""
        if self.bar.disable:  # the running means below are per run per update: skipped when unseen
            return
        self.bar.update(episodes)
        window = active[0].window
        returns = [r.running_return for r in active]
        if len(active) == 1:
            text = f"return({window})={returns[0]:.0f} length={active[0].running_length:.0f}"
        else:
            text = (
                f"{len(active)} agents, return({window}) mean={np.mean(returns):.0f} best={max(returns):.0f}"
            )
        self.bar.set_postfix_str(text, refresh=False)

    def close(self) -> None:
        """Close the progress bar."""
        self.bar.close()
