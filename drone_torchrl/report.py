"""``drone-report``: figures and a summary table of hyper-parameter sweeps (SPEC.md, section 4.1).

drone-report multirun/lr                      # figures + table into multirun/lr/report/
drone-report multirun/lr multirun/gamma       # one report per sweep, each in <sweep>/report/
drone-report multirun/lr --out /tmp/lr --window 50 --return-threshold 2500 --no-pd

It reads only the files a sweep job leaves on disk (``episodes.csv``, ``config.yaml``,
``.hydra/overrides.yaml`` and ``checkpoints/last.pt`` through :func:`drone_torchrl.sweep.job_status`),
so it works on sweeps that are still running and on jobs trained by any engine writing those files.

Method:

1. **Settings.** Jobs are grouped by their command-line overrides minus the seed and minus keys
   that do not change what is trained (:data:`NON_SETTING_KEYS`, :data:`NON_SETTING_PREFIXES`).
   Values are read back from the job's resolved ``config.yaml`` when the key is there, so
   ``algo.lr=1e-3`` and ``algo.lr=0.001`` are the same setting. A setting's label keeps only the
   overrides that differ between settings (``algo.lr=0.001``); a single setting is labelled
   ``all``.
2. **Curves.** Per run, the running mean over ``window`` episodes (default
   ``metrics.running_mean_window`` of ``conf/config.yaml``, the paper's 100) of the episode length,
   return and negative-thrust fraction. The window is *trailing*, and over the first
   ``window - 1`` episodes it averages the episodes available so far (pandas'
   ``rolling(window, min_periods=1)``), which is also what ``drone-train`` logs as its running
   mean. Consequence: a threshold can be crossed early by a short lucky start; the crossing
   episodes below are read off exactly these curves. Then, per episode index (0-based, as in
   ``episodes.csv``), the mean, population std (``ddof=0``), min and max over the seeds that have
   reached that episode: runs of different lengths (unfinished, failed) contribute where they have
   data, and the report says how many seeds are unfinished and how far the shortest got.
3. **Table.** Per setting: seeds finished/total, the final running-mean return (each run's last
   value; mean +- std over seeds, and as a percentage of the ``10 * max_steps`` ceiling), the first
   episode at which the running-mean length reaches ``max_steps`` and the running-mean return
   reaches ``return_threshold`` (mean over the seeds that reach it, and how many do), the final
   running-mean negative-thrust fraction, and the wall-clock time (each run's last
   ``wall_clock_s``; mean per run and total). The verdict names the setting with the best mean
   final running-mean return.
4. **Figures.** ``steps.png`` and ``returns.png`` like the paper's figures 4.2 and 4.4: one curve per
   setting with a mean +- std band, the ``max_steps`` cap and the ``10 * max_steps`` ceiling as
   dashed lines, and the PD hover controller's mean return (:func:`evaluate_pd`, 100 episodes,
   seed 0, on the jobs' env settings) as a dotted reference line.
"""

from __future__ import annotations

import argparse
import csv
import functools
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from drone_torchrl.envs.dynamics import REWARD_IN_ZONE
from drone_torchrl.sweep import job_status, sweep_jobs

PROG = "drone-report"
EXIT_ERROR = 2

REPORT_DIR = "report"
EPISODES_CSV = "episodes.csv"
CONFIG_FILE = "config.yaml"
HYDRA_DIR = ".hydra"
OVERRIDES_FILE = "overrides.yaml"
STEPS_FIGURE = "steps.png"
RETURNS_FIGURE = "returns.png"
SUMMARY_MD = "summary.md"
SUMMARY_CSV = "summary.csv"

SEED_KEY = "seed"
# Overrides that do not define what is trained: the sweep preset and its name, the run length
# (a longer run is the same setting, further along), bookkeeping, and evaluation/checkpoint knobs.
NON_SETTING_KEYS = frozenset(
    {SEED_KEY, "sweep", "sweep_name", "algo.episodes", "progress", "threads", "device", "resume"}
)
NON_SETTING_PREFIXES = ("hydra.", "eval.", "checkpoint.")
OVERRIDE_PREFIXES = "+"  # "+key=value" adds and "++key=value" forces a key: the same setting key
SINGLE_SETTING_LABEL = "all"
NO_OVERRIDES_LABEL = "defaults"
LABEL_SEPARATOR = ", "

