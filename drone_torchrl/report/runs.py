"""Reading a sweep's job folders, and grouping their runs into settings.

A report reads only the files a sweep job leaves on disk: ``episodes.csv``
(:func:`drone_torchrl.io.episodes_csv.read_episodes`), ``config.yaml``, ``.hydra/overrides.yaml``
and ``checkpoints/last.pt`` (through :func:`drone_torchrl.training.jobs.job_status`). A population
run (``hydra/launcher=population``: ``agents.parquet``) stands for one run per agent
(:func:`load_population`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from drone_torchrl.checks import first_line
from drone_torchrl.config import ENV_ADDED, ENV_ARGS, env_kwargs
from drone_torchrl.envs.dynamics import REWARD_IN_ZONE
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, CheckpointError, load_checkpoint
from drone_torchrl.io.episodes_csv import CSV_NAME, EpisodeCSVError, read_episodes
from drone_torchrl.training import population_record
from drone_torchrl.training.jobs import job_status, sweep_jobs

CONFIG_FILE = "config.yaml"
HYDRA_DIR = ".hydra"
OVERRIDES_FILE = "overrides.yaml"

SEED_KEY = "seed"
# A run's budget. Not a setting key (a longer run is the same setting, further along), but runs of
# different budgets are not compared: a folder that mixes them is grouped by budget too (group_runs).
BUDGET_KEY = "algo.episodes"
# Overrides that do not define what is trained: the sweep preset and its name, the run length
# (a longer run is the same setting, further along), bookkeeping, and evaluation/checkpoint knobs.
NON_SETTING_KEYS = frozenset(
    {SEED_KEY, "sweep", "sweep_name", BUDGET_KEY, "progress", "threads", "device", "resume"}
)
NON_SETTING_PREFIXES = ("hydra.", "eval.", "checkpoint.")
OVERRIDE_PREFIXES = "+"  # "+key=value" adds and "++key=value" forces a key: the same setting key
SINGLE_SETTING_LABEL = "all"
NO_OVERRIDES_LABEL = "defaults"
LABEL_SEPARATOR = ", "

# What drone_torchrl.training.jobs.job_status says of a job.
STATUS_FINISHED = "finished"
STATUS_FAILED = "failed"
STATUS_UNFINISHED = "unfinished"

# episodes.csv columns the report uses (drone_torchrl.io.episodes_csv.CSV_COLUMNS).
COL_RETURN = "return"
COL_LENGTH = "length"
COL_NEGATIVE_THRUST = "negative_thrust_fraction"
COL_WALL_CLOCK = "wall_clock_s"


class ReportError(Exception):
    """A sweep folder that cannot be reported: the message is one line naming the folder or file."""


# --------------------------------------------------------------------------------------------------
# Reading jobs


@dataclass
class Run:
    """One job folder of a sweep: its overrides, resolved config, status and episode columns."""

    job_dir: Path
    overrides: list[str]
    config: dict[str, Any]
    status: str
    columns: dict[str, np.ndarray]
    """Every ``episodes.csv`` column, ordered by episode."""
    notes: list[str] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        """Number of episodes in the run's ``episodes.csv``."""
        return int(self.columns[COL_RETURN].size)

    @property
    def seed(self) -> Any:
        """The run's seed (from its config, else its overrides)."""
        given = {k.lstrip(OVERRIDE_PREFIXES): v for k, _, v in (o.partition("=") for o in self.overrides)}
        return self.config.get(SEED_KEY, given.get(SEED_KEY))

    def _required(self, key: str) -> Any:
        found, value = _lookup(self.config, key)
        if not found:
            raise ReportError(f"{self.job_dir}: its config has no {key}")
        return value

    @property
    def budget(self) -> Any:
        """The run's ``algo.episodes`` (``None`` if its config has none)."""
        return _lookup(self.config, BUDGET_KEY)[1]

    @property
    def max_steps(self) -> int:
        """The run's ``env.max_steps``."""
        return int(self._required("env.max_steps"))

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The ``DroneEnv`` arguments of the run (:func:`drone_torchrl.config.env_kwargs`).

        A run from before an argument existed gets the value it ran with
        (:data:`~drone_torchrl.config.ENV_ADDED`).
        """
        for name in ENV_ARGS:  # a config without one of them: a one-line error, not a KeyError
            if name not in ENV_ADDED:
                self._required(f"env.{name}")
        return env_kwargs(self.config)


def _load_yaml(path: Path, kind: type) -> Any:
    """A YAML file as plain data of ``kind`` (dict or list); :class:`ReportError` if it is not one."""
    try:
        cfg = OmegaConf.load(path)
    except Exception as err:  # noqa: BLE001  (yaml and OmegaConf raise many kinds for a bad file)
        first = first_line(err)
        raise ReportError(f"{path} is not a readable YAML file ({first})") from None
    if kind is list and isinstance(cfg, DictConfig) and not cfg:
        return []  # an empty file: no overrides
    if not isinstance(cfg, DictConfig if kind is dict else ListConfig):
        raise ReportError(f"{path} does not hold a YAML {'mapping' if kind is dict else 'list'}")
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - Hydra-only interpolations (${hydra:...}) stay unresolved
        return OmegaConf.to_container(cfg, resolve=False)


def load_population(run_dir: Path) -> list[Run]:
    """A population run's agents, each as the run it would be in a folder of its own.

    Its job's overrides, the group's config with its per-agent values, its status and its episodes.
    An agent of a search (PBT, halving, a replay: :mod:`~drone_torchrl.training.pbt`) stands with the
    values it was trained with at the end (its overrides and config name them; a note names the
    values it started with where they differ).
    """
    path = run_dir / CHECKPOINT_DIR / LAST
    try:
        # Its agents' statuses and a search's values are in it: a damaged one is not "no checkpoint".
        checkpoint = load_checkpoint(path) if path.is_file() else None
        agents = population_record.read_agents(run_dir)
        rows = population_record.read_episodes(run_dir, None if checkpoint is None else checkpoint["parts"])
    except (CheckpointError, population_record.PopulationFileError) as err:
        raise ReportError(f"{err}: the population run {run_dir} cannot be reported") from None
    config = _load_yaml(run_dir / CONFIG_FILE, dict)
    searched = checkpoint is not None and bool(checkpoint.get("search"))
    final = population_record.agent_values(checkpoint) if searched else {}
    first = population_record.agent_values(checkpoint, until=0) if searched else {}
    columns = {key: np.asarray(values) for key, values in rows.items()}
    owner = columns.get("agent", np.zeros(0, dtype=int))
    runs = []
    for k, name in zip(agents["agent"], agents["name"], strict=True):
        own = OmegaConf.create(config)
        for key, values in agents.items():
            if key not in ("agent", "name"):
                OmegaConf.update(own, key, final.get(key, values)[k])
        overrides, notes = name.split(), []
        if final:  # every changed key named, so that every agent's setting has the same keys
            overrides = [o for o in overrides if o.partition("=")[0].lstrip(OVERRIDE_PREFIXES) not in final]
            overrides += [f"{key}={format_value(values[k])}" for key, values in final.items()]
            started = [
                f"{key}={format_value(first[key][k])}" for key in final if first[key][k] != final[key][k]
            ]
            if started:
                notes.append(f"agent {k} of {run_dir.name} started as {' '.join(started)}")
        mine = np.flatnonzero(owner == k)
        mine = mine[np.argsort(columns["episode"][mine], kind="stable")]
        failed = checkpoint is not None and checkpoint["failure"][k] is not None
        finished = checkpoint is not None and checkpoint["final"][k] is not None
        status = STATUS_FAILED if failed else STATUS_FINISHED if finished else STATUS_UNFINISHED
        agent_columns = {key: values[mine] for key, values in columns.items() if key != "agent"}
        runs.append(Run(run_dir, overrides, OmegaConf.to_container(own), status, agent_columns, notes))
    return runs


def load_run(job_dir: Path) -> Run | None:
    """Read one job folder; ``None`` if it has no ``episodes.csv`` (not started, or failed early)."""
    csv_path = job_dir / CSV_NAME
    if not csv_path.is_file():
        return None
    overrides_path = job_dir / HYDRA_DIR / OVERRIDES_FILE
    overrides = [str(o) for o in _load_yaml(overrides_path, list)] if overrides_path.is_file() else []
    for config_path in (job_dir / CONFIG_FILE, job_dir / HYDRA_DIR / CONFIG_FILE):
        if config_path.is_file():
            config = _load_yaml(config_path, dict)
            break
    else:
        raise ReportError(f"{job_dir} has an {CSV_NAME} but no {CONFIG_FILE}")
    try:
        columns, notes = read_episodes(csv_path)
    except EpisodeCSVError as err:
        raise ReportError(str(err)) from None
    return Run(job_dir, overrides, config, job_status(job_dir)[0], columns, notes)


def find_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders of a sweep; a single job folder stands for itself.

    A sweep's job folders are those of :func:`~drone_torchrl.training.jobs.sweep_jobs`.
    """
    jobs = sweep_jobs(sweep_dir)
    return jobs if jobs or not (sweep_dir / HYDRA_DIR).is_dir() else [sweep_dir]


