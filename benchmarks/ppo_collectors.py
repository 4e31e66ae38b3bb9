"""PPO's batches: TorchRL's Collector over DroneEnv (backend=reference) against the fast engine's.

    python benchmarks/ppo_collectors.py                       # hover_optimal's 64 drones x 64 steps
    python benchmarks/ppo_collectors.py --checkpoint outputs/<date>/<time>   # a trained policy
    python benchmarks/ppo_collectors.py model.hidden_sizes=[32,32]          # Hydra overrides

Times one batch of each collector (``next(...)`` on the learner's own iterator, so the actor's
log-probabilities are included; the learner's private ``_batches`` and ``learn`` are the two
halves of its update) and one learning step on it (GAE and the minibatch epochs of
``OnPolicy.learn``), medians over ``--repeats`` batches after ``--warmup`` (learning: over
``--learn-repeats``). The policy is the run's fresh one (short episodes from the floor) or a
checkpoint's (full-length ones). Prints milliseconds per batch and the fast engine's speed-up over
TorchRL's collector, timed in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from drone_torchrl import algorithms
from drone_torchrl.algorithms.ppo import OnPolicy
from drone_torchrl.config import config_dir
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.training.jobs import prepare


def _learner(backend: str, overrides: list[str], run_dir: Path) -> OnPolicy:
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*overrides, f"backend={backend}"])
    job = prepare(cfg, run_dir)
    return algorithms.get(cfg.algo.name).learner([job])


def _median_ms(fn: Callable[[], object], warmup: int, repeats: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiment", default="hover_optimal")
    parser.add_argument("--checkpoint", default=None, help="a run folder or .pt whose actor flies")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--learn-repeats", type=int, default=5, help="learning steps timed (each ~0.1 s)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the run's config")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    overrides = [f"experiment={args.experiment}", "eval.video=false", "progress=false", *args.overrides]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for collector in ("reference", "fast"):
            learner = _learner(collector, overrides, Path(tmp) / collector)
            if args.checkpoint is not None:
                path = Path(args.checkpoint)
                state = load_checkpoint(path / "checkpoints" / "last.pt" if path.is_dir() else path)
                learner.actor_module.load_state_dict(state["actor"])
                learner.critic.load_state_dict(state["critic"])
            batches = learner._batches
            collect = _median_ms(lambda b=batches: next(b), args.warmup, args.repeats)
            batch = next(batches)
            learn = _median_ms(lambda lr=learner, b=batch: lr.learn(b), 1, args.learn_repeats)
            done = batch.get(("next", "done")).sum().item()
            rows[collector] = (collect, learn, done)
            learner.close()
    frames = batch.numel()
    print(
        f"{args.experiment}: {frames} frames a batch, policy: {args.checkpoint or 'fresh'}, "
        f"{args.threads} thread(s), medians of {args.repeats}"
    )
    print(f"{'collector':<10} {'collect ms':>11} {'learn ms':>9} {'episodes ended':>15}")
    for name, (collect, learn, done) in rows.items():
        print(f"{name:<10} {collect:>11.1f} {learn:>9.1f} {done:>15.0f}")
    print(
        f"fast collection: {rows['reference'][0] / rows['fast'][0]:.1f}x TorchRL's Collector; "
        f"a batch with learning: {sum(rows['reference'][:2]) / sum(rows['fast'][:2]):.2f}x"
    )


if __name__ == "__main__":
    main()
