"""The fast engine on a GPU against the JAX peer on the same card, row by row (run by gpu_check.sh).

    bash benchmarks/gpu_check.sh                         # on the GPU machine (see gpu_check.sh)
    python benchmarks/gpu_check.py --device cpu --quick  # the same rows on the CPU, in seconds

Each row is printed as soon as it is measured (a killed run still leaves data):

1. the engine's build: compiling (or loading) the CUDA engine (the CPU engine with ``--device cpu``);
2. equality: ``tests/test_kernel_engines.py``'s GPU test, the CUDA engine against the CPU engine
   under each disturbance (skipped with ``--device cpu``);
3. per-update time at 1,024 / 8,192 / 65,536 agents (``--agents``): the population run's update of
   benchmarks/population.py (every episode the full 300 steps: the domain's bounds at infinity; the
   REINFORCE loss, gradient, per-agent clipping, Adam and the run's record), median of ``--updates``
   calls of ``--per-call`` updates after one untimed call; and the JAX peer's update
   (benchmarks/peers/jax_reinforce.py: the rollout as one ``lax.scan``, termination switched off,
   the loss ``vmap``-ed, Adam) over ``--per-call * --updates`` updates in one jitted call, its
   compile time apart;
4. the default ``drone-train`` with ``device=<device>`` against ``device=cpu`` (``algo.episodes``
   of ``--episodes``, no evaluation or video), wall-clock of the whole command.

``--quick``: 32 and 256 agents, 1 x 2 updates, 100 episodes of drone-train: under a minute on a CPU.
"""

# ruff: noqa: E402  (sys.path first: the scripts beside this one)
from __future__ import annotations

import argparse
import contextlib
import datetime
import math
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE / "peers")]

import torch

AGENTS = [1024, 8192, 65536]
QUICK_AGENTS = [32, 256]


def row(*cells: object) -> None:
    print("| " + " | ".join(str(c) for c in cells) + " |", flush=True)


def engine_build(device: str) -> None:
    from drone_torchrl.kernels import build

    start = time.perf_counter()
    lib = build.cuda_library() if device.startswith("cuda") else build.library()
    took = time.perf_counter() - start
    row(
        "engine build (compile or load)", device, f"{took:.1f} s", "ok" if lib else build.unavailable_reason()
    )


def equality(device: str) -> None:
    if not device.startswith("cuda"):
        row("equality: CUDA engine = CPU engine", device, "-", "skipped (no GPU)")
        return
    start = time.perf_counter()
    test = Path(HERE.parent, "tests", "test_kernel_engines.py")
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "gpu", str(test)],
        capture_output=True, text=True, cwd=HERE.parent,
    )  # fmt: skip
    last = (out.stdout.strip().splitlines() or [f"exit {out.returncode}"])[-1]
    row("equality: CUDA engine = CPU engine", device, f"{time.perf_counter() - start:.1f} s", last)
    if out.returncode != 0:
        print(out.stdout[-3000:], flush=True)


def project_update(device: str, agents: int, updates: int, per_call: int) -> float | None:
    import population

    from drone_torchrl.kernels import ops

    if ops.env_constants is not population.unbounded_constants:  # every episode the full 300 steps
        population._env_constants = ops.env_constants
        ops.env_constants = population.unbounded_constants
    try:
        result = population.time_population(population.config(device, 1), agents, updates, 1, per_call)
    except Exception as err:  # a row that fails is a row: the next ones still run
        row(f"project, {agents} agents", device, "failed", f"{type(err).__name__}: {err}"[:300])
        return None
    row(
        f"project, {agents} agents",
        device,
        f"{result['update']:.4f} s/update",
        f"set-up {result['setup']:.1f} s, first update {result['first']:.1f} s, recording {100 * result['recording']:.0f}%",
    )
    return result["update"]


