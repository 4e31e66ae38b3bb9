"""Does a search beat the landscape's grid? A protocol over several tuning seeds, not one run.

    python benchmarks/search_protocol.py                  # the full protocol (8 tuning x 16 test seeds)
    python benchmarks/search_protocol.py --estimate-only  # time a small population run, print the cost
    python benchmarks/search_protocol.py --tuning-seeds 110 111 --test-seeds 500 501 --max-values 2 \\
        --episodes-fraction 0.005 --out /tmp/protocol env.max_steps=20   # a smoke run (seconds a sweep)

Each search is tuned on each tuning seed (default 110-117) and what it found is replayed on fresh
test seeds (default 500-515) that no search saw, as Eimer, Lindauer & Raileanu (ICML 2023) ask of
hyperparameter optimisation in RL:

- the grid: the landscape's values (``conf/sweep/landscape.yaml``: 8 learning rates x 8 discounts)
  on the tuning seed, one population (``hydra/launcher=population``); its best cell (highest final
  return) is retrained with fixed values on the test seeds;
- ``pbt``: ``hydra/launcher=pbt`` over 8 learning rates x 4 discounts (32 agents),
  ``every_updates=400``, 4,800 episodes each (10% of the four-seed grid's episodes), and
  ``hydra/launcher=pbt_replay`` of its best final agent on the test seeds;
- ``halving``: ``hydra/launcher=halving`` over the 8 x 8 values (64 slots), 2,400 episodes each,
  ``rungs=[300,900]``, ``fraction=0.67``, and ``pbt_replay`` of its best final agent;
- ``pb2``: ``hydra/launcher=pb2`` (population-based bandits: PBT whose explore step a Gaussian
  process chooses) with PBT's values, interval and budget, and ``pbt_replay`` of its best final agent.
- the paper's default (alpha 1e-4, gamma 0.99) on the test seeds, once.

These settings (the module's constants, scaled by ``--episodes-fraction``) are fixed before any run:
they are printed first and written to ``<out>/settings.json``; a protocol started in a folder with
other settings is refused. Every sweep has a fixed folder under ``--out`` and a ``<name>.done.json``
next to it once it finished: the same command again skips the finished sweeps and continues the
others from their checkpoints (a killed protocol resumes). Extra arguments are Hydra overrides for
every sweep; each runs as ``drone-train -m ... eval.every_episodes=0 eval.video=false
progress=false``, its output in ``<name>.log``.

Reported, per tuning seed and across them: each replay's median final return and fraction of test
seeds in the zone (``drone-report``'s reader, as ``benchmarks/compare_sweeps.py``), the bootstrap 95%
intervals of (search - grid's best cell) and (search - paper default) in the median, the episodes and
wall-clock each search spent tuning; then the goal: for at least 6 of 8 tuning seeds (the same
share of fewer) the upper end of PBT minus grid is >= 0, and on every tuning seed PBT's median is at
least the paper default's minus 100. ``results.md`` and ``results.csv`` in ``--out``.

Two versions of a search are compared on the same grid: ``--drone-train PATH`` runs the searches'
tuning and replay sweeps with another installation's ``drone-train`` (e.g. another checkout's
venv; the grid and the paper default keep this one's), and ``--grid-from DIR`` reads the grid, its
test sweeps and the paper default from an earlier protocol folder of the same settings (its
``settings.json`` may differ only in the searches and tuning seeds) instead of running them again.
Both are settings (``settings.json``); ``results.md`` and ``results.csv`` say which code ran each row::

    python benchmarks/search_protocol.py --searches pbt --drone-train ../old/.venv/bin/drone-train \
        --grid-from benchmarks/out/search_protocol --out benchmarks/out/search_protocol_old

"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_sweeps import bootstrap_difference, finals  # noqa: E402  (a sibling script)

from drone_torchrl.config import config_dir  # noqa: E402
from drone_torchrl.episodes import RUNNING_MEAN_WINDOW  # noqa: E402
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR, LAST, load_checkpoint  # noqa: E402
from drone_torchrl.report.distribution import BOOTSTRAP_SEED, distribution  # noqa: E402
from drone_torchrl.report.runs import (  # noqa: E402
    COL_LENGTH,
    COL_WALL_CLOCK,
    group_runs,
    load_runs,
)
from drone_torchrl.training.pbt import schedule  # noqa: E402

# The protocol, fixed before any test run (docs/sweeps.md's settings).
TUNING_SEEDS = tuple(range(110, 118))
TEST_SEEDS = tuple(range(500, 516))
GRID_EPISODES = 6000
TEST_EPISODES = 6000
PBT_GAMMAS = (0.94821, 0.97317, 0.98611, 0.99627)  # 4 of the landscape's 8: 32 agents with 8 rates
PBT_EPISODES = 4800
PBT_EVERY_UPDATES = 400
HALVING_EPISODES = 2400
HALVING_RUNGS = (300, 900)
HALVING_FRACTION = 0.67
PAPER = {"algo.lr": 1e-4, "algo.gamma": 0.99}
GOAL_SHARE = 6 / 8  # of the tuning seeds on which PBT's upper end vs the grid must be >= 0
PAPER_MARGIN = 100.0  # PBT's median may be at most this far below the paper default's
COMMON = ("eval.every_episodes=0", "eval.video=false", "progress=false")
CALIBRATION_SEED = 0
# What --grid-from reads from an earlier protocol folder (under seed_<s>/ for each tuning seed).
GRID_SWEEPS = ("grid", "grid_test")
PAPER_SWEEP = Path("paper_default") / "test"
# Settings that may differ between a protocol and the folder its grid is read from.
NOT_THE_GRIDS = ("tuning_seeds", "searches", "drone_train", "grid_from")


def own_drone_train() -> Path:
    """The ``drone-train`` of the interpreter running this script (its venv's)."""
    return Path(sys.executable).parent / "drone-train"


def code_of(drone_train: Path) -> str:
    """Which drone_torchrl ``drone_train`` runs: its version, and its checkout's commit if editable.

    Asked of the interpreter beside it (a venv's ``bin``), which names the installed distribution's
    source folder (``direct_url.json``) for an editable install; ``unknown`` when it cannot tell.
    """
    python = next((p for p in (drone_train.parent / n for n in ("python", "python3")) if p.is_file()), None)
    if python is None:
        return "drone_torchrl of unknown version"
    script = (
        "import importlib.metadata as m, json; d = m.distribution('drone_torchrl'); "
        "print(json.dumps([d.version, json.loads(d.read_text('direct_url.json') or '{}').get('url', '')]))"
    )
    found = subprocess.run([str(python), "-I", "-c", script], capture_output=True, text=True)
    if found.returncode:
        return "drone_torchrl of unknown version"
    version, url = json.loads(found.stdout)
    text = f"drone_torchrl {version}"
    if url.startswith("file://"):
        source = unquote(urlparse(url).path)
        commit = subprocess.run(
            ["git", "-C", source, "describe", "--always", "--dirty", "--abbrev=7"],
            capture_output=True,
            text=True,
        )
        text += f" from {source}" + (f" at {commit.stdout.strip()}" if commit.returncode == 0 else "")
    return text


def landscape_values() -> tuple[list[float], list[float]]:
    """The landscape's learning rates and discounts, read from ``conf/sweep/landscape.yaml``."""
    params = OmegaConf.load(Path(config_dir()) / "sweep" / "landscape.yaml").hydra.sweeper.params
    return (
        [float(v) for v in str(params["algo.lr"]).split(",")],
        [float(v) for v in str(params["algo.gamma"]).split(",")],
    )


def spread(values: Sequence[float], keep: int | None) -> list[float]:
    """``keep`` of ``values`` spread evenly, both ends included (all of them with ``None``)."""
    if keep is None or keep >= len(values):
        return list(values)
    return [values[round(i * (len(values) - 1) / (keep - 1))] for i in range(keep)]


def scaled(episodes: int, fraction: float) -> int:
    """A budget scaled for a smoke run, at least 1."""
    return max(1, round(episodes * fraction))


@dataclass(frozen=True)
class Plan:
    """Everything a protocol's runs depend on; written to ``settings.json`` before any run."""

    tuning_seeds: tuple[int, ...]
    test_seeds: tuple[int, ...]
    searches: tuple[str, ...]
    lrs: tuple[float, ...]
    grid_gammas: tuple[float, ...]
    pbt_gammas: tuple[float, ...]
    grid_episodes: int
    test_episodes: int
    pbt_episodes: int
    pbt_every_updates: int
    halving_episodes: int
    halving_rungs: tuple[int, ...]
    halving_fraction: float
    paper: tuple[tuple[str, float], ...]
    overrides: tuple[str, ...]
    drone_train: str
    """The executable of the searches' tuning and replay sweeps."""
    grid_from: str | None
    """The earlier protocol folder the grid and paper default are read from (None: run here)."""

    def as_json(self) -> dict:
        """The plan as JSON data (tuples as lists, as they read back)."""
        return json.loads(json.dumps(asdict(self)))


def make_plan(args: argparse.Namespace) -> Plan:
    """The plan of the parsed command line."""
    lrs, gammas = landscape_values()
    f = args.episodes_fraction
    return Plan(
        tuning_seeds=tuple(args.tuning_seeds),
        test_seeds=tuple(args.test_seeds),
        searches=tuple(args.searches),
        lrs=tuple(spread(lrs, args.max_values)),
        grid_gammas=tuple(spread(gammas, args.max_values)),
        pbt_gammas=tuple(spread(PBT_GAMMAS, args.max_values)),
        grid_episodes=scaled(GRID_EPISODES, f),
        test_episodes=scaled(TEST_EPISODES, f),
        pbt_episodes=scaled(PBT_EPISODES, f),
        pbt_every_updates=scaled(PBT_EVERY_UPDATES, f),
        halving_episodes=scaled(HALVING_EPISODES, f),
        halving_rungs=tuple(scaled(r, f) for r in HALVING_RUNGS),
        halving_fraction=HALVING_FRACTION,
        paper=tuple(PAPER.items()),
        overrides=tuple(args.overrides),
        drone_train=str(args.drone_train),
        grid_from=None if args.grid_from is None else str(args.grid_from),
    )


def _csv(values: Sequence[float | int]) -> str:
    return ",".join(f"{v:g}" for v in values)


def grid_overrides(plan: Plan, seed: int) -> list[str]:
    """The grid on one tuning seed: every cell of the landscape, one population."""
    return [
        "hydra/launcher=population",
        f"algo.lr={_csv(plan.lrs)}",
        f"algo.gamma={_csv(plan.grid_gammas)}",
        f"seed={seed}",
        f"algo.episodes={plan.grid_episodes}",
    ]


def pbt_overrides(plan: Plan, seed: int) -> list[str]:
    """Population-based training on one tuning seed (docs/sweeps.md's command)."""
    return [
        "hydra/launcher=pbt",
        f"hydra.launcher.every_updates={plan.pbt_every_updates}",
        f"algo.lr={_csv(plan.lrs)}",
        f"algo.gamma={_csv(plan.pbt_gammas)}",
        f"seed={seed}",
        f"algo.episodes={plan.pbt_episodes}",
    ]


def halving_overrides(plan: Plan, seed: int) -> list[str]:
    """Successive halving over the grid's values on one tuning seed (docs/sweeps.md's settings)."""
    return [
        "hydra/launcher=halving",
        f"hydra.launcher.rungs=[{_csv(plan.halving_rungs)}]",
        f"hydra.launcher.fraction={plan.halving_fraction:g}",
        f"algo.lr={_csv(plan.lrs)}",
        f"algo.gamma={_csv(plan.grid_gammas)}",
        f"seed={seed}",
        f"algo.episodes={plan.halving_episodes}",
    ]


def pb2_overrides(plan: Plan, seed: int) -> list[str]:
    """Population-based bandits on one tuning seed: PBT's command with hydra/launcher=pb2."""
    return ["hydra/launcher=pb2", *pbt_overrides(plan, seed)[1:]]


# A search: its name, the launcher it needs and its tuning command. Each is replayed with
# hydra/launcher=pbt_replay of its best final agent.
SEARCHES: dict[str, tuple[str, Callable[[Plan, int], list[str]]]] = {
    "pbt": ("pbt", pbt_overrides),
    "halving": ("halving", halving_overrides),
    "pb2": ("pb2", pb2_overrides),
}


def available_launchers() -> set[str]:
    """The ``hydra/launcher`` options Hydra can compose: the plug-in's schemas and ``conf/``'s files."""
    from hydra.core.config_store import ConfigStore

    import drone_torchrl.launcher_schemas  # noqa: F401  (stores the schemas)

    stored = {Path(name).stem for name in ConfigStore.instance().list("hydra/launcher")}
    return stored | {p.stem for p in (Path(config_dir()) / "hydra" / "launcher").glob("*.yaml")}


def testing_overrides(plan: Plan) -> list[str]:
    """The test seeds and budget every replay shares."""
    return [f"seed={_csv(plan.test_seeds)}", f"algo.episodes={plan.test_episodes}"]


# --------------------------------------------------------------------------------------------------
# Running sweeps


@dataclass
class Sweep:
    """A finished sweep: its folder, the command's wall-clock, whether it was continued."""

    folder: Path
    wall_clock_s: float
    resumed: bool


def sweep_arguments(folder: Path, overrides: Sequence[str], plan: Plan) -> list[str]:
    """The arguments of ``drone-train`` for one sweep into ``folder``."""
    return ["-m", *overrides, *COMMON, *plan.overrides, f"hydra.sweep.dir={folder}"]


def _done(folder: Path) -> Path:
    return folder.with_name(folder.name + ".done.json")


def run_sweep(folder: Path, overrides: Sequence[str], plan: Plan, drone_train: Path | None = None) -> Sweep:
    """``drone-train -m`` into ``folder``, or its record if it finished under the same command.

    ``drone_train``: the executable (default: this venv's).
    """
    command = [str(drone_train or own_drone_train()), *sweep_arguments(folder, overrides, plan)]
    done = _done(folder)
    if done.is_file():
        record = json.loads(done.read_text())
        if record["command"] == command[1:]:
            print(f"  {folder}: done ({record['wall_clock_s']:.1f} s), skipped", flush=True)
            return Sweep(folder, record["wall_clock_s"], record["resumed"])
        sys.exit(f"{done} was written by another command; use another --out")
    resumed = folder.exists()
    folder.parent.mkdir(parents=True, exist_ok=True)
    log = folder.with_name(folder.name + ".log")
    print("$", command[0] if drone_train else "drone-train", " ".join(command[1:]), f"> {log}", flush=True)
    start = time.perf_counter()
    with log.open("a") as out:
        code = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=_env()).returncode
    wall = time.perf_counter() - start
    if code:
        sys.exit(f"the sweep {folder} failed (exit {code}); see {log}. The same command continues it.")
    done.write_text(json.dumps({"command": command[1:], "wall_clock_s": wall, "resumed": resumed}))
    print(f"  {wall:.1f} s", flush=True)
    return Sweep(folder, wall, resumed)


