"""The numbers of a sweep report: statistics over seeds, thresholds, verdict and references.

That is: running means, statistics over seeds, threshold crossings, the summary of each setting,
the verdict, the PD controller's reference return, the best achievable return
(:func:`drone_torchrl.evaluation.reference_optimum`), and :class:`SweepReport`, all of one sweep folder.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drone_torchrl.episodes import RUNNING_MEAN_WINDOW
from drone_torchrl.evaluation import evaluate_pd, reference_optimum
from drone_torchrl.optimum import Optimum
from drone_torchrl.report import DEFAULT_RETURN_THRESHOLD
from drone_torchrl.report.runs import (
    COL_LENGTH,
    COL_NEGATIVE_THRUST,
    COL_RETURN,
    COL_WALL_CLOCK,
    LABEL_SEPARATOR,
    STATUS_FAILED,
    STATUS_FINISHED,
    STATUS_UNFINISHED,
    Run,
    Setting,
    group_runs,
    load_runs,
    mixed_budgets,
)

#: A seed "ends in the zone" when its final running-mean return is at least this share of the ceiling
#: 10 * max_steps (1500 of 3000: the drone spends about half the episode or more in the zone).
ZONE_SHARE = 0.5
STD_DDOF = 0  # population std over seeds: a single seed has zero spread rather than NaN
#: A running mean "reaches" a threshold within this relative tolerance (float sums of integers).
CROSSING_RTOL = 1e-9

PD_EPISODES = 100
PD_SEED = 0

PERCENT = 100.0
LARGE_VALUE = 100.0  # values at least this large are printed without decimals


# --------------------------------------------------------------------------------------------------
# Curves


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


def run_curves(setting: Setting, column: str, window: int) -> list[np.ndarray]:
    """Running mean of ``column`` of each run of ``setting`` that has episodes."""
    return [running_mean(r.columns[column], window) for r in setting.runs_with_episodes]


def setting_curve(setting: Setting, column: str, window: int) -> SeedStats:
    """Running mean of ``column`` per run, aggregated per episode over the seeds."""
    return aggregate_over_seeds(run_curves(setting, column, window))


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """The report's one Markdown table writer: ``header`` and ``rows`` of cells as they are printed."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(cells) + " |" for cells in rows])


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
        """Mean first-crossing episode of the runs that reach the threshold (None if none does)."""
        return float(np.mean(self.episodes)) if self.episodes else None

    def text(self) -> str:
        """The crossing as a table cell, ``"412 (3/4 seeds)"`` or ``"never (0/4 seeds)"``."""
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
    final_lengths: list[float]
    length_cap: Crossing
    return_threshold: Crossing
    final_negative_thrust: float
    wall_clock_mean_s: float
    wall_clock_total_s: float
    notes: list[str]
    final_return_mean: float
    """Mean final running-mean return over the seeds (NaN without any)."""
    final_return_std: float
    """Standard deviation of the final returns over the seeds (NaN without any)."""
    final_return_pct: float
    """The mean final return as a percentage of the highest possible return."""
    final_return_pct_of_optimum: float
    """The final return as a percentage of :attr:`optimum` (NaN without one)."""
    optimum: float | None = None
    """The best achievable return of every episode of the setting (bounded thrust; else ``None``)."""

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


def progress_notes(setting: Setting) -> list[str]:
    """Unfinished and failed seeds, e.g. ``"2 of 4 seeds unfinished, shortest at 1200 episodes"``."""
    notes = []
    total = len(setting.runs)
    for status in (STATUS_UNFINISHED, STATUS_FAILED):  # each status is also its word in the note
        if stopped := [r for r in setting.runs if r.status == status]:
            shortest = min(r.episodes for r in stopped)
            notes.append(f"{len(stopped)} of {total} seeds {status}, shortest at {shortest} episodes")
    for run in setting.runs:
        if not run.episodes:
            notes.append(f"seed {run.seed} has no episode yet")
        notes.extend(run.notes)
    return notes


def summarize(
    setting: Setting, window: int, return_threshold: float = DEFAULT_RETURN_THRESHOLD
) -> SettingSummary:
    """The table row of one setting (see the :mod:`drone_torchrl.report` docstring for the definitions)."""
    lengths = run_curves(setting, COL_LENGTH, window)
    returns = run_curves(setting, COL_RETURN, window)
    negative = [c[-1] for c in run_curves(setting, COL_NEGATIVE_THRUST, window)]
    clocks = [float(r.columns[COL_WALL_CLOCK][-1]) for r in setting.runs_with_episodes]

    def crossing(curves: list[np.ndarray], threshold: float) -> Crossing:
        hits = [first_crossing(c, threshold) for c in curves]
        return Crossing(threshold, [h for h in hits if h is not None], len(curves))

    episodes = [r.episodes for r in setting.runs]
    best = reference_optimum(setting.env_kwargs)  # cached per env setting (optimum.env_optimum)
    finals = [float(c[-1]) for c in returns]
    mean = float(np.mean(finals)) if finals else math.nan
    return SettingSummary(
        label=setting.label,
        seeds_finished=sum(r.status == STATUS_FINISHED for r in setting.runs),
        seeds_total=len(setting.runs),
        episodes_min=min(episodes),
        episodes_max=max(episodes),
        max_steps=setting.max_steps,
        ceiling=setting.ceiling,
        final_returns=finals,
        final_lengths=[float(c[-1]) for c in lengths],
        length_cap=crossing(lengths, setting.max_steps),
        return_threshold=crossing(returns, return_threshold),
        final_negative_thrust=float(np.mean(negative)) if negative else math.nan,
        wall_clock_mean_s=float(np.mean(clocks)) if clocks else math.nan,
        wall_clock_total_s=float(np.sum(clocks)) if clocks else math.nan,
        notes=progress_notes(setting),
        final_return_mean=mean,
        final_return_std=float(np.std(finals, ddof=STD_DDOF)) if finals else math.nan,
        final_return_pct=PERCENT * mean / setting.ceiling,
        final_return_pct_of_optimum=math.nan if best is None else PERCENT * mean / best.best_return,
        optimum=None if best is None else best.best_return,
    )


