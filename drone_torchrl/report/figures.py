"""The report's figures: running-mean curves per setting with reference lines (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drone_torchrl.io.storage import new_figure, write_figure
from drone_torchrl.report.runs import COL_LENGTH, STATUS_FINISHED, Setting
from drone_torchrl.report.stats import setting_curve
from drone_torchrl.report.sweep import SweepReport

STEPS_FIGURE = "steps.png"
RETURNS_FIGURE = "returns.png"

FIGURE_SIZE = (9.0, 5.5)
FIGURE_DPI = 120
BAND_ALPHA = 0.2
LINE_WIDTH = 1.5
REFERENCE_COLOR = "black"
PD_COLOR = "dimgray"
OPTIMUM_COLOR = "darkred"


def _legend_label(setting: Setting) -> str:
    n = len(setting.runs)
    pending = n - sum(r.status == STATUS_FINISHED for r in setting.runs)
    seeds = f"{n} seed{'s' if n != 1 else ''}"
    return f"{setting.label} ({seeds}, {pending} not finished)" if pending else f"{setting.label} ({seeds})"


def plot_curves(report: SweepReport, column: str, path: Path) -> Path:
    """One running-mean curve per setting with a mean +- std band, plus reference lines; a PNG."""
    fig = new_figure(FIGURE_SIZE)
    ax = fig.add_subplot()
    for setting in report.settings:
        stats = setting_curve(setting, column, report.window)
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
        for name, best in report.optima.items():
            ax.axhline(
                best.best_return, linestyle="-.", color=OPTIMUM_COLOR, label=f"{name}: {best.best_return:.0f}"
            )
        ylabel, what = "return per episode", "Return"
    ax.set_xlabel("episode")
    ax.set_ylabel(f"{ylabel} (running mean over {report.window})")
    ax.set_title(f"{report.name}: {what.lower()}, mean +- std over seeds")
    ax.grid(alpha=BAND_ALPHA)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    return write_figure(fig, path, dpi=FIGURE_DPI)
