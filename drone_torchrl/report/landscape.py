"""Heat maps of a two-dimensional grid sweep (e.g. learning rate x discount, ``+sweep=landscape``).

A sweep whose settings differ in exactly two numeric keys, each with at least two values, is a
grid. Per cell, over its seeds:

- the median final running-mean return;
- the fraction of seeds that end in the zone: final running-mean return >= :data:`~.stats.ZONE_SHARE` of
  the ceiling ``10 * max_steps`` (1500 of 3000: the drone spends about half the episode or more
  hovering in the target zone, a return that a crash, or a drone that only survives outside the
  zone (about 300), cannot reach);
- the median episode at which the running-mean episode length first reaches ``max_steps``
  (seeds that never do count as never; a cell whose median seed never does shows "never").

The paper's setting (alpha 1e-4, gamma 0.99) is marked where it falls between the grid's values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drone_torchrl.io.storage import new_figure, write_csv, write_figure
from drone_torchrl.report.stats import ZONE_SHARE, SettingSummary, SweepReport

PAPER_SETTING = {"algo.lr": 1e-4, "algo.gamma": 0.99}
LANDSCAPE_FIGURE = "landscape.png"
LANDSCAPE_CSV = "landscape.csv"
# Its columns after the two keys' values.
LANDSCAPE_CSV_COLUMNS = ("seeds", "median_final_return", "zone_fraction", "median_full_length_episode")
MIN_VALUES_PER_AXIS = 2
NEVER = "never"


def _axis_position(key: str, value: float) -> float:
    """Where a value sits on its axis: ``-log(1 - gamma)`` for discounts, ``log(value)`` otherwise.

    For a discount that is the horizon, log-spaced and growing with gamma; ``log(value)`` is for
    the other, positive, values.
    """
    if key.endswith("gamma"):
        return -math.log(1.0 - value) if value < 1 else math.inf
    return math.log(value) if value > 0 else value


@dataclass
class Landscape:
    """A two-key sweep's grid: per cell ``[len(y), len(x)]`` the median return, zone fraction and seeds."""

    x_key: str
    y_key: str
    x_values: list[float]
    y_values: list[float]
    median_return: np.ndarray  # [len(y), len(x)], NaN where a cell has no run
    zone_fraction: np.ndarray
    full_length_episode: np.ndarray  # inf: the median seed never reaches full length
    seeds: np.ndarray


def landscape(report: SweepReport) -> Landscape | None:
    """The grid of a sweep, or None if its settings are not a two-key numeric grid."""
    keys = list(dict.fromkeys(k for setting in report.settings for k, _ in setting.pairs))
    values: dict[str, set[float]] = {}
    for key in keys:
        try:
            values[key] = {float(dict(s.pairs)[key]) for s in report.settings}
        except (KeyError, ValueError):
            continue
    axes = [k for k in keys if len(values.get(k, ())) >= MIN_VALUES_PER_AXIS]
    if len(axes) != 2 or len(report.settings) < MIN_VALUES_PER_AXIS**2:
        return None
    x_key, y_key = axes
    xs = sorted(values[x_key], key=lambda v: _axis_position(x_key, v))
    ys = sorted(values[y_key], key=lambda v: _axis_position(y_key, v))
    shape = (len(ys), len(xs))
    median_return, zone, full, seeds = (np.full(shape, np.nan) for _ in range(4))
    for setting, summary in zip(report.settings, report.summaries, strict=True):
        pairs = dict(setting.pairs)
        cell = ys.index(float(pairs[y_key])), xs.index(float(pairs[x_key]))
        median_return[cell], zone[cell], full[cell], seeds[cell] = _cell(summary)
    return Landscape(x_key, y_key, xs, ys, median_return, zone, full, seeds)


