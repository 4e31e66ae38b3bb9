"""Set-up, time per update and recording share of a population run (``hydra/launcher=population``)
for 1 ... 65,536 agents, every episode the full 300 steps.

    python benchmarks/population.py                          # 1, 16, 32, 256, 1024 agents, CPU
    python benchmarks/population.py --agents 1024 8192 65536 --updates 1 --per-call 1 --repeats 1
    python benchmarks/population.py --agents 1024 8192 65536 --updates 1 --per-call 1 --repeats 1 --command
    python benchmarks/population.py --agents 32 1024 --device cuda

One update = every agent's episode (300 steps: termination is switched off here, in the C++
kernels' bounds, so that the work per update does not depend on how well the agents fly),
REINFORCE loss and gradient, per-agent clipping and Adam, and the population run's record (its
Parquet rows and summaries; the checkpoint of every agent, timed once and amortised over
``checkpoint.every_episodes`` of conf/config.yaml), on the fast engine (backend=fast). Set-up: from the
configs to the first update (the agents' table, as the launcher makes it, the learner and the
folder; the imports, once per command, and the first update are printed apart); ``--command``
also times the real ``drone-train -m hydra/launcher=population 'seed=range(0,N)'`` from its start to
its log line that the population is set up (Hydra and the sweep's N jobs included); memory: what the
population added to this process per agent (a size after the first reuses memory the first
freed: time one size per command for that figure), and the estimate of
drone_torchrl.memory_estimate.
``--per-call`` updates run per call of the update (the training loop runs up to
``trainer.MAX_UPDATES_PER_CALL``).
Prints the median time per update over ``--repeats`` runs, the time per agent, the share of the
update spent in recording, and the ratio to the smallest population timed in the same run. The
populations are timed in turns (one run of each size per round), so that a slow spell of a shared
machine does not fall on one size only.
"""

# ruff: noqa: E402  (the imports come after START: they are timed)
from __future__ import annotations

import time

START = time.perf_counter()

import argparse
import math
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
import train_speed  # the script beside this one: python benchmarks/population.py
from omegaconf import OmegaConf

from drone_torchrl import memory_estimate
from drone_torchrl.config import config_dir, per_agent_keys
from drone_torchrl.memory_estimate import reinforce_parts
from drone_torchrl.training import population_record as record_module
from drone_torchrl.training.agents import AgentTable
from drone_torchrl.training.trainer import Trainer

IMPORTED = time.perf_counter()
# Episodes between two checkpoints of the population (its cost is amortised over them): the
# default of conf/config.yaml.
CHECKPOINT_EVERY = int(OmegaConf.load(Path(config_dir()) / "config.yaml").checkpoint.every_episodes)


def unbounded_constants(*args, **kwargs) -> torch.Tensor:
    """The kernels' drone constants with the domain's bounds at infinity: no termination."""
    from drone_torchrl.kernels import ops

    env = _env_constants(*args, **kwargs)
    for name in ("x_limit", "z_max", "alpha_limit"):
        env[ops.ENV_CONSTANTS.index(name)] = math.inf
    env[ops.ENV_CONSTANTS.index("floor")] = -math.inf
    return env


def config(device: str, threads: int):
    """train_speed's benchmark config on ``device`` (backend=fast), buffers flushed only at the end."""
    cfg = train_speed.config("fast", threads)
    cfg.device = device
    cfg.logger.flush_every_s = 1e9
    return cfg


