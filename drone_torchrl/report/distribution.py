"""How the seeds of each setting end, beyond mean +- std, and the paper's own way of averaging.

With many seeds per setting the final returns are often bimodal (some seeds hover in the zone, the
others survive outside it or crash), so a mean over 4 seeds mostly measures which seeds were drawn.
Per setting, :func:`distribution` gives:

- the median and interquartile range of the final running-mean return, with a bootstrap 95%
  interval of the median;
- the median final running-mean episode length;
- the fraction of seeds that reach full-length episodes (the running-mean length reaches
  ``max_steps`` at some episode) and the fraction that end in the zone (final running-mean return
  >= :data:`~drone_torchrl.report.stats.ZONE_SHARE` of the ceiling: 1500 of 3000);
- the band of 4-seed means (bootstrap: 4 seeds drawn without replacement, as a 4-seed study would
  draw them): the spread a paper-sized study sees;
- with bounded thrust, the median as a share of the best achievable return
  (:func:`~drone_torchrl.evaluation.reference_optimum`).

:func:`paper_averaged_curves` redraws the paper's figures 4.2 and 4.4 the way its public analysis
code computes them: the list of runs is never reset between settings, so the curve drawn for the
k-th setting (in the paper's order) is the mean over the runs of settings 1..k.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drone_torchrl.io.storage import new_figure, write_figure
from drone_torchrl.report.runs import COL_LENGTH, COL_RETURN, ReportError, Setting
from drone_torchrl.report.stats import (
    PERCENT,
    ZONE_SHARE,
    aggregate_over_seeds,
    markdown_table,
    run_curves,
    setting_curve,
    summarize,
)

BOOTSTRAP_SAMPLES = 10_000
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95
PAPER_STUDY_SEEDS = 4
# The settings in the order the paper's analysis code appends their runs (figures 4.2 and 4.4).
PAPER_ORDER = {"algo.lr": (5e-5, 1e-4, 5e-4, 1e-3), "algo.gamma": (0.999, 0.99, 0.95, 0.9)}
DISTRIBUTION_FIGURE = "finals.png"
PAPER_AVERAGING_FIGURE = "paper_averaging.png"


@dataclass
class Distribution:
    """How the seeds of one setting end (final = the last running-mean value of each run)."""

    label: str
    final_returns: np.ndarray
    final_lengths: np.ndarray
    reached_full_length: int
    in_zone: int
    median: float
    """Median of the seeds' final returns."""
    median_ci: tuple[float, float]
    four_seed_band: tuple[float, float]
    optimum: float | None = None
    """The best achievable return of the setting's episodes (bounded thrust; else ``None``)."""


def percentile_tails() -> tuple[float, float]:
    """The lower and upper percentiles (0-100) of a central interval of confidence ``CONFIDENCE``."""
    return 100 * (1 - CONFIDENCE) / 2, 100 * (1 + CONFIDENCE) / 2


def small_study_band(
    values: np.ndarray, rng: np.random.Generator, seeds: int = PAPER_STUDY_SEEDS
) -> tuple[float, float]:
    """Central interval of the mean of ``seeds`` runs drawn without replacement (a small study's mean)."""
    if values.size < seeds:
        return float("nan"), float("nan")
    draws = np.argsort(rng.random((BOOTSTRAP_SAMPLES, values.size)), axis=1)[:, :seeds]
    low, high = np.percentile(values[draws].mean(axis=1), percentile_tails())
    return float(low), float(high)


def distribution(setting: Setting, window: int) -> Distribution:
    """The final-value distribution of ``setting``'s runs that have episodes (of its :func:`~.stats.summarize`)."""
    summary = summarize(setting, window)
    if not summary.final_returns:
        raise ReportError(f"{setting.label}: no run has episodes")
    finals = np.array(summary.final_returns)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    # The median's percentile bootstrap interval: the seeds resampled with replacement.
    samples = rng.choice(finals, size=(BOOTSTRAP_SAMPLES, finals.size), replace=True)
    ci_low, ci_high = np.percentile(np.median(samples, axis=1), percentile_tails())
    return Distribution(
        label=setting.label,
        final_returns=finals,
        final_lengths=np.array(summary.final_lengths),
        reached_full_length=len(summary.length_cap.episodes),
        in_zone=int((finals >= ZONE_SHARE * summary.ceiling).sum()),
        median=float(np.median(finals)),
        median_ci=(float(ci_low), float(ci_high)),
        four_seed_band=small_study_band(finals, rng),
        optimum=summary.optimum,
    )


def format_distributions(distributions: Sequence[Distribution]) -> str:
    """A Markdown table: one row per setting."""
    lo, hi = percentile_tails()
    header = (
        f"setting|seeds|median final return [{CONFIDENCE:.0%} CI]|IQR|median final length|reach full length|"
        f"end in the zone|mean of {PAPER_STUDY_SEEDS} seeds ({lo:g}-{hi:g}%)|median, % of optimum"
    ).split("|")
    rows = [
        [
            d.label,
            f"{d.final_returns.size}",
            f"{d.median:.0f} [{d.median_ci[0]:.0f}, {d.median_ci[1]:.0f}]",
            "{:.0f}-{:.0f}".format(*np.percentile(d.final_returns, [25, 75])),
            f"{np.median(d.final_lengths):.0f}",
            f"{d.reached_full_length}/{d.final_returns.size}",
            f"{d.in_zone}/{d.final_returns.size}",
            f"{d.four_seed_band[0]:.0f}-{d.four_seed_band[1]:.0f}",
            "-" if d.optimum is None else f"{PERCENT * d.median / d.optimum:.1f}% of {d.optimum:g}",
        ]
        for d in distributions
    ]
    return markdown_table(header, rows)