def jax_update(device: str, agents: int, updates: int) -> float | None:
    try:
        import jax
        import jax.numpy as jnp
        import jax_reinforce as peer
    except ImportError as err:
        row(f"JAX peer, {agents} agents", device, "-", f"not installed ({err})")
        return None
    platform_name = "gpu" if device.startswith("cuda") else "cpu"
    with contextlib.suppress(RuntimeError):  # set by an earlier row already
        jax.config.update("jax_platforms", "cuda" if platform_name == "gpu" else "cpu")
    peer.termination_cause = lambda state: jnp.zeros(state.shape[:-1], jnp.int32)  # full-length episodes
    try:
        seeds = list(range(agents))
        result = peer.train([1e-4] * agents, [0.99] * agents, seeds, updates, scan=updates, rollout="scan")
    except Exception as err:
        row(f"JAX peer, {agents} agents", device, "failed", f"{type(err).__name__}: {err}"[:300])
        return None
    per_update = result["train_s"] / updates
    row(
        f"JAX peer, {agents} agents",
        device,
        f"{per_update:.4f} s/update",
        f"compile {result['compile_s']:.1f} s",
    )
    return per_update


def drone_train(device: str, episodes: int) -> float | None:
    overrides = [f"device={device}", f"algo.episodes={episodes}", "eval.every_episodes=0", "eval.video=false"]
    overrides += ["progress=false", f"hydra.run.dir={tempfile.mkdtemp(prefix='drone_gpu_check_')}"]
    start = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", "from drone_torchrl.apps.train import run; run()", *overrides],
        capture_output=True, text=True,
    )  # fmt: skip
    took = time.perf_counter() - start
    lines = (out.stdout + out.stderr).strip().splitlines() or [""]
    last = lines[-1] if out.returncode == 0 else next((x for x in reversed(lines) if "Error" in x), lines[-1])
    row(
        "drone-train " + " ".join(overrides[:2]),
        device,
        f"{took:.1f} s",
        f"exit {out.returncode}: {last[:200]}",
    )
    return took if out.returncode == 0 else None


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--agents", type=int, nargs="+")
    parser.add_argument("--updates", type=int, default=3, help="timed calls per population")
    parser.add_argument("--per-call", type=int, default=4, help="updates per call")
    parser.add_argument("--episodes", type=int, default=6000, help="drone-train's algo.episodes")
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():  # else a traceback at the first row
        built = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "built without CUDA"
        sys.exit(
            f"gpu_check: error: --device {args.device} needs a GPU: torch {torch.__version__} here is {built} "
            "and sees none (torch.cuda.is_available() is False); run it on the GPU machine, or pass --device cpu"
        )
    agents = args.agents or (QUICK_AGENTS if args.quick else AGENTS)
    updates, per_call, episodes = (1, 2, 100) if args.quick else (args.updates, args.per_call, args.episodes)
    gpu = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or "CPU"
    print(
        f"gpu_check {datetime.datetime.now().isoformat(timespec='seconds')} on {gpu}, torch {torch.__version__}\n"
    )
    row("row", "device", "figure", "notes")
    row("---", "---", "---", "---")
    engine_build(args.device)
    equality(args.device)
    ratios = []
    for n in agents:
        ours = project_update(args.device, n, updates, per_call)
        theirs = jax_update(args.device, n, updates * per_call)
        if ours and theirs:
            ratios.append((n, ours / theirs))
            row(f"ratio project / JAX, {n} agents", args.device, f"{ours / theirs:.2f}x", "target <= 1.5x")
    on_device = drone_train(args.device, episodes)
    if not args.device.startswith("cpu"):
        on_cpu = drone_train("cpu", episodes)
        if on_device and on_cpu:
            row("drone-train device / cpu", args.device, f"{on_device / on_cpu:.2f}x", "target <= 1.0x")
    if ratios:
        worst = max(r for _, r in ratios)
        print(
            f"\nworst project / JAX ratio: {worst:.2f}x (geometric mean {math.prod(r for _, r in ratios) ** (1 / len(ratios)):.2f}x)"
        )


if __name__ == "__main__":
    main()