def read_sweep(folder: Path, overrides: Sequence[str], plan: Plan) -> Sweep:
    """A finished sweep of an earlier protocol (``--grid-from``): its record, checked against ours.

    Its command must be the one this protocol would run, but for its folder (``hydra.sweep.dir``,
    which may have been given relative to where that protocol ran).
    """
    done = _done(folder)
    if not done.is_file():
        sys.exit(f"--grid-from: {done} is missing: that protocol has not finished this sweep")
    record = json.loads(done.read_text())

    def own(arguments: Sequence[str]) -> list[str]:
        return [a for a in arguments if not a.startswith("hydra.sweep.dir=")]

    if own(record["command"]) != own(sweep_arguments(folder, overrides, plan)):
        sys.exit(f"--grid-from: {done} was written by another command than this protocol's")
    print(f"  {folder}: read ({record['wall_clock_s']:.1f} s)", flush=True)
    return Sweep(folder, record["wall_clock_s"], record["resumed"])


def _env() -> dict[str, str]:
    return {**os.environ, "SDL_VIDEODRIVER": os.environ.get("SDL_VIDEODRIVER", "dummy")}


def _population(sweep: Path) -> Path:
    """The one population folder of a search's sweep (what ``pbt_replay`` reads)."""
    found = sorted(sweep.glob("population_*"))
    if len(found) != 1:
        sys.exit(f"{sweep} holds {len(found)} population folders; a search makes one")
    return found[0].resolve()


