"""The report of one sweep folder: its settings, their summaries, the PD references and the optima."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from drone_torchrl.episodes import RUNNING_MEAN_WINDOW
from drone_torchrl.optimum import Optimum
from drone_torchrl.report.runs import LABEL_SEPARATOR, Run, Setting, group_runs, load_runs, mixed_budgets
from drone_torchrl.report.stats import (
    DEFAULT_RETURN_THRESHOLD,
    SettingSummary,
    env_key,
    optimum_reference,
    pd_reference,
    summarize,
    verdict,
)

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
    pd_optima: dict[str, float] = field(default_factory=dict)
    """The best achievable return of the env of each PD reference that has one (keys of ``pd_returns``)."""
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


def default_window() -> int:
    """The running-mean window of a run (:data:`~drone_torchrl.episodes.RUNNING_MEAN_WINDOW`, the paper's 100)."""
    return RUNNING_MEAN_WINDOW


def build_report(
    sweep_dir: Path,
    window: int | None = None,
    return_threshold: float = DEFAULT_RETURN_THRESHOLD,
    pd: bool = True,
    runs: Sequence[Run] | None = None,
) -> SweepReport:
    """Read a sweep folder and compute its settings, table rows, PD references and optima.

    Already loaded ``runs`` are used instead of reading them again. The PD references are ``pd``;
    ``window=None`` is :func:`default_window`.
    """
    window = default_window() if window is None else window
    runs = load_runs(Path(sweep_dir)) if runs is None else runs
    settings = group_runs(runs)
    summaries = [summarize(s, window, return_threshold) for s in settings]
    pd_returns: dict[str, float] = {}
    optima: dict[str, Optimum] = {}
    pd_optima: dict[str, float] = {}
    by_env: dict[str, list[str]] = {}
    for s in settings:
        by_env.setdefault(env_key(s.env_kwargs), []).append(s.label)
    for env_json, labels in by_env.items():
        suffix = "" if len(by_env) == 1 else f" ({LABEL_SEPARATOR.join(labels)})"
        env = json.loads(env_json)
        best = optimum_reference(env)
        if best is not None:
            optima[OPTIMUM_LABEL + suffix] = best
        if pd:
            pd_returns[PD_LABEL + suffix] = pd_reference(env)
            if best is not None:
                pd_optima[PD_LABEL + suffix] = best.best_return
    return SweepReport(
        Path(sweep_dir),
        window,
        return_threshold,
        settings,
        summaries,
        pd_returns,
        optima,
        pd_optima,
        mixed_budgets(runs),
    )
