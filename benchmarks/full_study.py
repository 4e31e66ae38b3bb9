"""Time the paper's whole study end to end: both grids x 4 seeds x 6000 episodes, then the report.

    python benchmarks/full_study.py                       # docs/paper.md's commands, timed
    python benchmarks/full_study.py --out /tmp/study algo.episodes=600   # a shorter rehearsal
    python benchmarks/full_study.py --fresh --cold --peer eval.every_episodes=0 eval.video=false
    python benchmarks/full_study.py --bin /path/to/other/venv/bin --cold ...   # another installation

It runs exactly what the "Reproduce the paper" page (docs/paper.md) tells a user to type: the two
sweeps side by side (one process each, one per core; each trains its 16 jobs as one fused batch),
then ``drone-report`` on both folders. Extra arguments are Hydra overrides passed to both sweeps.
Prints each phase's wall-clock; the sweeps' logs are written next to their folders.

Compilation caches: the C++ kernels' build (``$DRONE_TORCHRL_CACHE``) and, for code that uses
``torch.compile``, Inductor's (``$TORCHINDUCTOR_CACHE_DIR``) are kept under ``--cache`` (default
``<out>/cache``). ``--cold`` empties it first, so the timing includes every compilation, as on a
new machine; without it, a second run finds them built (warm). The user's own caches are not used.

``--peer`` then times the independent JAX implementation of the same study
(``benchmarks/peers/jax_reinforce.py --study``, two processes of 16 agents, cold compilation; needs
the ``peers`` extra) in the same run and prints the ratio of the two training wall-clocks.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

SWEEPS = ("lr", "gamma")
PEER = Path(__file__).resolve().parent / "peers" / "jax_reinforce.py"


def _episodes(overrides: list[str]) -> int:
    """The episodes per job the overrides ask for (the study's 6000 otherwise)."""
    for item in overrides:
        if item.startswith("algo.episodes="):
            return int(item.split("=", 1)[1])
    return 6000


def time_peer(episodes: int, env: dict[str, str]) -> float:
    """The JAX peer's study (two processes side by side): its printed total wall-clock, in seconds."""
    cmd = [sys.executable, str(PEER), "--study", "--episodes", str(episodes)]
    print("$", " ".join(cmd[1:]), flush=True)
    start = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    elapsed = time.perf_counter() - start
    sys.stdout.write(out.stdout[-3000:])
    if out.returncode:
        sys.exit(f"the JAX peer failed (is the peers extra installed?):\n{out.stderr[-2000:]}")
    match = re.search(r"study \(both grids side by side\): ([\d.]+) s", out.stdout)
    return float(match.group(1)) if match else elapsed


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("multirun"), help="parent folder of the two sweeps")
    parser.add_argument("--fresh", action="store_true", help="delete earlier results in --out first")
    parser.add_argument("--bin", type=Path, default=Path(sys.executable).parent, help="where drone-train is")
    parser.add_argument("--cache", type=Path, help="the compilation caches (default: <out>/cache)")
    parser.add_argument("--cold", action="store_true", help="empty the compilation caches first")
    parser.add_argument("--peer", action="store_true", help="also time the JAX peer's study")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both sweeps, e.g. eval.video=false")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cache = (args.cache or args.out / "cache").resolve()
    if args.cold and cache.exists():
        shutil.rmtree(cache)
    cache.mkdir(parents=True, exist_ok=True)
    env = {
        **os.environ,
        "SDL_VIDEODRIVER": os.environ.get("SDL_VIDEODRIVER", "dummy"),
        "DRONE_TORCHRL_CACHE": str(cache / "kernels"),
        "TORCHINDUCTOR_CACHE_DIR": str(cache / "inductor"),
    }

    start = time.perf_counter()
    procs = {}
    for sweep in SWEEPS:
        folder = args.out / sweep
        if args.fresh and folder.exists():
            shutil.rmtree(folder)
        cmd = [
            str(args.bin / "drone-train"),
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

    cmd = [str(args.bin / "drone-report"), *(str(args.out / s) for s in SWEEPS)]
    print("$", "drone-report", *cmd[1:], flush=True)
    subprocess.run(cmd, check=True, env=env)
    done = time.perf_counter()
    training = trained - start
    print(
        f"\ntraining (both sweeps side by side, {'cold' if args.cold else 'warm'} caches): {training:.1f} s"
    )
    print(f"report: {done - trained:.0f} s")
    print(f"whole study: {done - start:.0f} s = {(done - start) / 60:.1f} min")
    if args.peer:
        peer = time_peer(_episodes(args.overrides), env)
        print(f"\nJAX peer's study (cold compilation): {peer:.1f} s")
        print(f"ratio, this project's training to the peer's: {training / peer:.2f}")


if __name__ == "__main__":
    main()
