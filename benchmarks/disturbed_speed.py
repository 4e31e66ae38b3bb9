"""A disturbed population against the nominal one: wall-clock of the whole command, compilation included.

    python benchmarks/disturbed_speed.py                          # 4 agents x 2000 episodes, 3 repeats
    python benchmarks/disturbed_speed.py --repeats 5 algo.episodes=6000

Runs ``drone-train -m seed=0,...,N-1 hydra/launcher=fused algo=reinforce_plus disturbance=<d>`` for
``d`` in ``none`` and ``strong`` (the conditions take turns, so a slow spell of a shared machine
falls on both), each with an empty kernel cache (``$DRONE_TORCHRL_CACHE`` a new folder: the C++
build is part of the time, as on a new machine). Prints each run's seconds, the medians and the
ratio strong / none.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONDITIONS = ("none", "strong")


def run(condition: str, agents: int, overrides: list[str], root: Path) -> float:
    cache = Path(tempfile.mkdtemp(dir=root))
    cmd = [
        str(Path(sys.executable).parent / "drone-train"),
        "-m",
        f"seed={','.join(str(s) for s in range(agents))}",
        "hydra/launcher=fused",
        "algo=reinforce_plus",
        f"disturbance={condition}",
        "algo.episodes=2000",
        "eval.every_episodes=0",
        "eval.video=false",
        "progress=false",
        f"hydra.sweep.dir={cache / 'sweep'}",
        *overrides,
    ]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "DRONE_TORCHRL_CACHE": str(cache / "kernels")}
    start = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, capture_output=True, text=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--agents", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both conditions")
    args = parser.parse_args()
    seconds: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeats):
            for condition in CONDITIONS:
                seconds[condition].append(run(condition, args.agents, args.overrides, Path(tmp)))
                print(f"{condition}: {seconds[condition][-1]:.1f} s", flush=True)
    median = {c: statistics.median(s) for c, s in seconds.items()}
    print(
        f"\n{args.agents} agents, algo=reinforce_plus, cold kernel cache each run, median of {args.repeats}:"
    )
    for condition in CONDITIONS:
        print(f"  disturbance={condition}: {median[condition]:.1f} s")
    print(f"  strong / none: {median['strong'] / median['none']:.2f}x")


if __name__ == "__main__":
    main()
