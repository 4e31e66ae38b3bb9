"""The fast engine's kernels under disturbances against the nominal drone, and against an older commit.

    python benchmarks/kernel_disturbances.py                  # this checkout, and d88f933's kernels
    python benchmarks/kernel_disturbances.py --against main --repeats 30 --rounds 3

Prints the median time of one ``KernelReinforce`` update (``4 x 1`` and ``32 x 1`` agents x
episodes, 300 steps each) for the nominal drone, ``disturbance=strong`` and each disturbance key
alone, with the ratio to nominal; the median time of one ``KernelSegments`` call (64 drones x 64
steps) nominal and strong; the nominal update of the ``--against`` commit's kernels, measured in the
same run (the rounds alternate between the two checkouts, so a slow spell of a shared machine slows
both alike); and the cold build time of both sources with ``build.py``'s flags.

One thread (``torch.set_num_threads(1)``). The arena's bounds are moved to infinity, so every
episode flies all 300 steps whatever its disturbances: the times compare the work per step, not
how soon a random policy crashes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIZES = ((4, 1), (32, 1))  # agents x episodes per update
STEPS = 300
SEGMENT_DRONES, SEGMENT_STEPS = 64, 64
STRONG = {
    "wind": 0.3,
    "gust": 0.15,
    "mass": 0.3,
    "motor_gain": 0.15,
    "motor_lag": 0.05,
    "noise_position": 0.03,
    "noise_angle": 0.03,
    "action_delay": 2,
}  # fmt: skip  (conf/disturbance/strong.yaml)
ALONE = {
    "wind": {"wind": 0.3}, "gust": {"gust": 0.15}, "mass": {"mass": 0.3}, "motor_gain": {"motor_gain": 0.15},
    "motor_lag": {"motor_lag": 0.05}, "noise_position": {"noise_position": 0.03},
    "noise_angle": {"noise_angle": 0.03}, "action_delay": {"action_delay": 2},
    "observed_actions": {"observed_actions": 2},
}  # fmt: skip


def _unbounded(env, ops):
    """The kernels' drone constants with the domain's bounds at infinity: no termination."""
    env = env.clone()
    for name in ("x_limit", "z_max", "alpha_limit"):
        env[ops.ENV_CONSTANTS.index(name)] = float("inf")
    env[ops.ENV_CONSTANTS.index("floor")] = float("-inf")
    return env


def _times(fn, repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` calls of ``fn``, after three warm-up calls."""
    timer = timeit.Timer(fn)
    timer.repeat(3, 1)
    return timer.repeat(repeats, 1)


def _update(agents: int, episodes: int, disturbance: dict | None):
    """One ``KernelReinforce`` update of fresh agents (each call a new update counter)."""
    import torch

    from drone_torchrl.envs import dynamics
    from drone_torchrl.kernels import modules, ops
    from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy

    observed = (disturbance or {}).get("observed_actions", 0)
    torch.manual_seed(0)
    nets = [ThreeNetPolicy([32, 32], "tanh", obs_dim=6 + 2 * observed) for _ in range(agents)]
    extra = {} if disturbance is None else {"disturbance": disturbance}  # the old API has no such argument
    rollout = modules.KernelRollout(
        StackedThreeNet(nets, "tanh"), dynamics.DroneParams(max_thrust=1.0), None, STEPS, **extra
    )
    rollout.env = _unbounded(rollout.env, ops)
    flags = {
        "baseline_mean": True,
        "normalize_returns": True,
        "discount_weight": False,
        "mean_log_prob": False,
    }
    update = modules.KernelReinforce(rollout, episodes, flags)
    seed, gamma, active = (
        torch.arange(agents),
        torch.full((agents,), 0.99),
        torch.ones(agents, dtype=torch.bool),
    )
    counter = iter(range(10**9))
    return lambda: update(seed, torch.full((agents,), next(counter)), gamma, active)


def _segments(disturbance: dict | None):
    """One ``KernelSegments`` call of ``SEGMENT_DRONES`` drones, ``SEGMENT_STEPS`` steps."""
    import torch

    from drone_torchrl.envs import dynamics
    from drone_torchrl.kernels import modules, ops
    from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy

    torch.manual_seed(0)
    stacked = StackedThreeNet([ThreeNetPolicy([32, 32], "tanh")], "tanh")
    params = dynamics.DroneParams(max_thrust=1.0)
    rollout = modules.KernelRollout(stacked, params, None, STEPS, disturbance=disturbance)
    segments = modules.KernelSegments(rollout, SEGMENT_DRONES)
    segments.rollout.env = _unbounded(segments.rollout.env, ops)
    generator = torch.Generator().manual_seed(0)
    shape = (SEGMENT_DRONES, SEGMENT_STEPS)
    noise = torch.randn(*shape, 2, generator=generator)
    fresh = dynamics.initial_state(shape, "floor", generator)
    keys = torch.randint(-(2**62), 2**62, shape, generator=generator)
    return lambda: segments(noise, fresh, keys)


