"""A population run: the agents of one population in ONE folder (``hydra/launcher=population``).

A sweep's per-job folders cost a lock, ``.hydra/``, a CSV, a logger and checkpoints per agent, which
at tens of thousands of agents is most of the time and open files. A population run keeps::

    <run>/
      .hydra/, config.yaml     the group's config (agent 0's values of the per-agent keys)
      agents.parquet           one row per agent: agent, name (its job's overrides), seed, algo.lr, ...
      episodes/part-NNNNNN.parquet
                               every finished episode: agent, episode, update, return, length,
                               time_in_zone, negative_thrust_fraction, termination_cause, wall_clock_s;
                               each part written atomically (a kill never leaves a torn one)
      checkpoints/last.pt      the stacked state and counters of every agent (the one checkpoint
                               layout, :mod:`drone_torchrl.io.checkpoint`)
      lineage.parquet          with population-based training (:mod:`.pbt`): each exploit step's
                               update, agent, parent and new values, as far as the checkpoint
      <logger's files>         population summaries: quantiles of the running-mean return, the best
                               agent, the number alive (not diverged)
      .lock, FAILED.txt        as a run folder's

Each agent keeps its counters in an :class:`~.run.AgentBook`, as a :class:`~.run.RunRecord` does; the
files are the :class:`PopulationRecord`'s (the same :class:`~.run.Record` writer interface). The checkpoint names
how many episode parts it covers: parts written after it (episodes the resumed run trains again)
are removed on resume, so every agent's episodes appear exactly once.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from drone_torchrl import extras
from drone_torchrl.checks import ConfigError, first_line
from drone_torchrl.config import open_checkpoint, run_config
from drone_torchrl.episodes import EPISODE_KEYS
from drone_torchrl.io.checkpoint import (
    CHECKPOINT_DIR,
    LAST,
    POPULATION,
    RUN,
    agent_counters,
    is_population,
    load_checkpoint,
    record_state,
)
from drone_torchrl.io.storage import write_atomically, writing
from drone_torchrl.io.streams import about, console
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.pbt import Search, complete_lineage, final_values
from drone_torchrl.training.population import Population
from drone_torchrl.training.run import _CAUSE_NAMES, AgentBook, Record, Schedule, TrainingDiverged

AGENTS_TABLE = "agents.parquet"
LINEAGE_TABLE = "lineage.parquet"
EPISODES_DIR = "episodes"
# The running-return quantiles the loggers get.
QUANTILES = (0.1, 0.5, 0.9)
# The columns of the episode parts.
_ROW_COLUMNS = ("agent", "episode", "update", *EPISODE_KEYS, "wall_clock_s")


def _pyarrow():
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        # drone-train refuses these launchers typed on its command line before Hydra starts; this is
        # for the other ways here (a launcher chosen in a config file, drone-report on a population run).
        launchers = "|".join(k for k, v in extras.LAUNCHERS.items() if v == extras.POPULATION)
        raise ConfigError(
            extras.missing(f"a population run (hydra/launcher={launchers})", extras.POPULATION)
        ) from None
    return pyarrow


def _return_quantiles(returns: np.ndarray, prefix: str) -> dict[str, float]:
    """``<prefix>/return_q<percent>`` of :data:`QUANTILES` and ``<prefix>/best_return``; {} when none is a number."""
    if not len(returns) or np.isnan(returns).all():
        return {}
    quantiles = zip(QUANTILES, np.nanquantile(returns, QUANTILES), strict=True)
    out = {f"{prefix}/return_q{round(100 * q)}": float(value) for q, value in quantiles}
    return out | {f"{prefix}/best_return": float(np.nanmax(returns))}


class PopulationRecord(Record):
    """The folder and files of a population run (see the module's docstring).

    Args:
        agents: the agents (an :class:`~.agents.AgentTable`, or each agent's validated config).
        names: each agent's name (its job's overrides), for ``agents.parquet``.
        run_dir: the run folder.
        backend: the backend that trains it.
        checkpoint: the population checkpoint to continue from (its state copied into ``state``), or None.
        state: the learner's stacked state.
    """

    kind = POPULATION

    def __init__(
        self,
        agents: AgentTable | Sequence[DictConfig],
        names: Sequence[str],
        run_dir: Path,
        backend: str,
        checkpoint: dict[str, Any] | None = None,
        state: Any = None,
    ) -> None:
        self.pa = _pyarrow()
        if checkpoint is not None:
            with torch.no_grad():  # the weights are a leaf that requires grad
                for key, value in checkpoint["state"].items():
                    state[key].copy_(value)
        agents = AgentTable.of(agents)
        self.cfg = cfg = agents.cfg
        self.run_dir = run_dir = Path(run_dir)
        self.values = agents.values
        self.names = list(names)
        n = len(agents)
        # Every agent's book holds the group's config: the per-agent keys are the table's.
        schedule = Schedule.of(cfg)
        self.agents = [AgentBook(cfg, checkpoint, schedule, self, i) for i in range(n)]
        self.eval_returns = [math.nan] * n
        self.parts = 0 if checkpoint is None else int(checkpoint["parts"])
        self.updates = 0 if checkpoint is None else int(checkpoint["population_updates"])
        # The buffered episode rows, a list per column.
        self.columns: dict[str, list] = {key: [] for key in _ROW_COLUMNS}
        # Failed agent -> its rows of the stacked state in the last checkpoint (finite), kept in
        # the checkpoints that follow instead of its diverged weights.
        self.last_finite: dict[int, dict[str, torch.Tensor]] = {}
        self.open(cfg, run_dir, backend, None if checkpoint is None else self.step)
        with writing(run_dir / EPISODES_DIR):
            (run_dir / EPISODES_DIR).mkdir(exist_ok=True)
        # The parts the checkpoint does not cover (written after it) are trained again.
        past = [p for p in (run_dir / EPISODES_DIR).glob("part-*.parquet") if int(p.stem[5:]) > self.parts]
        for path in past:
            path.unlink()
        self._write_table(
            {"agent": list(range(n)), "name": self.names, **self.values}, run_dir / AGENTS_TABLE
        )
        if cfg.eval.video or cfg.checkpoint.keep_best:
            console.info(
                f"{run_dir}: a population run keeps one stacked checkpoint and no videos, so "
                "checkpoint.keep_best and eval.video do not apply (drone-eval checkpoint=<run> agent=K "
                "renders agent K)",
                **about(run_dir),
            )
        if checkpoint is not None:
            console.info(
                f"{run_dir}: {n} agents continuing from their checkpoint ({self.step} episodes each); "
                f"{len(past)} episode part(s) written after it removed (those episodes are trained again)",
                **about(run_dir),
            )
        # Its search (:mod:`.pbt`), set by the trainer: its lineage goes into each checkpoint and lineage.parquet.
        self.search: Search | None = None

    # ------------------------------------------------------------------ agents
    def add_rows(self, agent: AgentBook, columns: dict[str, Sequence], metrics: dict[str, float]) -> None:
        """Add an agent's update's episode rows to the buffered ones (the summaries are :meth:`after_update`'s)."""
        self.columns["agent"].extend([agent.index] * len(columns["episode"]))
        for key, values in columns.items():
            self.columns[key].extend(values)

    def log_eval(self, agent: AgentBook, result: dict[str, float], learner_state: Any, actor: Any) -> None:
        """Keep an agent's evaluation for :meth:`after_eval` (a population run keeps no best.pt nor videos)."""
        self.eval_returns[agent.index] = result["return"]

    def agent_failed(self, agent: AgentBook) -> None:
        """Keep the failed agent's last finite state, and say so on stderr.

        Its state of the last checkpoint goes into the next ones (none yet: its weights are written
        with their non-finite values zeroed).
        """
        path = self.run_dir / CHECKPOINT_DIR / LAST
        if path.is_file():
            state = load_checkpoint(path)["state"]
            self.last_finite[agent.index] = {key: value[agent.index].clone() for key, value in state.items()}
        console.warning(
            f"{self.run_dir}: agent {agent.index} failed: {TrainingDiverged.__name__}: {agent.failure}",
            **about(self.run_dir),
        )

    # ------------------------------------------------------------------ episodes
    def _write_table(self, columns: dict[str, list], path: Path) -> None:
        """``columns`` as one Parquet file, written whole or not at all."""
        buffer = io.BytesIO()
        self.pa.parquet.write_table(self.pa.table(columns), buffer)
        write_atomically(path, buffer.getbuffer())

    def write_rows(self) -> None:
        """Write the buffered rows as the next episode part."""
        cols = self.columns
        if not cols["agent"]:
            return
        names = np.array([_CAUSE_NAMES[c] for c in sorted(_CAUSE_NAMES)])
        dtypes = {"agent": np.int32, "episode": np.int64, "update": np.int64, "length": np.int64}
        table = {
            k: np.asarray(v, dtype=dtypes.get(k, np.float64))
            for k, v in cols.items()
            if k != "termination_cause"
        }
        table["termination_cause"] = names[np.asarray(cols["termination_cause"], dtype=np.int64)]
        self._write_table(table, self.run_dir / EPISODES_DIR / f"part-{self.parts + 1:06d}.parquet")
        self.parts += 1
        self.columns = {key: [] for key in _ROW_COLUMNS}

    # ------------------------------------------------------------------ summaries
    @property
    def step(self) -> int:
        """The logger's step, the episodes of the agent furthest on (the agents go in step)."""
        return max(agent.episodes_done for agent in self.agents)

    def summary(self) -> dict[str, float]:
        """Quantiles of the agents' running-mean return, the best agent and the number alive."""
        alive = [a for a in self.agents if not a.failed]
        out: dict[str, float] = {"population/alive": float(len(alive))}
        returns = np.array([a.running_return for a in alive], dtype=np.float64)
        out |= _return_quantiles(returns, "population")
        if "population/best_return" in out:
            out["population/best_agent"] = float(alive[int(np.nanargmax(returns))].index)
        return out

    def after_update(self) -> None:
        """One update of the population booked: the summary every ``logger.every_updates``."""
        self.updates += 1
        if self.updates % self.agents[0].every_updates == 0:
            self.logger.log_metrics(self.summary(), step=self.step)
        self.flush_if_due()

    def after_eval(self) -> None:
        """Log the evaluation's quantiles over the agents and the best agent."""
        returns = np.array([r for a, r in zip(self.agents, self.eval_returns, strict=True) if not a.failed])
        if metrics := _return_quantiles(returns, "eval"):
            self.logger.log_metrics(metrics, step=self.step)

    # ------------------------------------------------------------------ checkpoints
    def learner_state(self, learner: Any, agent: int) -> dict[str, Any]:
        """Every agent's stacked state, whichever ``agent`` is due."""
        return dict(learner.state.items())

    def write_last(self, state: dict[str, torch.Tensor]) -> None:
        """Write ``last.pt`` with every agent's stacked state ``[N, ...]``, and the search's lineage so far."""
        super().write_last(state)
        if self.search is not None:  # the lineage as far as the checkpoint: a resume starts there
            self._write_table(self.search.lineage, self.run_dir / LINEAGE_TABLE)

    def final_metrics(self) -> dict[str, float] | None:
        """The final hparams' metrics: the best agent's final return and the :meth:`summary`."""
        finals = [a.final["final_return"] for a in self.agents if a.final is not None]
        return {"final_return_best": max(finals), **self.summary()} if finals else None

    def checkpoint_state(self, state: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The population's checkpoint: ``state``'s stacked tensors, every agent's counters, the search's record."""
        failed = torch.tensor([a.failed for a in self.agents])
        stacked = {}
        for key, tensor in state.items():
            tensor = tensor.detach().cpu()
            if bool(failed.any()):  # a diverged agent's weights are not kept: its last finite ones are
                tensor = tensor.clone()
                if tensor.is_floating_point():
                    tensor[failed] = torch.nan_to_num(tensor[failed], nan=0.0, posinf=0.0, neginf=0.0)
                for agent, rows in self.last_finite.items():
                    tensor[agent] = rows[key]
            stacked[key] = tensor
        return {
            **super().checkpoint_state({"state": stacked}),
            "agents": {"name": self.names, **self.values},
            "parts": self.parts,
            "population_updates": self.updates,
            "search": None if self.search is None else self.search.checkpoint(),
        }


class PopulationFileError(ValueError):
    """A population run's Parquet file that is missing or cannot be read: one line naming it."""


def _read(path: Path, columns: Sequence[str]) -> Any:
    """One Parquet file of a population run as a pyarrow table that has ``columns``.

    :class:`PopulationFileError` (one line naming the file) for a missing, damaged or foreign one.
    """
    pa = _pyarrow()
    try:
        table = pa.parquet.read_table(path)
    except FileNotFoundError:
        raise PopulationFileError(f"{path} is missing") from None
    except (pa.ArrowException, OSError) as err:  # pyarrow's for a damaged file: ArrowInvalid, or its IO error
        # pyarrow names the file first ("Could not open Parquet input source '<path>': <why>").
        reason = first_line(err).rpartition("': ")[2]
        raise PopulationFileError(f"{path} is not a readable Parquet file ({reason})") from None
    if missing := [column for column in columns if column not in table.column_names]:
        raise PopulationFileError(f"{path} is not a population run's table: it has no {', '.join(missing)}")
    return table


def read_episodes(run_dir: Path, parts: int | None = None) -> dict[str, list]:
    """Every episode a population run booked, its parts in the order written: column -> values.

    ``parts``: how many its checkpoint counts (each of ``part-000001`` .. must be there; those
    written after it may follow). :class:`PopulationFileError` for a part missing or damaged.
    """
    pa = _pyarrow()
    folder = Path(run_dir) / EPISODES_DIR
    paths = sorted(folder.glob("part-*.parquet"))
    for number in range(1, (parts or 0) + 1):
        if not (path := folder / f"part-{number:06d}.parquet").is_file():
            raise PopulationFileError(
                f"{path} is missing (the run's checkpoint counts {parts} episode parts)"
            )
    if not paths:
        return {}
    tables = [_read(path, ("agent", "episode", "return")) for path in paths]
    try:
        return pa.concat_tables(tables).to_pydict()
    except pa.ArrowException as err:  # a part of another table's columns or types
        raise PopulationFileError(
            f"{folder}: its parts are not one table ({str(err).strip()[:200]})"
        ) from None


def read_agents(run_dir: Path) -> dict[str, list]:
    """``agents.parquet``: column -> one value per agent (:class:`PopulationFileError` if unreadable)."""
    return _read(Path(run_dir) / AGENTS_TABLE, ("agent", "name")).to_pydict()


def read_table(path: Path) -> dict[str, list]:
    """A Parquet file of a population run (``agents.parquet``, ``lineage.parquet``): column -> values.

    :class:`PopulationFileError` (one line) for a missing or damaged file.
    """
    return _read(Path(path), ()).to_pydict()


def open_agent(key: str, location: Any, agent: Any = None) -> tuple[Path, dict[str, Any]]:
    """Open a checkpoint; of a population run's, its agent ``agent``.

    Opened by :func:`~drone_torchrl.config.open_checkpoint`, the agent taken by
    :func:`agent_checkpoint`; ``agent`` is for population runs only.
    """
    path, state = open_checkpoint(key, location)
    if not is_population(state):
        if agent is not None:
            raise ConfigError.of(
                "agent",
                agent,
                f"null: {path} is one run's checkpoint (agent=K picks an agent of a population run)",
            )
        return path, state
    if agent is None and key == "resume":
        # resume= continues one run; a population is continued, or extended, by its sweep's command.
        sweep = Path(path).parent.parent.parent
        raise ConfigError.of(
            "agent",
            agent,
            f"an agent of the population run {path}, 0..{len(state['episodes_done']) - 1} (it continues "
            "alone, as a fork); to train the whole population on, run its sweep's command again with a "
            f"larger algo.episodes and hydra.sweep.dir={sweep}",
        )
    return path, agent_checkpoint(state, agent, path)


def agent_values(state: dict[str, Any], until: int | None = None) -> dict[str, list]:
    """Each agent's values at the end of a population checkpoint: per-agent key -> one per agent.

    The sweep's values, then those its search (:mod:`.pbt`) gave each agent: the values its weights
    were trained with last (:func:`~.pbt.final_values`). ``until``: after the search's changes up to
    that update only (0: the values training started with; a replay sets them at update 0).
    """
    initial = {key: values for key, values in state["agents"].items() if key != "name"}
    lineage = complete_lineage((state.get("search") or {}).get("lineage"), initial)
    if until is not None:  # rows are appended in update order: a prefix
        rows = sum(update <= until for update in lineage["update"])
        lineage = {column: values[:rows] for column, values in lineage.items()}
    return final_values(lineage, initial)


def agent_checkpoint(state: dict[str, Any], agent: Any, path: Path) -> dict[str, Any]:
    """Agent ``agent`` of a population checkpoint as a run's checkpoint.

    Actor, optimizer, counters, its own config. What ``drone-eval``, ``drone-export`` and ``resume`` read.
    :class:`~.checks.ConfigError` (one line) for an agent the population does not have.
    """
    count = len(state["episodes_done"])
    if isinstance(agent, bool) or not isinstance(agent, int) or not 0 <= agent < count:
        raise ConfigError.of(
            "agent", agent, f"an agent of the population run {path}: an integer 0..{count - 1}"
        )
    cfg = run_config(state["config"])
    for key, values in state["agents"].items():
        if key != "name":
            OmegaConf.update(cfg, key, values[agent])
    # A search's later values of every key it changed (searched or copied with a parent's row).
    for key, values in agent_values(state).items():
        OmegaConf.update(cfg, key, values[agent])
    cfg.device = "cpu"
    one = Population([cfg])
    with torch.no_grad():  # the weights are a leaf that requires grad
        for key, value in state["state"].items():
            one.state[key].copy_(value[agent : agent + 1])
    # Counter-based RNG: the update count is the state.
    learner = {**one.checkpoint_entries(0), "rng": {"torch": None, "env": None, "agent": None}}
    config = OmegaConf.to_container(cfg, resolve=True)
    # Its failure stays the population's: a fork trains on from the agent's last finite state.
    counters = {**agent_counters(state, agent), "failure": None}
    return record_state(RUN, state["backend"], learner, config, [counters])
