"""The report's tables and files: ``summary.md`` and ``summary.csv`` next to the figures."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drone_torchrl.io.storage import write_atomically, write_csv
from drone_torchrl.report.distribution import (
    CONFIDENCE,
    DISTRIBUTION_FIGURE,
    PAPER_AVERAGING_FIGURE,
    PAPER_STUDY_SEEDS,
    distribution,
    format_distributions,
    format_paper_averaging,
    paper_order,
    plot_distributions,
    plot_paper_averaging,
)
from drone_torchrl.report.figures import RETURNS_FIGURE, STEPS_FIGURE, plot_curves
from drone_torchrl.report.landscape import LANDSCAPE_FIGURE, landscape, write_landscape
from drone_torchrl.report.runs import COL_LENGTH, COL_RETURN
from drone_torchrl.report.schedules import SCHEDULES_FIGURE, pbt_runs, write_schedules
from drone_torchrl.report.stats import PD_EPISODES, PD_SEED, PERCENT, STD_DDOF, ZONE_SHARE
from drone_torchrl.report.sweep import SweepReport

REPORT_DIR = "report"
SUMMARY_MD = "summary.md"
SUMMARY_CSV = "summary.csv"

SECONDS_PER_MINUTE = 60.0
SECONDS_PER_HOUR = 3600.0

#: The columns of ``summary.csv``, one row per setting of the sweep.
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
    "optimum_return",
    "final_return_pct_of_optimum",
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
    return [
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
            "optimum_return": "" if s.optimum is None else s.optimum,
            "final_return_pct_of_optimum": "" if s.optimum is None else s.final_return_pct_of_optimum,
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
        for s in report.summaries
    ]


def _common(values: set) -> str:
    return f"{next(iter(values)):g}" if len(values) == 1 else "10 x max_steps"


def _duration(seconds: float) -> str:
    if math.isnan(seconds):
        return "-"
    if seconds >= SECONDS_PER_HOUR:
        return f"{seconds / SECONDS_PER_HOUR:.1f} h"
    if seconds >= SECONDS_PER_MINUTE:
        return f"{seconds / SECONDS_PER_MINUTE:.1f} min"
    return f"{seconds:.1f} s"


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
        "% of optimum",
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
            "-"
            if math.isnan(s.final_return_pct_of_optimum)
            else f"{s.final_return_pct_of_optimum:.1f}% of {s.optimum:g}",
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
    """Write ``summary.md``: the verdict, the method, references, the table and links to figures.

    The verdict is on the first line; the links to the two figures come with ``figures``.
    """
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
    ceilings = {s.ceiling for s in report.settings}
    for name, value in report.pd_returns.items():
        shares = (
            [f"{PERCENT * value / next(iter(ceilings)):.1f}% of {_common(ceilings)}"]
            if len(ceilings) == 1
            else []
        )
        optimum = report.pd_optima.get(name)
        if optimum is not None:
            shares.append(f"{PERCENT * value / optimum:.1f}% of the optimum {optimum:g}")
        share = f" ({', '.join(shares)})" if shares else ""
        lines.append(f"{name}: mean return {value:.0f}{share} over {PD_EPISODES} episodes, seed {PD_SEED}.")
    for name, best in report.optima.items():
        lines.append(
            f"{name}: {best.best_return:g}, the best achievable return of every episode from these starts "
            f"({best.describe()}; see docs/optimum.md of drone_torchrl). '% of optimum' divides the final "
            "return by it."
        )
    if report.pd_returns or report.optima:
        lines.append("")
    lines += [format_table(report), ""]
    if figures:
        lines += [f"![steps]({STEPS_FIGURE})", "", f"![returns]({RETURNS_FIGURE})", ""]
    return "\n".join(lines)


def format_seeds(report: SweepReport, distributions: list) -> str:
    """The seeds' distribution per setting (:mod:`.distribution`): its section of ``summary.md``."""
    return "\n".join(
        [
            "## How the seeds end",
            "",
            "Final = each run's last running-mean value. CI: percentile bootstrap of the median. Full "
            "length: the running-mean length reaches the cap. In the zone: final return >= "
            f"{ZONE_SHARE:g} x the ceiling. Mean of {PAPER_STUDY_SEEDS} seeds: the central "
            f"{CONFIDENCE:.0%} of the means of {PAPER_STUDY_SEEDS} seeds drawn without replacement "
            "(what a study with that many seeds could have reported).",
            "",
            format_distributions(distributions),
            "",
            f"![finals]({DISTRIBUTION_FIGURE})",
            "",
        ]
    )