def _cell(summary: SettingSummary) -> tuple[float, float, float, float]:
    finals = np.asarray(summary.final_returns, dtype=np.float64)
    if finals.size == 0:
        return math.nan, math.nan, math.nan, 0.0
    reached = summary.length_cap.episodes
    episodes = np.array(reached + [math.inf] * (summary.length_cap.runs - len(reached)), dtype=np.float64)
    return (
        float(np.median(finals)),
        float(np.mean(finals >= ZONE_SHARE * summary.ceiling)),
        float(np.median(episodes)),  # one per final: never empty here
        float(finals.size),
    )


def _format(value: float, kind: str) -> str:
    if math.isnan(value):
        return "-"
    if kind == "fraction":
        return f"{value:.2f}"
    if math.isinf(value):
        return NEVER
    return f"{value:.0f}"


def plot_landscape(grid: Landscape, path: Path) -> Path:
    """Three heat maps side by side, values written in the cells, the paper's setting marked."""
    import matplotlib

    fig = new_figure((16.0, 5.0))
    marker = _paper_marker(grid)
    panels = [
        ("median final return (running mean)", grid.median_return, "value", "viridis"),
        (
            f"fraction of seeds ending in the zone (return >= {ZONE_SHARE:g} x the ceiling)",
            grid.zone_fraction,
            "fraction",
            "magma",
        ),
        ("median episode to full-length episodes", grid.full_length_episode, "value", "viridis_r"),
    ]
    for i, (title, values, kind, cmap) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        shown = np.where(np.isinf(values), np.nan, values)
        colours = matplotlib.colormaps[cmap].with_extremes(bad="lightgrey")
        image = ax.imshow(shown, origin="lower", cmap=colours, aspect="auto")
        fig.colorbar(image, ax=ax, shrink=0.8)
        for (row, col), value in np.ndenumerate(values):
            cell = shown[row, col]
            rgb = colours(image.norm(cell))[:3] if np.isfinite(cell) else (1.0, 1.0, 1.0)
            bright = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2] > 0.5  # ITU-R BT.601 luminance
            text = "black" if bright else "white"
            ax.text(col, row, _format(value, kind), ha="center", va="center", fontsize=7, color=text)
        ax.set_xticks(range(len(grid.x_values)), [f"{v:.3g}" for v in grid.x_values], rotation=45)
        ax.set_yticks(range(len(grid.y_values)), [f"{v:.5g}" for v in grid.y_values])
        ax.set(xlabel=grid.x_key, ylabel=grid.y_key)
        ax.set_title(title, fontsize="medium")
        if marker is not None:
            ax.plot(*marker, marker="*", color="red", markersize=14, markeredgecolor="white")
    if marker is not None:
        paper = ", ".join(f"{key} {value:g}" for key, value in PAPER_SETTING.items())
        fig.suptitle(f"red star: the paper's setting ({paper}); grey: never", fontsize="medium")
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)


def _paper_marker(grid: Landscape) -> tuple[float, float] | None:
    """The paper's setting in cell coordinates (interpolated on each axis), if both keys are its."""
    if grid.x_key not in PAPER_SETTING or grid.y_key not in PAPER_SETTING:
        return None
    coords = []
    for key, values in ((grid.x_key, grid.x_values), (grid.y_key, grid.y_values)):
        positions = [_axis_position(key, v) for v in values]
        coords.append(
            float(np.interp(_axis_position(key, PAPER_SETTING[key]), positions, range(len(values))))
        )
    return coords[0], coords[1]


def write_landscape(grid: Landscape, out_dir: Path) -> list[Path]:
    """``landscape.png`` and ``landscape.csv`` (one row per cell)."""
    figure = plot_landscape(grid, Path(out_dir) / LANDSCAPE_FIGURE)
    header = [grid.x_key, grid.y_key, *LANDSCAPE_CSV_COLUMNS]
    rows = [
        [
            grid.x_values[col],
            grid.y_values[row],
            int(seeds) if not math.isnan(seeds) else 0,
            grid.median_return[row, col],
            grid.zone_fraction[row, col],
            _format(grid.full_length_episode[row, col], "value"),
        ]
        for (row, col), seeds in np.ndenumerate(grid.seeds)
    ]
    return [figure, write_csv(Path(out_dir) / LANDSCAPE_CSV, header, rows)]
