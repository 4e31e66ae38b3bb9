"""Time the paper's whole study end to end: both grids x 4 seeds x 6000 episodes, then the report.

    python benchmarks/full_study.py                       # the README's commands, timed
    python benchmarks/full_study.py --out /tmp/study algo.episodes=600   # a shorter rehearsal

It runs exactly what the README's "Reproduce the paper" section tells a user to type: the two
sweeps side by side (one process each, one per core; each trains its 16 jobs as one fused batch),
then ``drone-report`` on both folders. Extra arguments are Hydra overrides passed to both sweeps.
Prints each phase's wall-clock; the sweeps' logs are written next to their folders.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

SWEEPS = ("lr", "gamma")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("multirun"), help="parent folder of the two sweeps")
    parser.add_argument("--fresh", action="store_true", help="delete earlier results in --out first")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both sweeps, e.g. compile=true")
    args = parser.parse_args()
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "SDL_VIDEODRIVER": os.environ.get("SDL_VIDEODRIVER", "dummy")}
    args.out.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    procs = {}
    for sweep in SWEEPS:
        folder = args.out / sweep
        if args.fresh and folder.exists():
            shutil.rmtree(folder)
        cmd = [
            str(bin_dir / "drone-train"),
            "-m",
            f"+sweep={sweep}",
            f"hydra.sweep.dir={folder}",
            *args.overrides,
        ]
        log = (args.out / f"{sweep}.log").open("w")
        print("$ drone-train", " ".join(cmd[1:]), f"> {log.name} &", flush=True)
        procs[sweep] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log)
    for sweep, (proc, log) in procs.items():
        code = proc.wait()
        log.close()
        print(f"sweep {sweep}: exit {code}, {time.perf_counter() - start:.0f} s since start", flush=True)
        if code:
            sys.exit(f"sweep {sweep} failed; see {log.name}")
    trained = time.perf_counter()

    cmd = [str(bin_dir / "drone-report"), *(str(args.out / s) for s in SWEEPS)]
    print("$", "drone-report", *cmd[1:], flush=True)
    subprocess.run(cmd, check=True, env=env)
    done = time.perf_counter()
    print(
        f"\ntraining (both sweeps side by side): {trained - start:.0f} s = {(trained - start) / 60:.1f} min"
    )
    print(f"report: {done - trained:.0f} s")
    print(f"whole study: {done - start:.0f} s = {(done - start) / 60:.1f} min")


if __name__ == "__main__":
    main()