def plot_distributions(
    distributions: Sequence[Distribution], title: str, zone_return: float, path: Path
) -> Path:
    """Box plot of each setting's final running-mean returns, every seed drawn as a point."""
    fig = new_figure((9.0, 5.0))
    ax = fig.add_subplot()
    data = [d.final_returns for d in distributions]
    ax.boxplot(data, whis=(0, 100), widths=0.5)
    jitter = np.random.default_rng(BOOTSTRAP_SEED)
    for i, values in enumerate(data, start=1):
        ax.scatter(i + jitter.uniform(-0.15, 0.15, values.size), values, s=10, alpha=0.6)
    ax.axhline(zone_return, linestyle="--", color="black", label=f"ends in the zone: >= {zone_return:g}")
    ax.set_xticks(range(1, len(data) + 1), [d.label for d in distributions], rotation=15, fontsize="small")
    ax.set(
        ylabel="final return (running mean)",
        title=f"{title}: final return of every seed (box: quartiles, whiskers: range)",
    )
    ax.grid(alpha=0.2)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)


# --------------------------------------------------------------------------------------------------
# The paper's averaging


def paper_order(settings: Sequence[Setting]) -> tuple[str, list[Setting]]:
    """The swept key and the settings in the paper's order; :class:`~.runs.ReportError` if not a paper grid."""
    for key, order in PAPER_ORDER.items():
        values = [dict(s.pairs).get(key) for s in settings]
        ranks = [None if v is None or float(v) not in order else order.index(float(v)) for v in values]
        if None not in ranks and len(set(ranks)) == len(ranks):
            return key, [s for _, s in sorted(zip(ranks, settings, strict=True), key=lambda p: p[0])]
    raise ReportError(
        "--paper-averaging needs a sweep over the paper's values of algo.lr "
        f"{list(PAPER_ORDER['algo.lr'])} or algo.gamma {list(PAPER_ORDER['algo.gamma'])}"
    )


def paper_averaged_curves(settings: Sequence[Setting], column: str, window: int) -> list[np.ndarray]:
    """Curve k = the mean over the runs of ``settings[0..k]`` (the paper's cumulative list of runs)."""
    pooled: list[np.ndarray] = []
    curves = []
    for setting in settings:
        pooled.extend(run_curves(setting, column, window))
        curves.append(aggregate_over_seeds(pooled).mean)
    return curves


def per_setting_curves(settings: Sequence[Setting], column: str, window: int) -> list[np.ndarray]:
    """Curve k = the mean over the runs of ``settings[k]`` only (what the paper's text describes)."""
    return [setting_curve(setting, column, window).mean for setting in settings]


# The two averagings, side by side in the figure and the table: each curve's function and its title.
AVERAGINGS = (
    (per_setting_curves, "per setting (each setting's own runs)"),
    (paper_averaged_curves, "as the paper averages (runs of settings 1..k)"),
)


def plot_paper_averaging(settings: Sequence[Setting], window: int, title: str, path: Path) -> Path:
    """Per-setting means next to the paper's cumulative means, for episode length and return."""
    fig = new_figure((12.0, 8.0))
    axes = fig.subplots(2, 2, sharey="row")
    for row, (column, ylabel) in enumerate(((COL_LENGTH, "steps per episode"), (COL_RETURN, "return"))):
        for col, (curves_of, kind) in enumerate(AVERAGINGS):
            ax = axes[row][col]
            for setting, curve in zip(settings, curves_of(settings, column, window), strict=True):
                ax.plot(np.arange(curve.size), curve, linewidth=1.5, label=setting.label)
            ax.set_title(f"{kind}", fontsize="medium")
            ax.set(xlabel="episode", ylabel=f"{ylabel} (running mean over {window})")
            ax.grid(alpha=0.2)
            ax.legend(loc="best", fontsize="small")
    fig.suptitle(f"{title}: settings in the paper's order")
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)


def format_paper_averaging(settings: Sequence[Setting], window: int) -> str:
    """Final values of both averagings (the last point of each curve), one row per setting."""
    header = "setting (paper's order)|runs pooled|final return: per setting|as the paper averages|"
    header += "final length: per setting|as the paper averages"
    curves = [
        curves_of(settings, column, window)
        for column in (COL_RETURN, COL_LENGTH)
        for curves_of, _ in AVERAGINGS
    ]
    pooled = np.cumsum([len(setting.runs_with_episodes) for setting in settings])
    rows = [
        [setting.label, f"{pooled[k]}", *(f"{c[k][-1]:.0f}" for c in curves)]
        for k, setting in enumerate(settings)
    ]
    return markdown_table(header.split("|"), rows)