def failed_without_episodes(sweep_dir: Path) -> list[tuple[Path, str]]:
    """``(job folder, reason)`` of the jobs that failed before writing any episode.

    Say, a bad value found only in the job, or a full disk. They have no ``episodes.csv``, so no place in a figure.
    """
    statuses = [
        (job, job_status(job)) for job in find_jobs(Path(sweep_dir)) if not (job / CSV_NAME).is_file()
    ]
    return [(job, detail) for job, (status, detail) in statuses if status == STATUS_FAILED]


def load_runs(sweep_dir: Path) -> list[Run]:
    """Every job of ``sweep_dir`` that has an ``episodes.csv``.

    Raises :class:`ReportError` if the folder does not exist or holds no such job.
    """
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise ReportError(f"{sweep_dir} does not exist or is not a folder")
    runs = []
    for job in find_jobs(sweep_dir):
        # A population run, also one whose agents.parquet is gone (load_population says so).
        if (job / population_record.AGENTS_TABLE).is_file() or (
            job / population_record.EPISODES_DIR
        ).is_dir():
            runs += load_population(job)
        elif (run := load_run(job)) is not None:
            runs.append(run)
    if not runs:
        failed = failed_without_episodes(sweep_dir)
        why = (
            f" ({len(failed)} job(s) failed before their first episode; {failed[0][0]}: {failed[0][1]})"
            if failed
            else ""
        )
        raise ReportError(f"{sweep_dir} holds no job folder with an {CSV_NAME}{why}")
    if not any(run.episodes for run in runs):
        raise ReportError(f"{sweep_dir}: its jobs' {CSV_NAME} files hold no episode yet")
    return runs