def _rss() -> int:
    """This process's resident memory now, in bytes."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def time_population(cfg, agents: int, updates: int, warmup: int, per_call: int) -> dict[str, float]:
    """One population run (``hydra/launcher=population``'s layout) of ``agents`` agents: its set-up
    (configs, learner, folder: up to the end of the first update), the median seconds per update
    over ``updates`` calls of ``per_call`` updates, the recording share (the rows, the summaries, the
    flush to Parquet and the checkpoint amortised over ``checkpoint.every_episodes``), and the
    memory the population added per agent."""
    record_time = 0.0

    def timed(method):
        def wrapper(*args, **kwargs):
            nonlocal record_time
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                record_time += time.perf_counter() - start

        return wrapper

    originals = {
        (record_module.AgentBook, "record"): record_module.AgentBook.record,
        (record_module.PopulationRecord, "after_update"): record_module.PopulationRecord.after_update,
    }
    rss_before = _rss()
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        budget = (warmup + updates) * per_call + 1
        cfg.algo.episodes = budget
        cfg.checkpoint.every_episodes = CHECKPOINT_EVERY
        # The launcher's table of the sweep seed=0,...,N-1: one config, a column per per-agent key.
        values = {key: [OmegaConf.select(cfg, key)] * agents for key in per_agent_keys()}
        values["seed"] = list(range(agents))
        table = AgentTable(cfg, values)
        trainer = Trainer(table, Path(tmp), [f"seed={i}" for i in range(agents)])
        setup = time.perf_counter() - start
        everyone = list(range(agents))
        start = time.perf_counter()
        trainer.step(everyone, per_call)
        first = time.perf_counter() - start
        for _ in range(warmup - 1):
            trainer.step(everyone, per_call)
        times = []
        for (owner, name), method in originals.items():
            setattr(owner, name, timed(method))
        try:
            for _ in range(updates):
                if cfg.device.startswith("cuda"):
                    torch.cuda.synchronize()
                start = time.perf_counter()
                trainer.step(everyone, per_call)
                if cfg.device.startswith("cuda"):
                    torch.cuda.synchronize()
                times.append((time.perf_counter() - start) / per_call)
        finally:
            for (owner, name), method in originals.items():
                setattr(owner, name, method)
        rss = _rss() - rss_before
        start = time.perf_counter()
        trainer.records[0].flush()
        trainer.save(everyone)
        checkpoint = time.perf_counter() - start
        trainer.close()
    per_update = statistics.median(times)
    # A checkpoint every CHECKPOINT_EVERY episodes: its cost shared by the updates in between.
    amortised = checkpoint / (CHECKPOINT_EVERY / int(cfg.algo.episodes_per_update))
    recording = record_time / (sum(times) * per_call) + amortised / per_update
    estimated = memory_estimate.estimate(cfg, agents, reinforce_parts).total / agents
    return {
        "setup": setup,
        "first": first,
        "update": per_update,
        "recording": recording,
        "bytes_per_agent": rss / agents,
        "estimated_per_agent": estimated,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, nargs="+", default=[1, 16, 32, 256, 1024])
    parser.add_argument("--updates", type=int, default=5, help="timed calls per population")
    parser.add_argument("--per-call", type=int, default=4, help="updates per call of the update")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--command", action="store_true", help="also time the real command's set-up (see command_setup)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    # Every episode flies max_steps steps.
    global _env_constants
    from drone_torchrl.kernels import ops

    _env_constants = ops.env_constants
    ops.env_constants = unbounded_constants
    cfg = config(args.device, args.threads)
    device_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    # The populations take turns, one run each per round: a slow spell of a shared machine then
    # slows every size alike instead of one, and the ratios between sizes stay meaningful.
    runs: dict[int, list[dict[str, float]]] = {n: [] for n in args.agents}
    for _ in range(args.repeats):
        for n in args.agents:
            runs[n].append(time_population(cfg, n, args.updates, 1, args.per_call))
            print(f"{n} agents: {runs[n][-1]}", flush=True)
    rows = [(n, {k: statistics.median(r[k] for r in runs[n]) for k in runs[n][0]}) for n in args.agents]
    base_n, base = rows[0]
    print(
        f"\n{device_name}, torch threads {args.threads}, backend=fast, 300-step episodes, "
        f"one episode per agent per update; median of {args.repeats} runs x {args.updates} calls "
        f"of {args.per_call} updates\n"
    )
    print(f"imports: {IMPORTED - START:.1f} s (once per command)\n")
    print(
        "| agents | set-up s (configs, learner, folder) | first update s | s / update | ms / agent / update "
        f"| recording share | memory / agent (measured; estimated) | x time of {base_n} agent(s) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for n, r in rows:
        print(
            f"| {n} | {r['setup']:.1f} | {r['first']:.1f} | {r['update']:.3f} | {1000 * r['update'] / n:.2f} | "
            f"{100 * r['recording']:.1f}% | {r['bytes_per_agent'] / 1024:.0f}; {r['estimated_per_agent'] / 1024:.0f} KiB "
            f"| {r['update'] / base['update']:.1f}x |"
        )
    if args.command:
        print("\nThe command, from its start to its first update (warm cache; median of --repeats):\n")
        print("| agents | drone-train -m hydra/launcher=population 'seed=range(0,N)': s to 'agents set up' |")
        print("|---|---|")
        command_setup(min(args.agents))  # warms the caches
        for n in args.agents:
            times = [command_setup(n) for _ in range(args.repeats)]
            print(f"| {n} | {statistics.median(times):.1f} |", flush=True)


def command_setup(agents: int) -> float:
    """Seconds from starting ``drone-train -m hydra/launcher=population 'seed=range(0,N)'`` to its log
    line saying the population is set up (imports, Hydra, the sweep's N jobs, their table, the
    learner and the folder); the command is then killed (its folder is a temporary one)."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            str(Path(sys.executable).with_name("drone-train")),
            "-m",
            "hydra/launcher=population",
            f"seed=range(0,{agents})",
            "progress=false",
            "eval.every_episodes=0",
            "eval.video=false",
            f"hydra.sweep.dir={tmp}/sweep",
        ]
        start = time.perf_counter()
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                if "agents set up; training" in line:
                    return time.perf_counter() - start
            raise RuntimeError(f"{' '.join(command)} ended before its first update (exit {proc.wait()})")
        finally:
            proc.kill()
            proc.wait()


if __name__ == "__main__":
    main()