# --------------------------------------------------------------------------------------------------
# Reading results


def pooled_finals(sweep: Path, window: int) -> tuple[np.ndarray, float]:
    """Every run's final return in ``sweep`` (its settings pooled: a replay's agents end alike)."""
    found = finals(sweep, window)
    values = np.concatenate([v for v, _ in found.values()])
    return values, next(iter(found.values()))[1]


def spent(sweep: Path) -> int:
    """The episodes a sweep trained, all agents (a halving slot's restarts included)."""
    return sum(run.episodes for run in load_runs(sweep))


def best_cell(sweep: Path, window: int) -> tuple[dict[str, str], str]:
    """The grid's best cell (highest median final return over the tuning seed's runs) and a description."""
    settings = group_runs(load_runs(sweep))
    medians = [distribution(s, window).median for s in settings]
    best = settings[int(np.argmax(medians))]
    values = {key: value for key, value in best.pairs if key in PAPER}
    text = ", ".join(f"{key.split('.')[-1]} {value}" for key, value in values.items())
    return values, f"{text} (final {max(medians):.0f})"


def replayed(test: Path) -> str:
    """The agent a replay followed (its checkpoint's record) and that agent's values over the updates.

    A replay written before its checkpoint kept the schedule has its run and agent only: the
    schedule is then read from that run's lineage (what the replay itself read when it started).
    """
    record = load_checkpoint(_population(test) / CHECKPOINT_DIR / LAST)["search"]["settings"]
    run = load_checkpoint(Path(record["run"]) / CHECKPOINT_DIR / LAST)
    source = run["final"][record["agent"]]
    steps = record.get("schedule") or schedule(run["search"]["lineage"], run["agents"], record["agent"])
    text, last = [], None
    for update, values in steps:
        mine = tuple((key, values[key]) for key in PAPER if key in values)
        if mine != last:  # an exploit that kept the values is no change
            text.append(f"{update}: " + ", ".join(f"{key.split('.')[-1]} {v:.3g}" for key, v in mine))
            last = mine
    return f"agent {record['agent']} (final {source['final_return']:.0f}): {'; '.join(text)}"