STATUS_FINISHED = "finished"
STATUS_FAILED = "failed"
STATUS_UNFINISHED = "unfinished"

# CSV columns the report needs (a subset of drone_torchrl.metrics.CSV_COLUMNS).
COL_EPISODE = "episode"
COL_RETURN = "return"
COL_LENGTH = "length"
COL_NEGATIVE_THRUST = "negative_thrust_fraction"
COL_WALL_CLOCK = "wall_clock_s"
CURVE_COLUMNS = (COL_LENGTH, COL_RETURN, COL_NEGATIVE_THRUST)
REQUIRED_COLUMNS = (COL_EPISODE, *CURVE_COLUMNS, COL_WALL_CLOCK)

DEFAULT_RETURN_THRESHOLD = 2000.0
STD_DDOF = 0  # population std over seeds: a single seed has zero spread rather than NaN
# A running mean "reaches" a threshold within this relative tolerance (float sums of integers).
CROSSING_RTOL = 1e-9

PD_EPISODES = 100
PD_SEED = 0
ENV_KEYS_NOT_PHYSICS = ("num_workers",)  # config env.* keys that are not DroneEnv physics

FIGURE_SIZE = (9.0, 5.5)
FIGURE_DPI = 120
BAND_ALPHA = 0.2
LINE_WIDTH = 1.5
REFERENCE_COLOR = "black"
PD_COLOR = "dimgray"
PERCENT = 100.0
SECONDS_PER_MINUTE = 60.0
SECONDS_PER_HOUR = 3600.0
LARGE_VALUE = 100.0  # values at least this large are printed without decimals


class ReportError(Exception):
    """A sweep folder that cannot be reported: the message is one line naming the folder or file."""


# --------------------------------------------------------------------------------------------------
# Numbers


