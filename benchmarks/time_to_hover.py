"""How fast a preset reaches a hovering policy: per seed, the training time until an evaluation first
reaches ``--target`` (default 2685, within one step of the optimum 2694), and drone-eval's figures of
the run's last checkpoint.

    python benchmarks/time_to_hover.py --seeds 0-7                    # experiment=hover_optimal
    python benchmarks/time_to_hover.py --seeds 100-107                # held-out seeds
    python benchmarks/time_to_hover.py --seeds 0-3 --preset hover_optimal algo.epochs=5

Each seed is one ``drone-train experiment=<preset> seed=S`` command, one at a time, with an
evaluation every ``--every`` episodes (default: the preset's ``eval.every_episodes``; its returns are
read from ``logger=csv``'s scalars) and no videos. Printed per seed:

- *to target*: the training wall-clock (``episodes.csv``'s ``wall_clock_s``) at the first evaluation
  whose return reaches the target, less the evaluations before it;
- *training*: the run's training wall-clock (to its budget, or to the evaluation that reached
  ``eval.stop_return`` where the preset sets one), less the evaluations;
- *command*: the whole command, start-up and the final evaluation included;
- drone-eval's return, first step in the zone (of the episode that enters last) and crashes over its 100 seeded starts, on
  ``checkpoints/last.pt`` (the same evaluator: :func:`drone_torchrl.comparison.run_eval`).

The evaluations' cost is measured, not guessed: after each run, one evaluation of its last
checkpoint (the run's ``eval.episodes`` starts) is timed, median of ``--eval-repeats``, and that
times the number of evaluations is taken off. Then the median and the worst over the seeds, and
how many reached the target.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from drone_torchrl import algorithms
from drone_torchrl.comparison import run_eval
from drone_torchrl.config import config_dir, env_kwargs, run_config
from drone_torchrl.evaluation import evaluate
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.training.jobs import prepare

LAST = Path("checkpoints") / "last.pt"
SCALARS = Path("csv") / "scalars.csv"


def seed_list(text: str) -> list[int]:
    """``"0-7"`` -> 0..7; ``"0,3,5"`` and ``"0-3,9"`` too."""
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds += range(int(first), int(last or first) + 1)
    return seeds


def _train(preset: str, seed: int, run_dir: Path, every: int | None, overrides: list[str]) -> float:
    """One ``drone-train`` command; returns its wall-clock."""
    cmd = [
        str(Path(sys.executable).parent / "drone-train"),
        f"experiment={preset}",
        f"seed={seed}",
        "logger=csv",
        *([] if every is None else [f"eval.every_episodes={every}"]),
        "eval.video=false",
        "progress=false",
        f"hydra.run.dir={run_dir}",
        *overrides,
    ]
    start = time.perf_counter()
    with open(run_dir.parent / f"{run_dir.name}.log", "w") as log:
        subprocess.run(
            cmd,
            check=True,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
        )
    return time.perf_counter() - start


def _eval_returns(run_dir: Path) -> list[tuple[int, float]]:
    """(episodes done, evaluation return) of every evaluation during training, in order."""
    with open(run_dir / SCALARS, newline="") as f:
        rows = [(int(r["step"]), float(r["value"])) for r in csv.DictReader(f) if r["tag"] == "eval/return"]
    return sorted(rows)


def _eval_seconds(run_dir: Path, repeats: int) -> float:
    """The median time of one evaluation of the run's last checkpoint, flown as training flies them.

    The run's learner's ``eval_policy`` (backend=fast PPO and A2C: the C++ engine; otherwise
    TorchRL's env and the actor), with the checkpoint's actor.
    """
    state = load_checkpoint(run_dir / LAST)
    cfg = run_config(state["config"])
    with tempfile.TemporaryDirectory() as tmp:
        learner = algorithms.get(cfg.algo.name).learner([prepare(cfg, Path(tmp) / "run")])
        learner.actor(0).load_state_dict(state["actor"])
        kwargs = env_kwargs(cfg)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            evaluate(
                learner.eval_policy(), kwargs, cfg.eval.episodes, cfg.eval.seed, agents=learner.eval_agents
            )
            times.append(time.perf_counter() - start)
        learner.close()
    return statistics.median(times)


def _drone_eval(run_dir: Path) -> dict:
    """drone-eval's figures of ``<run>/checkpoints/last.pt`` (no video, no plot)."""
    overrides = [f"checkpoint={run_dir / LAST}", "video=false", "plot=false"]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        results = run_eval(compose("eval", overrides=overrides))
    return next(iter(results.values()))


def measure(
    preset: str, seed: int, out: Path, every: int | None, target: float, repeats: int, overrides: list[str]
) -> dict:
    run_dir = out / f"{preset}-seed{seed}"
    command = _train(preset, seed, run_dir, every, overrides)
    columns, _ = read_episodes(run_dir / "episodes.csv")
    clock = columns["wall_clock_s"]  # at each episode's end, evaluations so far included
    evals = _eval_returns(run_dir)
    eval_s = _eval_seconds(run_dir, repeats)
    periodic = [step for step, _ in evals if step < len(clock)]  # the last one comes after the clock stops
    hit = next((i for i, (_, value) in enumerate(evals) if value >= target), None)
    to_target = math.nan
    if hit is not None:
        step = evals[hit][0]
        to_target = float(clock[step - 1]) - eval_s * hit
    result = _drone_eval(run_dir)
    return {
        "seed": seed,
        "to_target_s": to_target,
        "episodes_to_target": evals[hit][0] if hit is not None else math.nan,
        "training_s": float(clock[-1]) - eval_s * len(periodic),
        "evaluations": len(evals),
        "eval_s": eval_s,
        "command_s": command,
        "return": result["return_mean"],
        "first_zone_step": result["first_zone_step_max"],
        "crashes": sum(v for k, v in result["causes"].items() if k != "NONE"),
    }


def _row(r: dict) -> str:
    return (
        f"| {r['seed']} | {r['to_target_s']:.1f} ({r['episodes_to_target']:.0f} episodes) | {r['training_s']:.1f} "
        f"| {r['command_s']:.1f} | {r['evaluations']} x {r['eval_s']:.2f} s | {r['return']:.1f} "
        f"| {r['first_zone_step']:.0f} | {r['crashes']} |"
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="hover_optimal", help="the experiment option (conf/experiment)")
    parser.add_argument("--seeds", type=seed_list, default=seed_list("0-7"), help="e.g. 0-7 or 100-107")
    parser.add_argument(
        "--every", type=int, default=None, help="episodes between evaluations (default: the preset's)"
    )
    parser.add_argument("--target", type=float, default=2685.0, help="the evaluation return to reach")
    parser.add_argument("--eval-repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/time_to_hover"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    return parser.parse_args(argv)


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(
        f"experiment={args.preset} {' '.join(args.overrides)}: seeds {args.seeds}, target {args.target:.0f}"
    )
    print(
        "| seed | to target, s | training, s | command, s | evaluations | drone-eval return | first zone step (latest episode) | crashes |"
    )
    print("|---|---|---|---|---|---|---|---|")
    results = []
    for seed in args.seeds:
        results.append(
            measure(args.preset, seed, args.out, args.every, args.target, args.eval_repeats, args.overrides)
        )
        print(_row(results[-1]), flush=True)
    reached = [r for r in results if r["return"] >= args.target]
    times = [r["to_target_s"] for r in results]
    print(
        f"drone-eval at >= {args.target:.0f}: {len(reached)} of {len(results)}; return median "
        f"{statistics.median(r['return'] for r in results):.1f}, worst {min(r['return'] for r in results):.1f}; "
        f"to target median {statistics.median(times):.1f} s, worst {max(times):.1f} s; training median "
        f"{statistics.median(r['training_s'] for r in results):.1f} s; command median "
        f"{statistics.median(r['command_s'] for r in results):.1f} s"
    )


if __name__ == "__main__":
    main()
