"""The report's files: ``summary.md`` and ``summary.csv``, and the running-mean curves ``steps.png`` and ``returns.png``."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drone_torchrl.io.storage import new_figure, write_atomically, write_csv, write_figure
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
from drone_torchrl.report.landscape import LANDSCAPE_FIGURE, landscape, write_landscape
from drone_torchrl.report.runs import COL_LENGTH, COL_RETURN, STATUS_FINISHED
from drone_torchrl.report.schedules import SCHEDULES_FIGURE, pbt_runs, write_schedules
from drone_torchrl.report.stats import (
    OPTIMUM_LABEL,
    PD_EPISODES,
    PD_LABEL,
    PD_SEED,
    PERCENT,
    STD_DDOF,
    ZONE_SHARE,
    SettingSummary,
    SweepReport,
    markdown_table,
    setting_curve,
)

STEPS_FIGURE = "steps.png"
RETURNS_FIGURE = "returns.png"
REPORT_DIR = "report"
SUMMARY_MD = "summary.md"
SUMMARY_CSV = "summary.csv"


def plot_curves(report: SweepReport, column: str, path: Path) -> Path:
    """One running-mean curve per setting with a mean +- std band, plus reference lines; a PNG."""
    fig = new_figure((9.0, 5.5))
    ax = fig.add_subplot()
    for setting in report.settings:
        stats = setting_curve(setting, column, report.window)
        x = np.arange(stats.mean.size)
        n, pending = len(setting.runs), sum(r.status != STATUS_FINISHED for r in setting.runs)
        seeds = f"{n} seed{'s' if n != 1 else ''}" + (f", {pending} not finished" if pending else "")
        (line,) = ax.plot(x, stats.mean, linewidth=1.5, label=f"{setting.label} ({seeds})")
        ax.fill_between(x, stats.mean - stats.std, stats.mean + stats.std, color=line.get_color(), alpha=0.2)
    if column == COL_LENGTH:
        for max_steps in sorted({s.max_steps for s in report.settings}):
            ax.axhline(max_steps, linestyle="--", color="black", label=f"cap: {max_steps} steps")
        ylabel, what = "steps per episode", "Episode length"
    else:
        for ceiling in sorted({s.ceiling for s in report.settings}):
            ax.axhline(ceiling, linestyle="--", color="black", label=f"ceiling: {ceiling:g}")
        for name, value in report.pd_returns.items():
            ax.axhline(value, linestyle=":", color="dimgray", label=f"{name}: {value:.0f}")
        for name, best in report.optima.items():
            ax.axhline(
                best.best_return, linestyle="-.", color="darkred", label=f"{name}: {best.best_return:.0f}"
            )
        ylabel, what = "return per episode", "Return"
    ax.set(xlabel="episode", ylabel=f"{ylabel} (running mean over {report.window})")
    ax.set_title(f"{report.name}: {what.lower()}, mean +- std over seeds")
    ax.grid(alpha=0.2)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)


def summary_rows(report: SweepReport) -> list[dict[str, Any]]:
    """The rows of ``summary.csv``, one per setting: its columns in order (raw numbers; empty = never)."""
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
            "optimum_return": _or_empty(s.optimum),
            "final_return_pct_of_optimum": _or_empty(s.optimum and s.final_return_pct_of_optimum),
            "max_steps": s.max_steps,
            "length_cap_episode_mean": _or_empty(s.length_cap.mean),
            "length_cap_seeds_reached": len(s.length_cap.episodes),
            "return_threshold": report.return_threshold,
            "return_threshold_episode_mean": _or_empty(s.return_threshold.mean),
            "return_threshold_seeds_reached": len(s.return_threshold.episodes),
            "final_negative_thrust_fraction": s.final_negative_thrust,
            "wall_clock_mean_s": s.wall_clock_mean_s,
            "wall_clock_total_s": s.wall_clock_total_s,
            "notes": "; ".join(s.notes),
        }
        for s in report.summaries
    ]


def _or_empty(value: float | None) -> float | str:
    return "" if value is None else value


def _common(values: set) -> str:
    return f"{next(iter(values)):g}" if len(values) == 1 else "10 x max_steps"


def _span(low: int, high: int) -> str:
    return f"{high}" if low == high else f"{low}-{high}"


def _percent(value: float, suffix: str = "") -> str:
    return "-" if math.isnan(value) else f"{value:.1f}%{suffix}"


def _duration(seconds: float) -> str:
    if math.isnan(seconds):
        return "-"
    for unit, size in (("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.1f} s"


def format_table(report: SweepReport) -> str:
    """The summary table in Markdown."""
    ceiling = _common({s.ceiling for s in report.summaries})
    cap = _common({s.max_steps for s in report.summaries})
    # Each column: its header and its cell of a setting's summary.
    columns: list[tuple[str, Callable[[SettingSummary], str]]] = [
        ("setting", lambda s: s.label),
        ("seeds (finished/total)", lambda s: f"{s.seeds_finished}/{s.seeds_total}"),
        ("episodes", lambda s: _span(s.episodes_min, s.episodes_max)),
        (f"final return (running mean {report.window})", SettingSummary.return_text),
        (f"% of {ceiling}", lambda s: _percent(s.final_return_pct)),
        (
            "% of optimum",
            lambda s: _percent(s.final_return_pct_of_optimum, f" of {s.optimum:g}" if s.optimum else ""),
        ),
        (f"length reaches {cap} at episode", lambda s: s.length_cap.text()),
        (f"return reaches {report.return_threshold:g} at episode", lambda s: s.return_threshold.text()),
        ("negative thrust", lambda s: _percent(PERCENT * s.final_negative_thrust)),
        ("wall-clock per run", lambda s: _duration(s.wall_clock_mean_s)),
        ("wall-clock total (sum over runs)", lambda s: _duration(s.wall_clock_total_s)),
        ("notes", lambda s: "; ".join(s.notes)),
    ]
    rows = [[cell(s) for _, cell in columns] for s in report.summaries]
    return markdown_table([header for header, _ in columns], rows)


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
        best = report.optima.get(OPTIMUM_LABEL + name.removeprefix(PD_LABEL))  # the same env's
        if best is not None:
            shares.append(f"{PERCENT * value / best.best_return:.1f}% of the optimum {best.best_return:g}")
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


def _section(title: str, text: str, table: str, figure: str) -> str:
    """A section of ``summary.md``: its title, text and table, then its figure's link."""
    return "\n".join(
        [f"## {title}", "", text, "", table, "", f"![{figure[:-4].replace('_', ' ')}]({figure})", ""]
    )


