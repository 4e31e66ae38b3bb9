"""Time per update of the population engine for 1 ... 1024 agents, every episode the full 300 steps.

    python benchmarks/population.py                          # 1, 16, 32, 256, 1024 agents, CPU
    python benchmarks/population.py --agents 32 1024 --device cuda

One update = every agent's episode (300 steps: termination is switched off here, in the C++
kernels' bounds, so that the work per update does not depend on how well the agents fly),
REINFORCE loss and gradient, per-agent clipping and Adam, and the run records (CSV rows and
TensorBoard scalars buffered every update, written at the end), on the fast engine (backend=fast).
``--per-call`` updates run per call of the update (the training loop runs up to
``trainer.MAX_UPDATES_PER_CALL``).
Prints the median time per update over ``--repeats`` runs, the time per agent, the share of the
update spent in recording, and the ratio to the smallest population timed in the same run. The
populations are timed in turns (one run of each size per round), so that a slow spell of a shared
machine does not fall on one size only.
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
import train_speed  # noqa: E402  (the script beside this one: python benchmarks/population.py)

from drone_torchrl.training import run as run_module
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.trainer import Trainer


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


def time_population(cfg, agents: int, updates: int, warmup: int, per_call: int) -> tuple[float, float]:
    """Seconds per update (median over ``updates`` calls of ``per_call`` updates) and the recording share."""
    record_time = 0.0
    original = run_module.RunRecord.record

    def timed_record(self, *args, **kwargs):
        nonlocal record_time
        start = time.perf_counter()
        original(self, *args, **kwargs)
        record_time += time.perf_counter() - start

    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for seed in range(agents):
            job = copy.deepcopy(cfg)
            job.seed = seed
            job.algo.episodes = (warmup + updates) * per_call + 1
            jobs.append(prepare(job, Path(tmp) / f"agent{seed}"))
        trainer = Trainer(jobs)
        everyone = list(range(agents))
        for _ in range(warmup):
            trainer.step(everyone, per_call)
        times = []
        run_module.RunRecord.record = timed_record
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
            run_module.RunRecord.record = original
        trainer.close()
    return statistics.median(times), record_time / (sum(times) * per_call)


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
    runs: dict[int, list[tuple[float, float]]] = {n: [] for n in args.agents}
    for _ in range(args.repeats):
        for n in args.agents:
            runs[n].append(time_population(cfg, n, args.updates, 1, args.per_call))
    rows = [
        (n, statistics.median(t for t, _ in runs[n]), statistics.median(s for _, s in runs[n]))
        for n in args.agents
    ]
    base_n, base_t, _ = rows[0]
    print(
        f"\n{device_name}, torch threads {args.threads}, backend=fast, 300-step episodes, "
        f"one episode per agent per update; median of {args.repeats} runs x {args.updates} calls "
        f"of {args.per_call} updates\n"
    )
    print(f"| agents | s / update | ms / agent / update | recording share | x time of {base_n} agent(s) |")
    print("|---|---|---|---|---|")
    for n, t, share in rows:
        print(f"| {n} | {t:.3f} | {1000 * t / n:.2f} | {100 * share:.0f}% | {t / base_t:.1f}x |")


if __name__ == "__main__":
    main()