def worker(repeats: int, nominal_only: bool) -> dict[str, list]:
    """Times of this interpreter's ``drone_torchrl`` (whichever checkout ``sys.path`` finds)."""
    import torch

    import drone_torchrl

    torch.set_num_threads(1)
    out: dict[str, list] = {"_file": [str(Path(drone_torchrl.__file__).parent)]}
    conditions = {"nominal": None} if nominal_only else {"nominal": None, "strong": STRONG, **ALONE}
    for agents, episodes in SIZES:
        for name, disturbance in conditions.items():
            out[f"update {agents}x{episodes} {name}"] = _times(
                _update(agents, episodes, disturbance), repeats
            )
    if not nominal_only:
        for name, disturbance in {"nominal": None, "strong": STRONG}.items():
            out[f"segments {SEGMENT_DRONES}x{SEGMENT_STEPS} {name}"] = _times(_segments(disturbance), repeats)
    return out


def _export(ref: str, into: Path) -> Path:
    """``ref``'s package, extracted from git into ``into`` (importable from there)."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", ref, "drone_torchrl"], capture_output=True, check=True
    )
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def _run_worker(tree: Path | None, repeats: int, nominal_only: bool) -> dict[str, list[float]]:
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree)  # ahead of the editable install's finder
    cmd = [sys.executable, __file__, "--worker", "--repeats", str(repeats)] + (
        ["--nominal-only"] if nominal_only else []
    )
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def build_seconds(source: Path, repeats: int = 3) -> float:
    """Median seconds of a cold float32 build of ``source`` with build.py's flags."""
    from drone_torchrl.kernels import build

    compiler = build._compiler()
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            cmd = [
                compiler,
                *build.BASE_FLAGS,
                "-DDK_DOUBLE=0",
                *build.ARCH_FLAGS,
                str(source),
                "-o",
                f"{tmp}/k.so",
            ]
            start = time.perf_counter()
            subprocess.run(cmd, check=True)
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--against", default="d88f933", help="the commit whose nominal kernels to time too")
    parser.add_argument(
        "--repeats", type=int, default=20, help="timed calls per round (after 3 warm-up calls)"
    )
    parser.add_argument(
        "--rounds", type=int, default=2, help="rounds, alternating this checkout and --against"
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--nominal-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.repeats, args.nominal_only)))
        return
    times: dict[str, dict[str, list[float]]] = {"this": {}, "against": {}}
    with tempfile.TemporaryDirectory() as tmp:
        old = _export(args.against, Path(tmp))
        for _ in range(args.rounds):
            for who, tree, nominal_only in (("this", None, False), ("against", old, True)):
                for key, values in _run_worker(tree, args.repeats, nominal_only).items():
                    times[who].setdefault(key, []).extend(values)
        old_build = build_seconds(old / "drone_torchrl/kernels/drone_kernels.cpp")
    new_build = build_seconds(ROOT / "drone_torchrl/kernels/drone_kernels.cpp")
    median_ms = {
        who: {k: 1e3 * statistics.median(v) for k, v in t.items() if not k.startswith("_")}
        for who, t in times.items()
    }
    print(
        f"medians of {args.rounds * args.repeats} calls, one thread; this checkout: {times['this']['_file'][0]}"
    )
    for key, ms in median_ms["this"].items():
        base = median_ms["this"][key.rsplit(" ", 1)[0] + " nominal"]
        print(f"  {key:<40} {ms:8.3f} ms  {ms / base:5.2f}x nominal")
    print(f"nominal update, {args.against}'s kernels ({times['against']['_file'][0]}):")
    for key, ms in median_ms["against"].items():
        print(f"  {key:<40} {ms:8.3f} ms  (this checkout {median_ms['this'][key] / ms:5.2f}x)")
    print(f"cold float32 build: {args.against} {old_build:.1f} s, this checkout {new_build:.1f} s")


if __name__ == "__main__":
    main()
