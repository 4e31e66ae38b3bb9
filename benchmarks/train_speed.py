"""Training throughput: the TorchRL single-agent loop against the fused engine with 1 ... 128 agents.

    python benchmarks/train_speed.py                      # 1, 4, 32, 128 agents, eager
    python benchmarks/train_speed.py --agents 1 32 --compile --updates 20

Every configuration runs the same REINFORCE update (paper settings, one episode per update) on
policies that hover from the air reset: the mean head outputs 0.5 (hover thrust) and the std head a
small std, so episodes last long (150-250 steps; the table prints the mean), as in the second half
of a paper run, where the time goes.
Rates count agent-steps (every agent's own env steps) and agent-episodes per second of wall clock,
medians over ``--repeats``; ratios are to the TorchRL single-agent loop timed in the same run.
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
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl.config import config_dir, env_kwargs
from drone_torchrl.envs.factory import make_env
from drone_torchrl.fused import FusedTrainer
from drone_torchrl.modules.policy import ThreeNetPolicy
from drone_torchrl.objectives.reinforce import valid_steps
from drone_torchrl.train import build_actor, build_loss

HOVER_THRUST = 0.5  # per motor, as a fraction of the weight
HOVER_STD = 0.002  # small enough that a hovering drone survives 300 steps from the air reset


def hover_policy(net: ThreeNetPolicy) -> None:
    """Make a fresh policy hover: constant mean thrust 0.5, constant small std."""
    with torch.no_grad():
        net.mean.weight.zero_()
        net.mean.bias.fill_(HOVER_THRUST)
        net.std.weight.zero_()
        net.std.bias.fill_(math.log(math.expm1(HOVER_STD - net.min_std)))


def config(compile_step: bool, threads: int):
    overrides = [
        "env.reset_mode=air",
        "eval.every_episodes=0",
        "eval.episodes=1",
        "eval.video=false",
        "checkpoint.every_episodes=1000000",
        "progress=false",
        f"compile={str(compile_step).lower()}",
        f"threads={threads}",
    ]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=overrides)


def time_torchrl(cfg, updates: int) -> tuple[float, int]:
    """The training loop of ``drone_torchrl.train`` (engine=torchrl), one agent."""
    env = make_env(num_envs=cfg.algo.episodes_per_update, **env_kwargs(cfg))
    env.set_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    actor = build_actor(cfg)
    hover_policy(actor.module[0].module)
    loss_module = build_loss(cfg, actor)
    optimizer = torch.optim.Adam(actor.parameters(), lr=cfg.algo.lr)
    steps = 0
    start = time.perf_counter()
    for _ in range(updates):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = env.rollout(cfg.env.max_steps, actor, break_when_all_done=True)
        loss = loss_module(rollout)["loss_reinforce"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        steps += int(valid_steps(rollout.get(("next", "done"))).sum())
    return time.perf_counter() - start, steps


def time_fused(cfg, n_agents: int, updates: int, warmup: int) -> tuple[float, int]:
    """``FusedTrainer.update`` with ``n_agents`` agents (seeds 0..n-1), logging and CSV included."""
    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for seed in range(n_agents):
            job = copy.deepcopy(cfg)
            job.seed = seed
            job.algo.episodes = warmup + updates
            jobs.append((job, Path(tmp) / f"agent{seed}"))
        trainer = FusedTrainer(jobs, [None] * n_agents)
        for agent in trainer.agents:
            hover_policy(agent.policy)
        for _ in range(warmup):  # compilation, if any, happens here
            trainer.update(trainer.agents)
        steps = 0
        start = time.perf_counter()
        for _ in range(updates - 1):
            steps += trainer.update(trainer.agents)
        elapsed = time.perf_counter() - start
        steps += trainer.update(trainer.agents)  # the last update closes the runs (final eval): untimed
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
    parser.add_argument("--compile", action="store_true", help="also time the fused engine with compile=true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    eager = config(False, args.threads)
    base = [time_torchrl(eager, args.updates) for _ in range(args.repeats)]
    base_rate = statistics.median(steps / t for t, steps in base)
    base_eps = statistics.median(args.updates / t for t, _ in base)
    rows.append(("torchrl loop", 1, base_rate, base_eps))
    variants = [("fused", eager)] + ([("fused+compile", config(True, args.threads))] if args.compile else [])
    for name, cfg in variants:
        warmup = 2 if cfg.compile else 1
        for n in args.agents:
            runs = [time_fused(cfg, n, args.updates + 1, warmup) for _ in range(args.repeats)]
            rate = statistics.median(steps / t for t, steps in runs)
            eps = statistics.median(n * args.updates / t for t, _ in runs)
            rows.append((name, n, rate, eps))

    print(
        f"\nmedian of {args.repeats} repeats, {args.updates} updates each, torch threads {args.threads}, "
        "hovering policies\n"
    )
    print("| engine | agents | agent-steps/s | agent-episodes/s | steps/episode | x torchrl loop |")
    print("|---|---|---|---|---|---|")
    for name, n, rate, eps in rows:
        print(f"| {name} | {n} | {rate:,.0f} | {eps:,.2f} | {rate / eps:.0f} | {rate / base_rate:.1f}x |")


if __name__ == "__main__":
    main()
