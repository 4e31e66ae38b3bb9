"""The fast engine's kernels under disturbances against the nominal drone, and against an older commit.

    python benchmarks/kernel_disturbances.py                  # this checkout, and d88f933's kernels
    python benchmarks/kernel_disturbances.py --against main --repeats 10 --rounds 4

Prints the median (and least) time of one ``KernelReinforce`` update (``4 x 1`` and ``32 x 1`` agents x
episodes, 300 steps each) for the nominal drone, ``disturbance=strong`` and each disturbance key
alone, with the ratio to nominal; the median time of one ``KernelSegments`` call (64 drones x 64
steps) nominal and strong; the nominal update of the ``--against`` commit's kernels, measured in the
same run (the rounds alternate between the two checkouts, so a slow spell of a shared machine slows
both alike), and whether one nominal update's outputs are bit for bit the same in both; and the
cold build time of both sources with ``build.py``'s flags.

One thread (``torch.set_num_threads(1)``). The arena's bounds are moved to infinity, so every
episode flies all 300 steps whatever its disturbances: the times compare the work per step, not
how soon a random policy crashes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
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


def _times(calls: dict[str, object], repeats: int) -> dict[str, list[float]]:
    """Seconds of ``repeats`` calls of each of ``calls``, after three warm-up calls: the calls take
    turns, one each per pass, so a slow spell of a shared machine slows them all alike."""
    timers = {name: timeit.Timer(fn) for name, fn in calls.items()}
    for timer in timers.values():
        timer.repeat(3, 1)
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, timer in timers.items():
            times[name] += timer.repeat(1, 1)
    return times


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
    conditions = {"nominal": None} if nominal_only else {"nominal": None, "strong": STRONG, **ALONE}
    calls = {
        f"update {agents}x{episodes} {name}": _update(agents, episodes, disturbance)
        for agents, episodes in SIZES
        for name, disturbance in conditions.items()
    }
    if not nominal_only:
        for name, disturbance in {"nominal": None, "strong": STRONG}.items():
            calls[f"segments {SEGMENT_DRONES}x{SEGMENT_STEPS} {name}"] = _segments(disturbance)
    return {
        "_file": [str(Path(drone_torchrl.__file__).parent)],
        "_digest": [_digest()],
        **_times(calls, repeats),
    }


def _digest() -> str:
    """A hash of one nominal update's every output (gradient, loss, std, lengths, counts), in the
    paper's arena: the same hash means the same numbers, bit for bit."""
    import torch

    from drone_torchrl.envs import dynamics
    from drone_torchrl.kernels import modules
    from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy

    torch.manual_seed(0)
    stacked = StackedThreeNet([ThreeNetPolicy([32, 32], "tanh") for _ in range(8)], "tanh")
    rollout = modules.KernelRollout(stacked, dynamics.DroneParams(), None, STEPS)
    flags = {
        "baseline_mean": True,
        "normalize_returns": True,
        "discount_weight": False,
        "mean_log_prob": False,
    }
    update = modules.KernelReinforce(rollout, 4, flags)
    out = update(
        torch.arange(8), torch.arange(8) * 3, torch.full((8,), 0.99), torch.ones(8, dtype=torch.bool)
    )
    return hashlib.sha256(b"".join(x.numpy().tobytes() for x in out)).hexdigest()[:16]


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


def build_seconds(source: Path, repeats: int = 3) -> tuple[float, float]:
    """Median wall-clock and CPU seconds of a cold float32 build of ``source`` with build.py's flags
    (the CPU time hardly depends on what else the machine runs)."""
    from drone_torchrl.kernels import build

    flags = [*build.BASE_FLAGS, "-DDK_DOUBLE=0", *build.ARCH_FLAGS]
    wall, cpu = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
            subprocess.run([build._compiler(), *flags, str(source), "-o", f"{tmp}/k.so"], check=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            wall.append(time.perf_counter() - start)
            cpu.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--against", default="d88f933", help="the commit whose nominal kernels to time too")
    parser.add_argument(
        "--repeats", type=int, default=5, help="timed passes per round (after 3 warm-up calls)"
    )
    parser.add_argument(
        "--rounds", type=int, default=6, help="rounds, alternating this checkout and --against"
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--nominal-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.repeats, args.nominal_only)))
        return
    times: dict[str, dict[str, list]] = {"this": {}, "against": {}}
    with tempfile.TemporaryDirectory() as tmp:
        old = _export(args.against, Path(tmp))
        for _ in range(args.rounds):
            for who, tree, nominal_only in (("this", None, False), ("against", old, True)):
                for key, values in _run_worker(tree, args.repeats, nominal_only).items():
                    times[who].setdefault(key, []).extend(values)
        builds = {args.against: build_seconds(old / "drone_torchrl/kernels/drone_kernels.cpp")}
    builds["this checkout"] = build_seconds(ROOT / "drone_torchrl/kernels/drone_kernels.cpp")
    ms = {
        who: {k: (1e3 * statistics.median(v), 1e3 * min(v)) for k, v in t.items() if not k.startswith("_")}
        for who, t in times.items()
    }
    print(
        f"{args.rounds * args.repeats} calls each, one thread, median (min) ms; this checkout: {times['this']['_file'][0]}"
    )
    for key, (median, least) in ms["this"].items():
        base, base_min = ms["this"][key.rsplit(" ", 1)[0] + " nominal"]
        print(
            f"  {key:<32} {median:7.3f} ({least:7.3f})  {median / base:5.2f}x ({least / base_min:5.2f}x) nominal"
        )
    same = times["this"]["_digest"][0] == times["against"]["_digest"][0]
    print(
        f"nominal, {args.against}'s kernels ({times['against']['_file'][0]}); one update's outputs bit for bit the same: {same}"
    )
    for key, (median, least) in ms["against"].items():
        this, this_min = ms["this"][key]
        print(
            f"  {key:<32} {median:7.3f} ({least:7.3f})  this checkout {this / median:5.2f}x ({this_min / least:5.2f}x)"
        )
    for who, (wall, cpu) in builds.items():
        print(f"cold float32 build, {who}: {wall:.1f} s wall, {cpu:.1f} s CPU (median of 3)")


if __name__ == "__main__":
    main()