def verdict(summaries: Sequence[SettingSummary]) -> str:
    """The best setting's line: its mean final running-mean return and its share of the ceiling.

    ``"best: algo.lr=0.0001 (2210 +- 150, 73.7% of 3000)"``: the best mean final running-mean return
    (with bounded thrust also its share of the optimum: ``..., 82.0% of the optimum 2694)``).

    Names settings tied with the best, and says the verdict is provisional when some runs are
    unfinished or failed (their finals are taken where they stopped).
    """
    candidates = [s for s in summaries if s.final_returns]
    if not candidates:
        return "best: none (no episodes yet)"
    best = max(candidates, key=lambda s: s.final_return_mean)
    share = f"{best.final_return_pct:.1f}% of {best.ceiling:g}"
    if best.optimum is not None:
        share += f", {best.final_return_pct_of_optimum:.1f}% of the optimum {best.optimum:g}"
    line = f"best: {best.label} ({best.return_text()}, {share})"
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
def _pd_return(env_json: str) -> float:
    """Mean return of the PD hover controller (:func:`~.evaluation.evaluate_pd`, 100 episodes, seed 0).

    Computed once per distinct env setting (its arguments as JSON) in this process (cached).
    """
    return evaluate_pd(json.loads(env_json), episodes=PD_EPISODES, seed=PD_SEED)["return_mean"]


# --------------------------------------------------------------------------------------------------
# One sweep's report

PD_LABEL = "PD controller"
OPTIMUM_LABEL = "optimum"


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
    optima: dict[str, Optimum] = field(default_factory=dict)
    """The best achievable return per distinct env setting with bounded thrust (``"optimum"``, or
    ``"optimum (<labels>)"`` when the settings differ in their env)."""
    mixed_budgets: str | None = None
    """The line saying the runs mix budgets (:func:`~drone_torchrl.report.runs.mixed_budgets`), or ``None``."""

    @property
    def name(self) -> str:
        """The sweep folder's name."""
        return self.sweep_dir.resolve().name

    @property
    def verdict(self) -> str:
        """The verdict line on the sweep's settings; none is named best when the runs mix budgets.

        A run given more episodes ends further along, so a best across budgets would rank budgets,
        not settings.
        """
        if self.mixed_budgets is not None:
            return f"best: none named: {self.mixed_budgets}; compare runs of one budget"
        return verdict(self.summaries)


def build_report(
    sweep_dir: Path,
    window: int | None = None,
    return_threshold: float = DEFAULT_RETURN_THRESHOLD,
    pd: bool = True,
    runs: Sequence[Run] | None = None,
) -> SweepReport:
    """Read a sweep folder and compute its settings, table rows, PD references and optima.

    Already loaded ``runs`` are used instead of reading them again. The PD references are ``pd``;
    ``window=None`` is a run's own (:data:`~drone_torchrl.episodes.RUNNING_MEAN_WINDOW`, the paper's 100).
    """
    window = RUNNING_MEAN_WINDOW if window is None else window
    runs = load_runs(Path(sweep_dir)) if runs is None else runs
    settings = group_runs(runs)
    summaries = [summarize(s, window, return_threshold) for s in settings]
    report = SweepReport(
        Path(sweep_dir), window, return_threshold, settings, summaries, {}, mixed_budgets=mixed_budgets(runs)
    )
    by_env: dict[str, list[str]] = {}
    for s in settings:
        # JSON: a hashable key (the arguments hold a mapping, env.disturbance) that json.loads gives back.
        by_env.setdefault(json.dumps(s.env_kwargs, sort_keys=True), []).append(s.label)
    for env_json, labels in by_env.items():
        suffix = "" if len(by_env) == 1 else f" ({LABEL_SEPARATOR.join(labels)})"
        if (best := reference_optimum(json.loads(env_json))) is not None:
            report.optima[OPTIMUM_LABEL + suffix] = best
        if pd:
            report.pd_returns[PD_LABEL + suffix] = _pd_return(env_json)
    return report