# --------------------------------------------------------------------------------------------------
# Settings


def _lookup(config: dict[str, Any], key: str) -> tuple[bool, Any]:
    node: Any = config
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return False, None
        node = node[part]
    return True, node


def format_value(value: Any) -> str:
    """A config value in Hydra's override syntax (``0.0001``, ``5e-05``, ``null``, ``[32,32]``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ",".join(format_value(v) for v in value) + "]"
    return str(value)


def setting_of(overrides: Sequence[str], config: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    """The ``(key, value)`` pairs that define a job's setting, in override order.

    Values come from the resolved config when the key is there (so ``1e-3`` and ``0.001`` agree),
    else from the override string (config-group choices such as ``experiment=bounded``).
    """
    pairs = []
    for item in overrides:
        name, _, raw = item.partition("=")
        key = name.lstrip(OVERRIDE_PREFIXES)
        if key in NON_SETTING_KEYS or key.startswith(NON_SETTING_PREFIXES):
            continue
        found, value = _lookup(config, key)
        pairs.append((key, format_value(value) if found else raw))
    return tuple(pairs)


@dataclass
class Setting:
    """The runs (one per seed) of one setting, and its label in figures and tables."""

    label: str
    pairs: tuple[tuple[str, str], ...]
    runs: list[Run]

    @property
    def max_steps(self) -> int:
        """The setting's ``env.max_steps`` (its first run's)."""
        return self.runs[0].max_steps

    @property
    def ceiling(self) -> float:
        """The highest possible return, ``REWARD_IN_ZONE * max_steps`` (3000 for 300 steps)."""
        return REWARD_IN_ZONE * self.max_steps

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The setting's ``DroneEnv`` arguments (its first run's)."""
        return self.runs[0].env_kwargs

    @property
    def runs_with_episodes(self) -> list[Run]:
        """The setting's runs that have episodes."""
        return [run for run in self.runs if run.episodes]


def _sort_key(value: str | None) -> tuple[int, float, str]:
    if value is None:
        return (2, 0.0, "")
    try:
        return (0, float(value), "")
    except ValueError:
        return (1, 0.0, value)


def mixed_budgets(runs: Sequence[Run]) -> str | None:
    """The line saying that ``runs`` mix budgets (``algo.episodes=2, 3``), or ``None`` if they do not."""
    found = sorted({run.budget for run in runs if run.budget is not None}, key=lambda b: _sort_key(str(b)))
    if len(found) < 2:
        return None
    return f"its runs mix budgets ({BUDGET_KEY}={LABEL_SEPARATOR.join(format_value(b) for b in found)})"


def group_runs(runs: Sequence[Run]) -> list[Setting]:
    """Group runs by setting (overrides minus the seed and non-setting keys) and label the groups.

    A label lists only the overrides that differ between settings; ``all`` when there is one
    setting (``defaults`` for a setting without any of the differing overrides). Settings are
    sorted by their differing values, numerically where they are numbers. Runs of different
    budgets (:func:`mixed_budgets`) are different settings, labelled with their ``algo.episodes``.
    """
    by_budget = mixed_budgets(runs) is not None
    groups: dict[tuple[tuple[str, str], ...], list[Run]] = {}
    for run in runs:
        pairs = setting_of(run.overrides, run.config)
        if by_budget:
            pairs += ((BUDGET_KEY, format_value(run.budget)),)
        groups.setdefault(pairs, []).append(run)
    keys = list(dict.fromkeys(k for pairs in groups for k, _ in pairs))
    values = [dict(pairs) for pairs in groups]
    differing = [k for k in keys if len({v.get(k) for v in values}) > 1]
    settings = []
    for pairs, members in groups.items():
        mapping = dict(pairs)
        label = LABEL_SEPARATOR.join(f"{k}={mapping[k]}" for k in differing if k in mapping)
        if not label:
            label = SINGLE_SETTING_LABEL if len(groups) == 1 else NO_OVERRIDES_LABEL
        members.sort(key=lambda r: _sort_key(str(r.seed)))
        settings.append(Setting(label, pairs, members))
    settings.sort(key=lambda s: [_sort_key(dict(s.pairs).get(k)) for k in differing])
    return settings