def running_mean(values: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """Trailing running mean over ``window`` values; the first ``window - 1`` average what exists.

    Same as pandas ``Series.rolling(window, min_periods=1).mean()``:
    ``running_mean([0, 3, 6, 9], 3) == [0, 1.5, 3, 6]``.
    """
    if window < 1:
        raise ValueError(f"window={window} is not allowed; expected an integer >= 1")
    x = np.asarray(values, dtype=np.float64)
    cumulative = np.concatenate(([0.0], np.cumsum(x)))
    end = np.arange(1, x.size + 1)
    start = np.maximum(end - window, 0)
    return (cumulative[end] - cumulative[start]) / (end - start)


def first_crossing(values: Sequence[float] | np.ndarray, threshold: float) -> int | None:
    """Index of the first value ``>= threshold`` (within :data:`CROSSING_RTOL`), or ``None``."""
    x = np.asarray(values, dtype=np.float64)
    tolerance = CROSSING_RTOL * max(abs(threshold), 1.0)
    hits = np.flatnonzero(x >= threshold - tolerance)
    return int(hits[0]) if hits.size else None


@dataclass
class SeedStats:
    """Per-episode statistics over the seeds that reached each episode (arrays of equal length)."""

    mean: np.ndarray
    std: np.ndarray
    min: np.ndarray
    max: np.ndarray
    count: np.ndarray
    """How many seeds contribute at each episode."""


def aggregate_over_seeds(curves: Sequence[np.ndarray]) -> SeedStats:
    """Mean, std (``ddof=0``), min and max per episode over curves of possibly different lengths.

    Episode ``i`` is summarised over the curves longer than ``i``; the result is as long as the
    longest curve.
    """
    curves = [np.asarray(c, dtype=np.float64) for c in curves if len(c)]
    if not curves:
        empty = np.zeros(0)
        return SeedStats(empty, empty, empty, empty, np.zeros(0, dtype=np.int64))
    length = max(c.size for c in curves)
    table = np.full((len(curves), length), np.nan)
    for row, curve in zip(table, curves, strict=True):
        row[: curve.size] = curve
    return SeedStats(
        mean=np.nanmean(table, 0),
        std=np.nanstd(table, 0, ddof=STD_DDOF),
        min=np.nanmin(table, 0),
        max=np.nanmax(table, 0),
        count=(~np.isnan(table)).sum(0),
    )


# --------------------------------------------------------------------------------------------------
# Reading jobs


@dataclass
class Run:
    """One job folder of a sweep: its overrides, resolved config, status and episode columns."""

    job_dir: Path
    overrides: list[str]
    config: dict[str, Any]
    status: str
    status_detail: str
    columns: dict[str, np.ndarray]
    notes: list[str] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        return int(self.columns[COL_RETURN].size)

    @property
    def seed(self) -> Any:
        return self.config.get(SEED_KEY, override_value(self.overrides, SEED_KEY))

    @property
    def max_steps(self) -> int:
        found, value = _lookup(self.config, "env.max_steps")
        if not found:
            raise ReportError(f"{self.job_dir}: its config has no env.max_steps")
        return int(value)

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The ``DroneEnv`` arguments of the run: its ``env.*`` config minus non-physics keys."""
        return {k: v for k, v in self.config["env"].items() if k not in ENV_KEYS_NOT_PHYSICS}

    def wall_clock(self) -> float | None:
        """The run's last ``wall_clock_s`` (``None`` without episodes)."""
        return float(self.columns[COL_WALL_CLOCK][-1]) if self.episodes else None


def read_episodes(path: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """The report's columns of an ``episodes.csv`` as float arrays, ordered by episode, and notes.

    Tolerant of a run being written: reading stops at the first row that does not parse (a line
    still being appended). Duplicate episode indices keep their last row; the rows stop at the
    first gap in the episode indices (noted).
    """
    notes: list[str] = []
    with Path(path).open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in REQUIRED_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ReportError(f"{path} lacks the column(s) {', '.join(missing)}")
        by_episode: dict[int, list[float]] = {}
        for row in reader:
            try:
                values = [float(row[c]) for c in REQUIRED_COLUMNS]
            except (TypeError, ValueError):
                break
            by_episode[int(values[0])] = values[1:]
    ordered = sorted(by_episode)
    contiguous = 0
    while contiguous < len(ordered) and ordered[contiguous] == contiguous:
        contiguous += 1
    if contiguous < len(ordered):
        notes.append(f"{path}: episode indices have a gap; using episodes 0-{contiguous - 1}")
    data = np.array([by_episode[e] for e in ordered[:contiguous]], dtype=np.float64).reshape(
        contiguous, len(REQUIRED_COLUMNS) - 1
    )
    return {name: data[:, i] for i, name in enumerate(REQUIRED_COLUMNS[1:])}, notes


def _load_yaml(path: Path) -> Any:
    cfg = OmegaConf.load(path)
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # noqa: BLE001 - Hydra-only interpolations (${hydra:...}) stay unresolved
        return OmegaConf.to_container(cfg, resolve=False)


def override_value(overrides: Sequence[str], key: str) -> str | None:
    """The raw value of ``key`` (or ``+key``/``++key``) among ``key=value`` override strings."""
    for item in overrides:
        name, _, value = item.partition("=")
        if name.lstrip(OVERRIDE_PREFIXES) == key:
            return value
    return None


def load_run(job_dir: Path) -> Run | None:
    """Read one job folder; ``None`` if it has no ``episodes.csv`` (not started, or failed early)."""
    job_dir = Path(job_dir)
    csv_path = job_dir / EPISODES_CSV
    if not csv_path.is_file():
        return None
    overrides_path = job_dir / HYDRA_DIR / OVERRIDES_FILE
    overrides = [str(o) for o in (_load_yaml(overrides_path) or [])] if overrides_path.is_file() else []
    for config_path in (job_dir / CONFIG_FILE, job_dir / HYDRA_DIR / CONFIG_FILE):
        if config_path.is_file():
            config = _load_yaml(config_path)
            break
    else:
        raise ReportError(f"{job_dir} has an {EPISODES_CSV} but no {CONFIG_FILE}")
    try:
        status, detail = job_status(job_dir)
    except Exception as err:  # noqa: BLE001 - an unreadable checkpoint: the run is not known finished
        status, detail = STATUS_UNFINISHED, f"unreadable checkpoint ({type(err).__name__})"
    columns, notes = read_episodes(csv_path)
    return Run(job_dir, overrides, config, status, detail, columns, notes)


def find_jobs(sweep_dir: Path) -> list[Path]:
    """Job folders of a sweep (:func:`sweep_jobs`); a single job folder stands for itself."""
    sweep_dir = Path(sweep_dir)
    jobs = sweep_jobs(sweep_dir)
    if not jobs and (sweep_dir / HYDRA_DIR).is_dir():
        jobs = [sweep_dir]
    return jobs


def load_runs(sweep_dir: Path) -> list[Run]:
    """Every job of ``sweep_dir`` that has an ``episodes.csv``.

    Raises :class:`ReportError` if the folder does not exist or holds no such job.
    """
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise ReportError(f"{sweep_dir} does not exist or is not a folder")
    runs = [run for job in find_jobs(sweep_dir) if (run := load_run(job)) is not None]
    if not runs:
        raise ReportError(f"{sweep_dir} holds no job folder with an {EPISODES_CSV}")
    if not any(run.episodes for run in runs):
        raise ReportError(f"{sweep_dir}: its jobs' {EPISODES_CSV} files hold no episode yet")
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


def is_setting_key(key: str) -> bool:
    """Whether an override key defines a setting (not the seed, the sweep preset, bookkeeping...)."""
    return key not in NON_SETTING_KEYS and not key.startswith(NON_SETTING_PREFIXES)


def setting_of(overrides: Sequence[str], config: dict[str, Any]) -> tuple[tuple[str, str], ...]:
    """The ``(key, value)`` pairs that define a job's setting, in override order.

    Values come from the resolved config when the key is there (so ``1e-3`` and ``0.001`` agree),
    else from the override string (config-group choices such as ``experiment=bounded``).
    """
    pairs = []
    for item in overrides:
        name, _, raw = item.partition("=")
        key = name.lstrip(OVERRIDE_PREFIXES)
        if not is_setting_key(key):
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
        return self.runs[0].max_steps

    @property
    def ceiling(self) -> float:
        """The highest possible return, ``REWARD_IN_ZONE * max_steps`` (3000 for 300 steps)."""
        return REWARD_IN_ZONE * self.max_steps

    @property
    def env_kwargs(self) -> dict[str, Any]:
        return self.runs[0].env_kwargs

    @property
    def runs_with_episodes(self) -> list[Run]:
        return [run for run in self.runs if run.episodes]

    def curve(self, column: str, window: int) -> SeedStats:
        """Running mean of ``column`` per run, aggregated per episode over the seeds."""
        return aggregate_over_seeds(
            [running_mean(r.columns[column], window) for r in self.runs_with_episodes]
        )


def _sort_key(value: str | None) -> tuple[int, float, str]:
    if value is None:
        return (2, 0.0, "")
    try:
        return (0, float(value), "")
    except ValueError:
        return (1, 0.0, value)


def group_runs(runs: Sequence[Run]) -> list[Setting]:
    """Group runs by setting (overrides minus the seed and non-setting keys) and label the groups.

    A label lists only the overrides that differ between settings; ``all`` when there is one
    setting (``defaults`` for a setting without any of the differing overrides). Settings are
    sorted by their differing values, numerically where they are numbers.
    """
    groups: dict[tuple[tuple[str, str], ...], list[Run]] = {}
    for run in runs:
        groups.setdefault(setting_of(run.overrides, run.config), []).append(run)
    keys: list[str] = []
    for pairs in groups:
        keys.extend(k for k, _ in pairs if k not in keys)
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


# --------------------------------------------------------------------------------------------------
# Summary


@dataclass
class Crossing:
    """When the runs of a setting first reach a threshold."""

    threshold: float
    episodes: list[int]
    """First crossing episode of each run that reaches the threshold."""
    runs: int
    """Runs considered (those with episodes)."""

    @property
    def mean(self) -> float | None:
        return float(np.mean(self.episodes)) if self.episodes else None

    def text(self) -> str:
        reached = f"({len(self.episodes)}/{self.runs} seeds)"
        return f"{self.mean:.0f} {reached}" if self.episodes else f"never {reached}"


@dataclass
class SettingSummary:
    """One row of the summary table."""

    label: str
    seeds_finished: int
    seeds_total: int
    episodes_min: int
    episodes_max: int
    max_steps: int
    ceiling: float
    final_returns: list[float]
    length_cap: Crossing
    return_threshold: Crossing
    final_negative_thrust: float
    wall_clock_mean_s: float
    wall_clock_total_s: float
    notes: list[str]

    @property
    def final_return_mean(self) -> float:
        return float(np.mean(self.final_returns)) if self.final_returns else math.nan

    @property
    def final_return_std(self) -> float:
        return float(np.std(self.final_returns, ddof=STD_DDOF)) if self.final_returns else math.nan

    @property
    def final_return_pct(self) -> float:
        return PERCENT * self.final_return_mean / self.ceiling

    def return_text(self) -> str:
        """``"2210 +- 150"``."""
        return (
            f"{_number(self.final_return_mean)} +- {_number(self.final_return_std, self.final_return_mean)}"
        )


def _number(value: float, scale: float | None = None) -> str:
    """No decimals for large numbers (``2210``), one for small ones (``5.7``)."""
    if value is None or math.isnan(value):
        return "-"
    magnitude = abs(value if scale is None else scale)
    return f"{value:.0f}" if magnitude >= LARGE_VALUE else f"{value:.1f}"


def _duration(seconds: float) -> str:
    if math.isnan(seconds):
        return "-"
    if seconds >= SECONDS_PER_HOUR:
        return f"{seconds / SECONDS_PER_HOUR:.1f} h"
    if seconds >= SECONDS_PER_MINUTE:
        return f"{seconds / SECONDS_PER_MINUTE:.1f} min"
    return f"{seconds:.1f} s"


def progress_notes(setting: Setting) -> list[str]:
    """Unfinished and failed seeds, e.g. ``"2 of 4 seeds unfinished, shortest at 1200 episodes"``."""
    notes = []
    total = len(setting.runs)
    unfinished = [r for r in setting.runs if r.status == STATUS_UNFINISHED]
    failed = [r for r in setting.runs if r.status == STATUS_FAILED]
    if unfinished:
        shortest = min(r.episodes for r in unfinished)
        notes.append(f"{len(unfinished)} of {total} seeds unfinished, shortest at {shortest} episodes")
    if failed:
        shortest = min(r.episodes for r in failed)
        notes.append(f"{len(failed)} of {total} seeds failed, shortest at {shortest} episodes")
    for run in setting.runs:
        if not run.episodes:
            notes.append(f"seed {run.seed} has no episode yet")
        notes.extend(run.notes)
    return notes


def summarize(
    setting: Setting, window: int, return_threshold: float = DEFAULT_RETURN_THRESHOLD
) -> SettingSummary:
    """The table row of one setting (see the module docstring for the definitions)."""
    runs = setting.runs_with_episodes
    lengths = [running_mean(r.columns[COL_LENGTH], window) for r in runs]
    returns = [running_mean(r.columns[COL_RETURN], window) for r in runs]
    negative = [running_mean(r.columns[COL_NEGATIVE_THRUST], window)[-1] for r in runs]
    clocks = [r.wall_clock() for r in runs]

    def crossing(curves: list[np.ndarray], threshold: float) -> Crossing:
        hits = [first_crossing(c, threshold) for c in curves]
        return Crossing(threshold, [h for h in hits if h is not None], len(curves))

    episodes = [r.episodes for r in setting.runs]
    return SettingSummary(
        label=setting.label,
        seeds_finished=sum(r.status == STATUS_FINISHED for r in setting.runs),
        seeds_total=len(setting.runs),
        episodes_min=min(episodes),
        episodes_max=max(episodes),
        max_steps=setting.max_steps,
        ceiling=setting.ceiling,
        final_returns=[float(c[-1]) for c in returns],
        length_cap=crossing(lengths, setting.max_steps),
        return_threshold=crossing(returns, return_threshold),
        final_negative_thrust=float(np.mean(negative)) if negative else math.nan,
        wall_clock_mean_s=float(np.mean(clocks)) if clocks else math.nan,
        wall_clock_total_s=float(np.sum(clocks)) if clocks else math.nan,
        notes=progress_notes(setting),
    )


def verdict(summaries: Sequence[SettingSummary]) -> str:
    """``"best: algo.lr=0.0001 (2210 +- 150, 73.7% of 3000)"``: the best mean final running-mean return.

    Names settings tied with the best, and says the verdict is provisional when some runs are
    unfinished or failed (their finals are taken where they stopped).
    """
    candidates = [s for s in summaries if s.final_returns]
    if not candidates:
        return "best: none (no episodes yet)"
    best = max(candidates, key=lambda s: s.final_return_mean)
    line = f"best: {best.label} ({best.return_text()}, {best.final_return_pct:.1f}% of {best.ceiling:g})"
    tied = [s.label for s in candidates if s is not best and s.final_return_mean == best.final_return_mean]
    if tied:
        line += f"; tied with {LABEL_SEPARATOR.join(tied)}"
    total = sum(s.seeds_total for s in summaries)
    pending = total - sum(s.seeds_finished for s in summaries)
    if pending:
        line += f"; provisional: {pending} of {total} runs not finished"
    return line


# --------------------------------------------------------------------------------------------------
# PD reference


@functools.cache
def _pd_return(env_items: tuple[tuple[str, Any], ...]) -> float:
    from drone_torchrl.envs.heuristic import evaluate_pd

    return evaluate_pd(dict(env_items), episodes=PD_EPISODES, seed=PD_SEED)["return_mean"]


def pd_reference(env_kwargs: dict[str, Any]) -> float:
    """Mean return of the PD hover controller (:func:`evaluate_pd`, 100 episodes, seed 0).

    Computed once per distinct env setting in this process (cached).
    """
    return _pd_return(tuple(sorted(env_kwargs.items())))


# --------------------------------------------------------------------------------------------------
# The report of one sweep


@dataclass
class SweepReport:
    """Everything reported about one sweep folder."""

    sweep_dir: Path
    window: int
    return_threshold: float
    settings: list[Setting]
    summaries: list[SettingSummary]
    pd_returns: dict[str, float]
    """PD reference return per distinct env setting, keyed by the labels of the settings using it."""

    @property
    def name(self) -> str:
        return self.sweep_dir.resolve().name

    @property
    def verdict(self) -> str:
        return verdict(self.summaries)


def default_window() -> int:
    """``metrics.running_mean_window`` of the package's ``conf/config.yaml`` (the paper's 100)."""
    from drone_torchrl.config import config_dir

    return int(OmegaConf.load(Path(config_dir()) / "config.yaml").metrics.running_mean_window)


def build_report(
    sweep_dir: Path,
    window: int | None = None,
    return_threshold: float = DEFAULT_RETURN_THRESHOLD,
    pd: bool = True,
    runs: Sequence[Run] | None = None,
) -> SweepReport:
    """Read a sweep folder (or use its already loaded ``runs``) and compute its settings, table
    rows and PD references; ``window=None`` is :func:`default_window`."""
    window = default_window() if window is None else window
    runs = load_runs(Path(sweep_dir)) if runs is None else runs
    settings = group_runs(runs)
    summaries = [summarize(s, window, return_threshold) for s in settings]
    pd_returns: dict[str, float] = {}
    if pd:
        by_env: dict[tuple, list[str]] = {}
        for s in settings:
            by_env.setdefault(tuple(sorted(s.env_kwargs.items())), []).append(s.label)
        for env_items, labels in by_env.items():
            key = "PD controller" if len(by_env) == 1 else f"PD controller ({LABEL_SEPARATOR.join(labels)})"
            pd_returns[key] = pd_reference(dict(env_items))
    return SweepReport(Path(sweep_dir), window, return_threshold, settings, summaries, pd_returns)


# --------------------------------------------------------------------------------------------------
# Figures


def _legend_label(setting: Setting) -> str:
    n = len(setting.runs)
    pending = n - sum(r.status == STATUS_FINISHED for r in setting.runs)
    seeds = f"{n} seed{'s' if n != 1 else ''}"
    return f"{setting.label} ({seeds}, {pending} not finished)" if pending else f"{setting.label} ({seeds})"


def plot_curves(report: SweepReport, column: str, path: Path) -> Path:
    """One running-mean curve per setting with a mean +- std band, plus reference lines; a PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=FIGURE_SIZE)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for setting in report.settings:
        stats = setting.curve(column, report.window)
        x = np.arange(stats.mean.size)
        (line,) = ax.plot(x, stats.mean, linewidth=LINE_WIDTH, label=_legend_label(setting))
        ax.fill_between(
            x, stats.mean - stats.std, stats.mean + stats.std, color=line.get_color(), alpha=BAND_ALPHA
        )
    if column == COL_LENGTH:
        for max_steps in sorted({s.max_steps for s in report.settings}):
            ax.axhline(max_steps, linestyle="--", color=REFERENCE_COLOR, label=f"cap: {max_steps} steps")
        ylabel, what = "steps per episode", "Episode length"
    else:
        for ceiling in sorted({s.ceiling for s in report.settings}):
            ax.axhline(ceiling, linestyle="--", color=REFERENCE_COLOR, label=f"ceiling: {ceiling:g}")
        for name, value in report.pd_returns.items():
            ax.axhline(value, linestyle=":", color=PD_COLOR, label=f"{name}: {value:.0f}")
        ylabel, what = "return per episode", "Return"
    ax.set_xlabel("episode")
    ax.set_ylabel(f"{ylabel} (running mean over {report.window})")
    ax.set_title(f"{report.name}: {what.lower()}, mean +- std over seeds")
    ax.grid(alpha=BAND_ALPHA)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=FIGURE_DPI)
    return path


# --------------------------------------------------------------------------------------------------
# Tables


SUMMARY_CSV_COLUMNS = (
    "setting",
    "seeds_finished",
    "seeds_total",
    "episodes_min",
    "episodes_max",
    "final_return_mean",
    "final_return_std",
    "return_ceiling",
    "final_return_pct_of_ceiling",
    "max_steps",
    "length_cap_episode_mean",
    "length_cap_seeds_reached",
    "return_threshold",
    "return_threshold_episode_mean",
    "return_threshold_seeds_reached",
    "final_negative_thrust_fraction",
    "wall_clock_mean_s",
    "wall_clock_total_s",
    "notes",
)


def summary_rows(report: SweepReport) -> list[dict[str, Any]]:
    """The summary table as dicts with :data:`SUMMARY_CSV_COLUMNS` (raw numbers; empty = never)."""
    rows = []
    for s in report.summaries:
        rows.append(
            {
                "setting": s.label,
                "seeds_finished": s.seeds_finished,
                "seeds_total": s.seeds_total,
                "episodes_min": s.episodes_min,
                "episodes_max": s.episodes_max,
                "final_return_mean": s.final_return_mean,
                "final_return_std": s.final_return_std,
                "return_ceiling": s.ceiling,
                "final_return_pct_of_ceiling": s.final_return_pct,
                "max_steps": s.max_steps,
                "length_cap_episode_mean": "" if s.length_cap.mean is None else s.length_cap.mean,
                "length_cap_seeds_reached": len(s.length_cap.episodes),
                "return_threshold": report.return_threshold,
                "return_threshold_episode_mean": ""
                if s.return_threshold.mean is None
                else s.return_threshold.mean,
                "return_threshold_seeds_reached": len(s.return_threshold.episodes),
                "final_negative_thrust_fraction": s.final_negative_thrust,
                "wall_clock_mean_s": s.wall_clock_mean_s,
                "wall_clock_total_s": s.wall_clock_total_s,
                "notes": "; ".join(s.notes),
            }
        )
    return rows


def _common(values: set) -> str:
    return f"{next(iter(values)):g}" if len(values) == 1 else "10 x max_steps"


def format_table(report: SweepReport) -> str:
    """The summary table in Markdown."""
    ceiling = _common({s.ceiling for s in report.summaries})
    cap = _common({s.max_steps for s in report.summaries})
    header = [
        "setting",
        "seeds (finished/total)",
        "episodes",
        f"final return (running mean {report.window})",
        f"% of {ceiling}",
        f"length reaches {cap} at episode",
        f"return reaches {report.return_threshold:g} at episode",
        "negative thrust",
        "wall-clock per run",
        "wall-clock total (sum over runs)",
        "notes",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for s in report.summaries:
        episodes = (
            f"{s.episodes_max}" if s.episodes_min == s.episodes_max else f"{s.episodes_min}-{s.episodes_max}"
        )
        cells = [
            s.label,
            f"{s.seeds_finished}/{s.seeds_total}",
            episodes,
            s.return_text(),
            "-" if math.isnan(s.final_return_pct) else f"{s.final_return_pct:.1f}%",
            s.length_cap.text(),
            s.return_threshold.text(),
            "-" if math.isnan(s.final_negative_thrust) else f"{PERCENT * s.final_negative_thrust:.1f}%",
            _duration(s.wall_clock_mean_s),
            _duration(s.wall_clock_total_s),
            "; ".join(s.notes),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_report(report: SweepReport, figures: bool = True) -> str:
    """``summary.md``: the verdict on its first line, then the method, references, the table and
    (with ``figures``) links to the two figures."""
    runs = sum(len(s.runs) for s in report.settings)
    lines = [
        report.verdict,
        "",
        f"# Sweep report: {report.name}",
        "",
        f"{report.sweep_dir}: {runs} runs in {len(report.settings)} settings. Curves and finals are "
        f"trailing running means over {report.window} episodes (fewer over the first {report.window - 1}), "
        f"per run, then mean +- std (ddof={STD_DDOF}) over the seeds that reached each episode. "
        "Episodes are counted from 0; crossing episodes are the mean over the seeds that reach the "
        "threshold. Negative thrust: running-mean fraction of motor commands below zero at the end. "
        "Wall-clock: each run's last wall_clock_s; the total is their sum, which exceeds the elapsed "
        "time when runs trained side by side (one fused process, parallel launchers).",
        "",
    ]
    for name, value in report.pd_returns.items():
        ceilings = {s.ceiling for s in report.settings}
        share = (
            f" ({PERCENT * value / next(iter(ceilings)):.1f}% of {_common(ceilings)})"
            if len(ceilings) == 1
            else ""
        )
        lines.append(f"{name}: mean return {value:.0f}{share} over {PD_EPISODES} episodes, seed {PD_SEED}.")
    if report.pd_returns:
        lines.append("")
    lines += [format_table(report), ""]
    if figures:
        lines += [f"![steps]({STEPS_FIGURE})", "", f"![returns]({RETURNS_FIGURE})", ""]
    return "\n".join(lines)


def write_report(report: SweepReport, out_dir: Path) -> list[Path]:
    """Write ``steps.png``, ``returns.png``, ``summary.md`` and ``summary.csv`` into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [
        plot_curves(report, COL_LENGTH, out_dir / STEPS_FIGURE),
        plot_curves(report, COL_RETURN, out_dir / RETURNS_FIGURE),
    ]
    md = out_dir / SUMMARY_MD
    md.write_text(format_report(report))
    table = out_dir / SUMMARY_CSV
    with table.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(summary_rows(report))
    return [*paths, md, table]


def output_dirs(sweep_dirs: Sequence[Path], out: Path | None) -> list[Path]:
    """``<sweep>/report`` each; with ``out``: ``out`` for one sweep, ``out/<sweep name>`` for several.

    Sweep folders with the same name get ``-2``, ``-3``... suffixes under ``out``.
    """
    if out is None:
        return [Path(d) / REPORT_DIR for d in sweep_dirs]
    if len(sweep_dirs) == 1:
        return [Path(out)]
    dirs, seen = [], {}
    for d in sweep_dirs:
        name = Path(d).resolve().name
        seen[name] = seen.get(name, 0) + 1
        dirs.append(Path(out) / (name if seen[name] == 1 else f"{name}-{seen[name]}"))
    return dirs


# --------------------------------------------------------------------------------------------------
# CLI


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not an integer >= 1")
    return value


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Figures (steps.png, returns.png) and a summary table (summary.md, summary.csv) of sweeps.",
    )
    parser.add_argument("sweeps", nargs="+", type=Path, help="sweep folders, e.g. multirun/lr multirun/gamma")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: <sweep>/report; with several sweeps: <out>/<sweep name>)",
    )
    parser.add_argument(
        "--window",
        type=_positive_int,
        default=None,
        help="running-mean window in episodes (default: metrics.running_mean_window of conf/config.yaml)",
    )
    parser.add_argument(
        "--return-threshold",
        type=float,
        default=DEFAULT_RETURN_THRESHOLD,
        help=f"report the first episode the running-mean return reaches this (default {DEFAULT_RETURN_THRESHOLD:g})",
    )
    parser.add_argument("--no-pd", action="store_true", help="skip the PD controller reference line")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    """``drone-report``: one report per sweep folder; exit code 2 with a one-line error if unusable."""
    args = parse_args(argv)
    try:
        window = default_window() if args.window is None else args.window
        runs = [load_runs(d) for d in args.sweeps]  # check every folder before any work
        out_dirs = output_dirs(args.sweeps, args.out)
        for sweep_dir, sweep_runs, out_dir in zip(args.sweeps, runs, out_dirs, strict=True):
            report = build_report(sweep_dir, window, args.return_threshold, not args.no_pd, sweep_runs)
            paths = write_report(report, out_dir)
            print(format_report(report, figures=False))
            print(f"wrote {', '.join(str(p) for p in paths)}\n")
    except ReportError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        sys.exit(EXIT_ERROR)


__all__ = [
    "Crossing",
    "ReportError",
    "Run",
    "SeedStats",
    "Setting",
    "SettingSummary",
    "SweepReport",
    "aggregate_over_seeds",
    "build_report",
    "first_crossing",
    "format_report",
    "format_table",
    "group_runs",
    "load_runs",
    "main",
    "pd_reference",
    "running_mean",
    "setting_of",
    "summarize",
    "verdict",
    "write_report",
]


if __name__ == "__main__":
    main()