def format_seeds(report: SweepReport, distributions: list) -> str:
    """The seeds' distribution per setting (:mod:`.distribution`): its section of ``summary.md``."""
    text = (
        "Final = each run's last running-mean value. CI: percentile bootstrap of the median. Full "
        "length: the running-mean length reaches the cap. In the zone: final return >= "
        f"{ZONE_SHARE:g} x the ceiling. Mean of {PAPER_STUDY_SEEDS} seeds: the central "
        f"{CONFIDENCE:.0%} of the means of {PAPER_STUDY_SEEDS} seeds drawn without replacement "
        "(what a study with that many seeds could have reported)."
    )
    return _section("How the seeds end", text, format_distributions(distributions), DISTRIBUTION_FIGURE)


def format_paper_averaging_section(report: SweepReport) -> str:
    """The markdown section of the sweep's settings averaged as the paper does, in the paper's order."""
    key, ordered = paper_order(report.settings)
    text = (
        f"The paper's analysis code never resets its list of runs between settings: the curve of the "
        f"k-th {key} setting (in the paper's order) is the mean over the runs of settings 1..k."
    )
    return _section(
        "As the paper averages", text, format_paper_averaging(ordered, report.window), PAPER_AVERAGING_FIGURE
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
    rows = summary_rows(report)
    table = write_csv(out_dir / SUMMARY_CSV, list(rows[0]), [list(row.values()) for row in rows])
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