@dataclass
class Row:
    """One search on one tuning seed, replayed on the test seeds."""

    tuning_seed: int | None
    search: str
    found: str
    tuning_episodes: int
    tuning_wall_clock_s: float
    resumed: bool
    """The tuning sweep was continued: its wall-clock counts only the last command."""
    test_seeds: int
    median: float
    in_zone: float
    vs_grid: tuple[float, float, float] | None
    vs_paper: tuple[float, float, float] | None
    code: str = ""
    """Which code ran the row's sweeps (:func:`code_of`), or where they were read from."""


def difference(before: np.ndarray, after: np.ndarray) -> tuple[float, float, float]:
    """(after - before) in the median, with its bootstrap 95% interval (compare_sweeps.py's)."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)  # each row's own: the same with more tuning seeds
    low, high = bootstrap_difference(before, after, lambda x: np.median(x, axis=-1), rng)
    return float(np.median(after) - np.median(before)), low, high


def _fmt(diff: tuple[float, float, float] | None) -> str:
    return "" if diff is None else f"{diff[0]:+.0f} [{diff[1]:+.0f}, {diff[2]:+.0f}]"


def markdown(rows: Sequence[Row]) -> str:
    """The table of every row, after the code that ran them (each distinct ``code`` once)."""
    codes = {}
    for r in rows:
        codes.setdefault(r.code, []).append(r.search)
    lines = [
        "Code:",
        *(f"- {', '.join(dict.fromkeys(searches))}: {code}" for code, searches in codes.items() if code),
        "",
        "| tuning seed | search | found | tuning episodes | tuning wall-clock | test seeds: median final "
        "return | in the zone | minus grid's best cell [95% CI] | minus paper default [95% CI] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        seed = "" if r.tuning_seed is None else str(r.tuning_seed)
        wall = (
            f"{r.tuning_wall_clock_s:.0f} s{' (resumed)' if r.resumed else ''}" if r.tuning_episodes else ""
        )
        lines.append(
            f"| {seed} | {r.search} | {r.found} | {r.tuning_episodes:,} | {wall} | {r.median:.0f} "
            f"| {r.in_zone:.2f} | {_fmt(r.vs_grid)} | {_fmt(r.vs_paper)} |"
        )
    return "\n".join(lines)


def summary(rows: Sequence[Row], plan: Plan) -> str:
    """Each search across the tuning seeds, and the goal check."""
    lines = [
        "",
        "| search | tuning seeds | median of the medians | lowest | highest | not worse than the grid "
        "(upper end >= 0) | mean tuning episodes | total tuning wall-clock |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for search in ("grid", *plan.searches):
        mine = [r for r in rows if r.search == search and r.tuning_seed is not None]
        if not mine:
            continue
        medians = np.array([r.median for r in mine])
        not_worse = "" if search == "grid" else f"{sum(r.vs_grid[2] >= 0 for r in mine)}/{len(mine)}"
        lines.append(
            f"| {search} | {len(mine)} | {np.median(medians):.0f} | {medians.min():.0f} | {medians.max():.0f} "
            f"| {not_worse} | {np.mean([r.tuning_episodes for r in mine]):,.0f} "
            f"| {sum(r.tuning_wall_clock_s for r in mine):.0f} s |"
        )
    pbt = [r for r in rows if r.search == "pbt" and r.tuning_seed is not None]
    if pbt:
        needed = math.ceil(GOAL_SHARE * len(pbt))
        not_worse = sum(r.vs_grid[2] >= 0 for r in pbt)
        above_paper = sum(r.vs_paper[0] >= -PAPER_MARGIN for r in pbt)
        met = not_worse >= needed and above_paper == len(pbt)
        lines += [
            "",
            f"Goal: PBT not worse than the grid's best cell on >= {needed}/{len(pbt)} tuning seeds: "
            f"{not_worse}/{len(pbt)}; PBT's median >= the paper default's - {PAPER_MARGIN:.0f} on every "
            f"tuning seed: {above_paper}/{len(pbt)}. Goal {'met' if met else 'not met'}.",
        ]
    return "\n".join(lines)


def write_csv(rows: Sequence[Row], path: Path) -> None:
    """One line per row, differences as three columns each."""
    with path.open("w", newline="") as out:
        writer = csv.writer(out)
        head = ["tuning_seed", "search", "found", "tuning_episodes", "tuning_wall_clock_s", "resumed"]
        writer.writerow(
            head
            + [
                "test_seeds",
                "median",
                "in_zone",
                *(f"{d}_{p}" for d in ("vs_grid", "vs_paper") for p in ("diff", "low", "high")),
                "code",
            ]
        )
        for r in rows:
            diffs = [f"{v:.1f}" if d else "" for d in (r.vs_grid, r.vs_paper) for v in (d or (0, 0, 0))]
            writer.writerow(
                [r.tuning_seed if r.tuning_seed is not None else "", r.search, r.found, r.tuning_episodes]
                + [
                    f"{r.tuning_wall_clock_s:.1f}",
                    r.resumed,
                    r.test_seeds,
                    f"{r.median:.1f}",
                    f"{r.in_zone:.3f}",
                    *diffs,
                    r.code,
                ]
            )


# --------------------------------------------------------------------------------------------------
# Estimating the cost


def protocol_sweeps(plan: Plan) -> list[tuple[int, int]]:
    """``(agents, episodes each)`` of every sweep of the protocol."""
    grid = len(plan.lrs) * len(plan.grid_gammas)
    tests = len(plan.test_seeds)
    per_seed = [(grid, plan.grid_episodes), (tests, plan.test_episodes)]
    sizes = {
        "pbt": (len(plan.lrs) * len(plan.pbt_gammas), plan.pbt_episodes),
        "pb2": (len(plan.lrs) * len(plan.pbt_gammas), plan.pbt_episodes),
        "halving": (grid, plan.halving_episodes),
    }
    for search in plan.searches:
        per_seed += [sizes.get(search, (grid, plan.pbt_episodes)), (tests, plan.test_episodes)]
    return per_seed * len(plan.tuning_seeds) + [(tests, plan.test_episodes)]


def estimate(plan: Plan, out: Path, episodes: int) -> str:
    """The protocol's episodes, and its wall-clock from a timed population of the grid's size.

    A population steps its agents in one batch, so an update costs a fixed part plus a part per
    agent-step. Both are fitted (least squares) to the measured time of each update of a
    population of the grid's values against the mean length of its episodes; each sweep is then
    its episodes per agent times the update's cost at its number of agents, plus the measured
    start of a command. Trained agents fly longer than the measured ones: the low figure takes
    episodes as long as measured, the high one every episode at ``env.max_steps``.
    """
    folder = out / "calibration" / f"episodes_{episodes}"
    sweep = run_sweep(
        folder, [*grid_overrides(plan, CALIBRATION_SEED)[:-1], f"algo.episodes={episodes}"], plan
    )
    runs = load_runs(folder)
    walls = np.stack([run.columns[COL_WALL_CLOCK] for run in runs]).max(axis=0)
    lengths = np.stack([run.columns[COL_LENGTH] for run in runs]).mean(axis=0)
    agents, max_steps = len(runs), runs[0].max_steps
    per_step, fixed = np.polyfit(lengths[1:], np.diff(walls), 1) if np.ptp(lengths) else (0.0, 0.0)
    if per_step <= 0 or fixed < 0:  # too few updates to tell the parts apart: all per step
        per_step, fixed = (walls[-1] - walls[0]) / max(1.0, lengths[1:].sum()), 0.0
    per_agent_step = per_step / agents
    start = max(0.0, sweep.wall_clock_s - float(walls[-1]))
    sweeps = protocol_sweeps(plan)

    def minutes(length: float) -> float:
        return sum(start + e * (fixed + per_agent_step * n * length) for n, e in sweeps) / 60

    return (
        f"Estimate: {len(sweeps)} sweeps, {sum(n * e for n, e in sweeps):,} episodes. Measured on "
        f"{agents} agents x {episodes} episodes ({agents * episodes / walls[-1]:,.0f} episodes/s, "
        f"mean episode {lengths.mean():.0f} of {max_steps} steps): an update costs "
        f"{fixed * 1e3:.2f} ms + {per_agent_step * 1e6:.2f} us an agent-step, a command starts in "
        f"{start:.1f} s. Wall-clock: {minutes(float(lengths.mean())):.0f} min with episodes as long "
        f"as measured, {minutes(max_steps):.0f} min with every episode {max_steps} steps."
    )


# --------------------------------------------------------------------------------------------------


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line; a bad value is refused in one line before anything runs."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--tuning-seeds", nargs="+", type=int, default=list(TUNING_SEEDS))
    parser.add_argument("--test-seeds", nargs="+", type=int, default=list(TEST_SEEDS))
    parser.add_argument(
        "--searches",
        nargs="+",
        default=list(SEARCHES),
        help=f"the searches to run besides the grid (known: {', '.join(SEARCHES)})",
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/search_protocol"))
    parser.add_argument(
        "--episodes-fraction",
        type=float,
        default=1.0,
        help="scale every budget, PBT's interval and halving's rungs (a smoke run: 0.005)",
    )
    parser.add_argument(
        "--max-values",
        type=int,
        default=None,
        help="keep this many learning rates and discounts of each list (a smoke run: 2; 4 agents)",
    )
    parser.add_argument(
        "--calibration-episodes",
        type=int,
        default=1500,
        help="episodes per agent of the timed population run of the estimate (long enough that "
        "episodes grow: the fit needs short and long ones)",
    )
    parser.add_argument(
        "--drone-train",
        type=Path,
        default=own_drone_train(),
        help="the drone-train of the searches' tuning and replay sweeps, e.g. another checkout's venv "
        "(default: this venv's; the grid and paper default always run with this venv's)",
    )
    parser.add_argument(
        "--grid-from",
        type=Path,
        default=None,
        help="read the grid, its test sweeps and the paper default from this earlier protocol folder "
        "(same settings but for the searches and tuning seeds) instead of running them",
    )
    parser.add_argument("--estimate-only", action="store_true", help="print the cost, run no protocol")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every sweep, e.g. env.max_steps=20")
    args = parser.parse_args(argv)

    def refuse(message: str) -> None:  # one line, no usage block: the option and value say it all
        parser.exit(2, f"{parser.prog}: error: {message}\n")

    for option, seeds in (("--tuning-seeds", args.tuning_seeds), ("--test-seeds", args.test_seeds)):
        if len(set(seeds)) != len(seeds):
            refuse(f"{option} {' '.join(map(str, seeds))}: a seed is repeated")
    shared = sorted(set(args.tuning_seeds) & set(args.test_seeds))
    if shared:
        refuse(
            f"--tuning-seeds and --test-seeds share {', '.join(map(str, shared))}: test seeds must be fresh"
        )
    if len(args.test_seeds) < 2:
        refuse(f"--test-seeds {args.test_seeds[0]}: a bootstrap interval needs at least 2 test seeds")
    if not 0 < args.episodes_fraction <= 1:
        refuse(f"--episodes-fraction {args.episodes_fraction}: must be in (0, 1]")
    if args.max_values is not None and args.max_values < 2:
        refuse(f"--max-values {args.max_values}: must be at least 2 (PBT needs 4 agents)")
    if args.calibration_episodes < 1:
        refuse(f"--calibration-episodes {args.calibration_episodes}: must be at least 1")
    args.drone_train = args.drone_train.absolute()
    if not (args.drone_train.is_file() and os.access(args.drone_train, os.X_OK)):
        refuse(f"--drone-train {args.drone_train}: not an executable file")
    if args.grid_from is not None:
        args.grid_from = args.grid_from.absolute()
        if not (args.grid_from / "settings.json").is_file():
            refuse(f"--grid-from {args.grid_from}: no settings.json there (not a protocol's folder)")
        if args.grid_from == args.out.absolute():
            refuse(f"--grid-from {args.grid_from}: is --out; a protocol reads its own grid without it")
        if args.estimate_only:
            refuse("--grid-from with --estimate-only: the estimate runs no grid")
    unknown = [s for s in args.searches if s not in SEARCHES]
    if unknown:
        refuse(f"--searches {' '.join(unknown)}: unknown; known: {', '.join(SEARCHES)}")
    missing = [s for s in args.searches if SEARCHES[s][0] not in available_launchers()]
    if missing:
        refuse(
            f"--searches {' '.join(missing)}: no hydra/launcher={SEARCHES[missing[0]][0]} in this installation"
        )
    for item in args.overrides:
        if item.partition("=")[0].lstrip("+~") in (
            "seed",
            "algo.lr",
            "algo.gamma",
            "algo.episodes",
            "hydra.sweep.dir",
        ):
            refuse(f"override {item}: the protocol sets {item.partition('=')[0]} itself")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    """Run (or resume) the protocol and print its tables."""
    args = parse_args(argv)
    plan = make_plan(args)
    out = args.out
    settings = out / "settings.json"
    # Settings a folder written before they existed had: this venv's drone-train, its own grid.
    earlier = {"drone_train": str(own_drone_train()), "grid_from": None}
    # More tuning seeds and searches may be added to a protocol later (each search has folders of
    # its own); anything else would mix two protocols.
    if settings.is_file():
        before, now = json.loads(settings.read_text()), plan.as_json()
        changed = [
            key
            for key in now
            if key not in ("tuning_seeds", "searches") and before.get(key, earlier.get(key)) != now[key]
        ]
        if changed:
            sys.exit(f"{settings} holds other {', '.join(changed)}: use another --out, or its settings")
    grid_out, take = out, run_sweep
    if args.grid_from is not None:
        grid_out, take = args.grid_from, read_sweep
        theirs, now = json.loads((grid_out / "settings.json").read_text()), plan.as_json()
        changed = [key for key in now if key not in NOT_THE_GRIDS and theirs.get(key) != now[key]]
        if changed:
            sys.exit(
                f"--grid-from {grid_out}: its settings.json holds other {', '.join(changed)} "
                f"({'; '.join(f'{k}: {theirs.get(k)} there, {now[k]} here' for k in changed)})"
            )
        missing = [
            str(grid_out / f"seed_{seed}" / f"{name}.done.json")
            for seed in plan.tuning_seeds
            for name in GRID_SWEEPS
            if not _done(grid_out / f"seed_{seed}" / name).is_file()
        ]
        if not _done(grid_out / PAPER_SWEEP).is_file():
            missing.insert(0, str(_done(grid_out / PAPER_SWEEP)))
        if missing:
            sys.exit(f"--grid-from {grid_out}: unfinished sweeps, no {', '.join(missing)}")
    out.mkdir(parents=True, exist_ok=True)
    settings.write_text(json.dumps(plan.as_json(), indent=1))
    print("Settings (fixed before any run):")
    for key, value in plan.as_json().items():
        print(f"  {key}: {value}")
    drone_train = Path(plan.drone_train)
    grid_code = (
        f"read from {grid_out}" if args.grid_from else f"{own_drone_train()} ({code_of(own_drone_train())})"
    )
    search_code = f"{drone_train} ({code_of(drone_train)})"
    print(f"The grid and paper default: {grid_code}\nThe searches: {search_code}\n", flush=True)
    if args.estimate_only:
        print(estimate(plan, out, args.calibration_episodes))
        return

    window = RUNNING_MEAN_WINDOW
    paper_test = take(
        grid_out / PAPER_SWEEP,
        ["hydra/launcher=population", *(f"{k}={v:g}" for k, v in plan.paper), *testing_overrides(plan)],
        plan,
    )
    paper, zone = pooled_finals(paper_test.folder, window)
    rows = [
        Row(
            None,
            "paper default",
            "alpha 1e-4, gamma 0.99",
            0,
            0.0,
            False,
            paper.size,
            float(np.median(paper)),
            float((paper >= zone).mean()),
            None,
            None,
            grid_code,
        )
    ]
    for seed in plan.tuning_seeds:
        base = out / f"seed_{seed}"
        tuned = take(grid_out / f"seed_{seed}" / "grid", grid_overrides(plan, seed), plan)
        cell, found = best_cell(tuned.folder, window)
        test = take(
            grid_out / f"seed_{seed}" / "grid_test",
            ["hydra/launcher=population", *(f"{k}={v}" for k, v in cell.items()), *testing_overrides(plan)],
            plan,
        )
        grid, _ = pooled_finals(test.folder, window)
        rows.append(
            Row(
                seed,
                "grid",
                found,
                spent(tuned.folder),
                tuned.wall_clock_s,
                tuned.resumed,
                grid.size,
                float(np.median(grid)),
                float((grid >= zone).mean()),
                None,
                difference(paper, grid),
                grid_code,
            )
        )
        for search in plan.searches:
            tuned = run_sweep(base / search, SEARCHES[search][1](plan, seed), plan, drone_train)
            test = run_sweep(
                base / f"{search}_test",
                [
                    "hydra/launcher=pbt_replay",
                    f"hydra.launcher.run={_population(tuned.folder)}",
                    *testing_overrides(plan),
                ],
                plan,
                drone_train,
            )
            values, _ = pooled_finals(test.folder, window)
            rows.append(
                Row(
                    seed,
                    search,
                    replayed(test.folder),
                    spent(tuned.folder),
                    tuned.wall_clock_s,
                    tuned.resumed,
                    values.size,
                    float(np.median(values)),
                    float((values >= zone).mean()),
                    difference(grid, values),
                    difference(paper, values),
                    search_code,
                )
            )
    text = markdown(rows) + "\n" + summary(rows, plan) + "\n"
    print()
    print(text)
    (out / "results.md").write_text(text)
    write_csv(rows, out / "results.csv")
    print(f"written: {out / 'results.md'}, {out / 'results.csv'}")


if __name__ == "__main__":
    main()
