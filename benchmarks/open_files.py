"""Files a population holds open while it trains, per logger backend.

    python benchmarks/open_files.py                         # 1024 agents, tensorboard, csv, mlflow
    python benchmarks/open_files.py --agents 64 --backends csv

Runs ``drone-train -m seed=range(N) hydra/launcher=fused`` (short episodes, a flush after every
update: ``logger.flush_every_s=0``) once per backend, and samples the training process's open file
descriptors (``/proc/<pid>/fd``) every few milliseconds: the peak count in all, the peak count of
those inside the sweep folder, and of those the run-folder locks (one ``.lock`` per job and one for
the sweep, held while it runs: drone_torchrl.io.run_lock); the rest are the runs' logs, CSVs and
checkpoints while they are written. Linux only.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from drone_torchrl.io.run_lock import LOCK_NAME

BACKENDS = ("tensorboard", "csv", "mlflow")
POLL_S = 0.005


def _open_files(pid: int, root: str) -> tuple[int, int, int]:
    """(open descriptors, those pointing inside ``root``, of them lock files) of process ``pid``."""
    folder = f"/proc/{pid}/fd"
    total = inside = locks = 0
    try:
        names = os.listdir(folder)
    except OSError:
        return 0, 0, 0
    for name in names:
        try:
            target = os.readlink(f"{folder}/{name}")
        except OSError:
            continue
        total += 1
        inside += target.startswith(root)
        locks += target.startswith(root) and target.endswith(f"/{LOCK_NAME}")
    return total, inside, locks


def measure(backend: str, agents: int, episodes: int, out: Path) -> tuple[int, int, int, int, float]:
    sweep = out / backend
    command = [
        str(Path(sys.executable).parent / "drone-train"),
        "-m",
        f"seed=range(0,{agents})",
        "hydra/launcher=fused",
        f"logger={backend}",
        f"algo.episodes={episodes}",
        "env.max_steps=50",
        "logger.flush_every_s=0",
        "checkpoint.every_episodes=5",
        "eval.every_episodes=0",
        "eval.video=false",
        "eval.episodes=1",
        "progress=false",
        f"hydra.sweep.dir={sweep}",
    ]
    start = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak_total = peak_inside = peak_locks = peak_logs = 0
    while proc.poll() is None:
        total, inside, locks = _open_files(proc.pid, str(sweep.resolve()))
        peak_total, peak_inside = max(peak_total, total), max(peak_inside, inside)
        peak_locks, peak_logs = max(peak_locks, locks), max(peak_logs, inside - locks)
        time.sleep(POLL_S)
    if proc.returncode:
        raise SystemExit(f"{backend}: drone-train failed ({proc.returncode}): {proc.stderr.read()[-2000:]}")
    return peak_total, peak_inside, peak_locks, peak_logs, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=1024)
    parser.add_argument("--episodes", type=int, default=20, help="per agent")
    parser.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS))
    args = parser.parse_args()
    print(f"{args.agents} agents x {args.episodes} episodes of at most 50 steps, a flush after every update")
    print(
        "| backend | peak open descriptors | inside the sweep folder | of them locks | of them logs | wall-clock |"
    )
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for backend in args.backends:
            total, inside, locks, logs, wall = measure(backend, args.agents, args.episodes, Path(tmp))
            print(f"| {backend} | {total} | {inside} | {locks} | {logs} | {wall:.0f} s |", flush=True)


if __name__ == "__main__":
    main()