def format_paper_averaging_section(report: SweepReport) -> str:
    """The markdown section of the sweep's settings averaged as the paper does, in the paper's order."""
    key, ordered = paper_order(report.settings)
    return "\n".join(
        [
            "## As the paper averages",
            "",
            f"The paper's analysis code never resets its list of runs between settings: the curve of the "
            f"k-th {key} setting (in the paper's order) is the mean over the runs of settings 1..k.",
            "",
            format_paper_averaging(ordered, report.window),
            "",
            f"![paper averaging]({PAPER_AVERAGING_FIGURE})",
            "",
        ]
    )


def write_report(report: SweepReport, out_dir: Path, paper_averaging: bool = False) -> list[Path]:
    """Write the report's figures and tables into ``out_dir``.

    Write ``steps.png``, ``returns.png``, ``finals.png``, ``summary.md`` and ``summary.csv`` into
    ``out_dir``; for a two-key grid sweep of fixed values also ``landscape.png`` and
    ``landscape.csv`` (:mod:`.landscape`; not for a search, whose agents' values change: one line
    says so), and for each searched population run ``pbt_schedules.png`` and ``.csv``
    (:mod:`.schedules`); with ``paper_averaging`` also ``paper_averaging.png``.
    """
    out_dir = Path(out_dir)
    distributions = [distribution(s, report.window) for s in report.settings if s.runs_with_episodes]
    paths = [
        plot_curves(report, COL_LENGTH, out_dir / STEPS_FIGURE),
        plot_curves(report, COL_RETURN, out_dir / RETURNS_FIGURE),
        plot_distributions(
            distributions,
            report.name,
            ZONE_SHARE * max(s.ceiling for s in report.settings),
            out_dir / DISTRIBUTION_FIGURE,
        ),
    ]
    extra = format_seeds(report, distributions)
    if paper_averaging:
        _, ordered = paper_order(report.settings)
        paths.append(
            plot_paper_averaging(ordered, report.window, report.name, out_dir / PAPER_AVERAGING_FIGURE)
        )
        extra += "\n" + format_paper_averaging_section(report)
    searched = pbt_runs(report.sweep_dir)
    grid = None if searched else landscape(report)
    if searched:  # a heat map's cells are fixed values: a search's agents did not keep theirs
        print(
            f"{report.sweep_dir}: no {LANDSCAPE_FIGURE}: its agents' values changed while they trained "
            f"(a search: {', '.join(run.name for run in searched)}); {SCHEDULES_FIGURE} draws them"
        )
    if grid is not None:
        paths += write_landscape(grid, out_dir)
    for run in searched:  # a search's schedules: every agent's values over the updates
        paths += write_schedules(run, out_dir, "" if len(searched) == 1 else f"{run.name}_")
    md = out_dir / SUMMARY_MD
    summary = format_report(report) + "\n" + extra
    summary += f"\n![landscape]({LANDSCAPE_FIGURE})\n" if grid is not None else ""
    write_atomically(md, summary.encode())
    rows = [[row[column] for column in SUMMARY_CSV_COLUMNS] for row in summary_rows(report)]
    return [*paths, md, write_csv(out_dir / SUMMARY_CSV, SUMMARY_CSV_COLUMNS, rows)]


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
