"""PBT's schedules in ``drone-report``: the values the best agents of a PBT run were trained with.

For each population run of a sweep trained with ``hydra/launcher=pbt`` (its checkpoint holds a
lineage), the best ``BEST_AGENTS`` agents by final return are followed back through the lineage
(:func:`drone_torchrl.training.pbt.schedule`): ``pbt_schedules.png`` draws each searched key
against the update, one line per agent, and ``pbt_schedules.csv`` lists the steps.
"""

from __future__ import annotations

import math
from pathlib import Path

from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint
from drone_torchrl.io.storage import new_figure, write_csv, write_figure
from drone_torchrl.training.pbt import schedule

BEST_AGENTS = 3
SCHEDULES_FIGURE = "pbt_schedules.png"
SCHEDULES_CSV = "pbt_schedules.csv"
FIGURE_DPI = 120
PANEL_SIZE = (5.0, 3.2)


def pbt_runs(sweep_dir: Path) -> list[Path]:
    """The population runs of ``sweep_dir`` (or ``sweep_dir`` itself) trained with PBT."""
    folders = [Path(sweep_dir), *sorted(p for p in Path(sweep_dir).glob("population_*") if p.is_dir())]
    return [f for f in folders if (f / "lineage.parquet").is_file() and (f / CHECKPOINT_DIR / LAST).is_file()]


def best_schedules(run_dir: Path, best: int = BEST_AGENTS) -> tuple[list[str], list[tuple[int, float, list]]]:
    """The searched keys, and ``(agent, final return, schedule)`` of the ``best`` agents.

    The best are ranked by final return; agents without one (unfinished or diverged) are left out.
    """
    state = load_checkpoint(Path(run_dir) / CHECKPOINT_DIR / LAST)
    settings = state["search"]["settings"]
    keys = list(settings["keys"])
    finals = [math.nan if f is None else f["final_return"] for f in state["final"]]
    ranked = sorted((i for i in range(len(finals)) if not math.isnan(finals[i])), key=lambda i: -finals[i])
    initial = {key: state["agents"][key] for key in keys}
    lineage = state["search"]["lineage"]
    return keys, [(i, finals[i], schedule(lineage, initial, i, keys)) for i in ranked[:best]]


def write_schedules(run_dir: Path, out_dir: Path, prefix: str = "") -> list[Path]:
    """``<prefix>pbt_schedules.png`` and ``.csv`` of one PBT population run into ``out_dir``."""
    keys, best = best_schedules(run_dir)
    budget = max(int(e) for e in load_checkpoint(Path(run_dir) / CHECKPOINT_DIR / LAST)["updates_done"])
    fig = new_figure((PANEL_SIZE[0] * len(keys), PANEL_SIZE[1]))
    axes = fig.subplots(1, len(keys), squeeze=False)
    for ax, key in zip(axes[0], keys, strict=True):
        for agent, final, steps in best:
            updates = [u for u, _ in steps] + [budget]
            values = [v[key] for _, v in steps]
            ax.step(updates, [*values, values[-1]], where="post", label=f"agent {agent} (final {final:.0f})")
        ax.set_xlabel("update")
        ax.set_ylabel(key)
        ax.set_yscale("log" if key == "algo.lr" else "linear")
    axes[0][0].legend(fontsize="small")
    fig.suptitle(f"{Path(run_dir).name}: the values the best agents' weights were trained with")
    fig.tight_layout()
    figure = write_figure(fig, Path(out_dir) / f"{prefix}{SCHEDULES_FIGURE}", dpi=FIGURE_DPI)
    rows = [
        [agent, final, update, *(values[k] for k in keys)]
        for agent, final, steps in best
        for update, values in steps
    ]
    table = write_csv(
        Path(out_dir) / f"{prefix}{SCHEDULES_CSV}", ["agent", "final_return", "from_update", *keys], rows
    )
    return [figure, table]
