"""Searches' schedules in ``drone-report``: the values each agent of a PBT or halving run was trained with.

For each population run of a sweep trained with a search (``hydra/launcher=pbt``, ``halving`` or
``pbt_replay``: its checkpoint holds a lineage), every agent with a final return is followed back
through the lineage (:func:`drone_torchrl.training.pbt.schedule`): ``pbt_schedules.png`` draws each
key whose values change against the update, one line per agent coloured by its final return (the
best agent thick and labelled), and ``pbt_schedules.csv`` lists every agent's steps, best first.
"""

from __future__ import annotations

import math
from pathlib import Path

from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint
from drone_torchrl.io.storage import new_figure, write_csv, write_figure
from drone_torchrl.training.pbt import recorded_keys, schedule

SCHEDULES_FIGURE = "pbt_schedules.png"
SCHEDULES_CSV = "pbt_schedules.csv"
PANEL_SIZE = (5.0, 3.2)
# The most agents drawn (the best by final return): beyond, lines hide each other; the CSV has all.
MAX_DRAWN = 300


def pbt_runs(sweep_dir: Path) -> list[Path]:
    """The population runs of ``sweep_dir`` (or ``sweep_dir`` itself) trained with a search (a lineage)."""
    folders = [Path(sweep_dir), *sorted(p for p in Path(sweep_dir).glob("population_*") if p.is_dir())]
    return [f for f in folders if (f / "lineage.parquet").is_file() and (f / CHECKPOINT_DIR / LAST).is_file()]


def write_schedules(run_dir: Path, out_dir: Path, prefix: str = "") -> list[Path]:
    """``<prefix>pbt_schedules.png`` and ``.csv`` of one searched population run into ``out_dir``."""
    import matplotlib

    state = load_checkpoint(Path(run_dir) / CHECKPOINT_DIR / LAST)
    budget = max(int(e) for e in state["updates_done"])
    initial = {key: values for key, values in state["agents"].items() if key != "name"}
    keys = list(recorded_keys(initial))
    # Every agent with a final return, best first (unfinished or diverged agents have none).
    finals = [math.nan if f is None else f["final_return"] for f in state["final"]]
    ranked = sorted((i for i in range(len(finals)) if not math.isnan(finals[i])), key=lambda i: -finals[i])
    agents = [(i, finals[i], schedule(state["search"]["lineage"], initial, i, keys)) for i in ranked]
    # A key no agent's schedule changes (e.g. an unsearched weight decay) gets no panel.
    varying = [k for k in keys if len({v[k] for _, _, steps in agents for _, v in steps}) > 1] or keys[:1]
    drawn = agents[:MAX_DRAWN]
    fig = new_figure((PANEL_SIZE[0] * len(varying) + 1.0, PANEL_SIZE[1]))
    fig.set_layout_engine("constrained")  # room for the shared colour bar
    axes = fig.subplots(1, len(varying), squeeze=False)
    finals = [final for _, final, _ in drawn] or [0.0]
    low, high = min(finals), max(finals)
    norm = matplotlib.colors.Normalize(low, high if high > low else low + 1)  # equal finals: one colour
    colours = matplotlib.colormaps["viridis"]
    for ax, key in zip(axes[0], varying, strict=True):
        for rank, (agent, final, steps) in reversed(list(enumerate(drawn))):  # the best drawn last, on top
            updates = [u for u, _ in steps] + [budget]
            values = [v[key] for _, v in steps]
            best = rank == 0
            label = f"best: agent {agent} (final {final:.0f})" if best else None
            width, alpha = (2.5, 1.0) if best else (0.8, 0.6)
            line = {"color": colours(norm(final)), "linewidth": width, "alpha": alpha, "label": label}
            ax.step(updates, [*values, values[-1]], where="post", **line)
        positive = all(v[key] > 0 for _, _, steps in drawn for _, v in steps)
        ax.set(xlabel="update", ylabel=key, yscale="log" if key != "algo.gamma" and positive else "linear")
    if drawn:
        axes[0][0].legend(fontsize="small")
    fig.colorbar(matplotlib.cm.ScalarMappable(norm, colours), ax=axes[0].tolist(), label="final return")
    shown = (
        "every agent's" if len(drawn) == len(agents) else f"the best {len(drawn)} of {len(agents)} agents'"
    )
    fig.suptitle(f"{Path(run_dir).name}: the values {shown} weights were trained with", fontsize="medium")
    figure = write_figure(fig, Path(out_dir) / f"{prefix}{SCHEDULES_FIGURE}", dpi=120)
    rows = [
        [agent, final, update, *(values[k] for k in keys)]
        for agent, final, steps in agents
        for update, values in steps
    ]
    table = write_csv(
        Path(out_dir) / f"{prefix}{SCHEDULES_CSV}", ["agent", "final_return", "from_update", *keys], rows
    )
    return [figure, table]
