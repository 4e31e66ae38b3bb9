"""Training throughput: the reference backend (TorchRL, one agent) against the fast one with 1 ... 128 agents.

    python benchmarks/train_speed.py                      # 1, 4, 32, 128 agents
    python benchmarks/train_speed.py --agents 1 32 --updates 20

Every configuration runs the same loop (``Trainer.step``: episodes, REINFORCE loss, Adam, run record
with CSV and TensorBoard; paper settings, one episode per update); only the backend differs. On
policies that hover from the air reset: the mean head outputs 0.5 (hover thrust) and the std head a
small std, so episodes last long (150-250 steps; the table prints the mean), as in the second half
of a paper run, where the time goes.
Rates count agent-steps (every agent's own env steps) and agent-episodes per second of wall clock,
medians over ``--repeats``; ratios are to the reference's single-agent loop timed in the same run.
"""

from __future__ import annotations

import argparse
import copy
import math
import statistics
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from drone_torchrl.config import config_dir
from drone_torchrl.modules.stacked import StackedThreeNet
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.trainer import Trainer

HOVER_THRUST = 0.5  # per motor, as a fraction of the weight
HOVER_STD = 0.002  # small enough that a hovering drone survives 300 steps from the air reset


def hover_policy(policy: StackedThreeNet) -> None:
    """Make every agent's fresh policy hover: constant mean thrust 0.5, constant small std."""
    params = policy.params
    with torch.no_grad():
        params.get(("mean", "weight")).zero_()
        params.get(("mean", "bias")).fill_(HOVER_THRUST)
        params.get(("std", "weight")).zero_()
        params.get(("std", "bias")).fill_(math.log(math.expm1(HOVER_STD - policy.min_std)))


def config(backend: str, threads: int):
    overrides = [
        "env.reset_mode=air",
        "eval.every_episodes=0",
        "eval.episodes=1",
        "eval.video=false",
        "checkpoint.every_episodes=1000000",
        "progress=false",
        f"backend={backend}",
        f"threads={threads}",
    ]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=overrides)


def time_updates(cfg, n_agents: int, updates: int, warmup: int) -> tuple[float, int]:
    """``Trainer.step`` of ``n_agents`` agents (seeds 0..n-1): seconds for ``updates - 1`` updates
    after ``warmup`` untimed ones, and the agent-steps they took."""
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for seed in range(n_agents):
            job = copy.deepcopy(cfg)
            job.seed = seed
            job.algo.episodes = warmup + updates
            jobs.append(prepare(job, Path(tmp) / f"agent{seed}"))
        trainer = Trainer(jobs)
        hover_policy(trainer.population.policy)
        agents = list(range(n_agents))
        for _ in range(warmup):  # compilation, if any, happens here
            trainer.step(agents, 1)
        steps = 0
        start = time.perf_counter()
        for _ in range(updates - 1):
            steps += trainer.step(agents, 1)
        elapsed = time.perf_counter() - start
        steps += trainer.step(agents, 1)  # the last update closes the runs (final eval): untimed
        trainer.close()
    return elapsed, steps


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, nargs="+", default=[1, 4, 32, 128])
    parser.add_argument("--updates", type=int, default=10, help="timed updates per configuration")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    reference = config("reference", args.threads)
    base = [time_updates(reference, 1, args.updates + 1, 1) for _ in range(args.repeats)]
    base_rate = statistics.median(steps / t for t, steps in base)
    base_eps = statistics.median(args.updates / t for t, _ in base)
    rows.append(("reference", 1, base_rate, base_eps))
    fast = config("fast", args.threads)
    for n in args.agents:
        runs = [time_updates(fast, n, args.updates + 1, 1) for _ in range(args.repeats)]
        rate = statistics.median(steps / t for t, steps in runs)
        eps = statistics.median(n * args.updates / t for t, _ in runs)
        rows.append(("fast", n, rate, eps))

    print(
        f"\nmedian of {args.repeats} repeats, {args.updates} updates each, torch threads {args.threads}, "
        "hovering policies\n"
    )
    print("| backend | agents | agent-steps/s | agent-episodes/s | steps/episode | x reference |")
    print("|---|---|---|---|---|---|")
    for name, n, rate, eps in rows:
        print(f"| {name} | {n} | {rate:,.0f} | {eps:,.2f} | {rate / eps:.0f} | {rate / base_rate:.1f}x |")


if __name__ == "__main__":
    main()
