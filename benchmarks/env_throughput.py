"""Throughput of ``DroneEnv`` through TorchRL's API against the bare ``dynamics.step`` function.

For each batch size the same action sequence is fed to

* **env**: ``DroneEnv(batch_size=[B])`` driven by ``env.step_and_maybe_reset(td)`` in a loop, i.e.
  TorchRL's own stepping path including ``step_mdp`` and the automatic partial resets of done
  sub-environments (the path collectors use), and
* **bare**: ``dynamics.step(state, action, params)`` in a loop on a ``[B, 6]`` tensor, the physics
  alone (no resets, no TensorDict, no checks). Its cost does not depend on the values, so the
  states drifting without resets does not matter.

Action modes (``--actions``; the default runs both):

* ``random``: each motor uniform in ``[0, 1]`` times the weight (mean thrust = the weight). Drones
  tumble and leave the domain at different times, so partial resets (``"_reset"`` masks with some
  True entries) happen on most steps at large batch sizes: the realistic training workload.
* ``zero``: both motors off. Every drone falls from the floor reset and terminates (``FLOOR``) on
  its 5th step, all at the same time, so every 5th step is a full reset.

A pool of ``ACTION_POOL`` action tensors is drawn once per batch size from a fixed seed and cycled
through, for both loops, so action generation is not timed.

Rates are transitions per second (``batch x steps / time``), the median over ``--repeats`` timed
repeats after ``--warmup`` untimed steps. At batch 1 the per-step latency (microseconds) is also
printed. ``--compile`` additionally times everything with ``dynamics.step`` replaced by
``torch.compile(dynamics.step)`` (the env calls ``dynamics.step`` through the module, so it picks
the compiled function up too).

Usage::

    python benchmarks/env_throughput.py                 # 1 thread, batches 1 64 4096 65536
    python benchmarks/env_throughput.py --compile --threads 2
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from drone_torchrl.envs import DroneEnv, dynamics

DEFAULT_BATCH_SIZES = (1, 64, 4096, 65536)
ACTION_MODES = ("random", "zero")
ACTION_POOL = 16
ACTION_SEED = 1234
ENV_SEED = 0
# Timed steps per repeat: about TRANSITIONS_PER_REPEAT transitions, within [MIN_STEPS, MAX_STEPS].
TRANSITIONS_PER_REPEAT = 2_000_000
MIN_STEPS, MAX_STEPS = 50, 2000
DEFAULT_REPEATS = 5
DEFAULT_WARMUP = 20
TARGET_RATIO = 0.5  # the target at the largest batch: env >= 50% of the bare rate
COMPILE_PROBE_BATCH = 8
COMPILE_ATOL = 1e-6  # compiled kernels may fuse/reorder float ops
RECOMPILE_LIMIT = 64  # every batch size is a new static shape for torch.compile
US_PER_S = 1e6

StepFn = Callable[[torch.Tensor, torch.Tensor, dynamics.DroneParams], tuple]


@dataclass
class Result:
    """Median rates (transitions/s) of one batch size, action mode and dynamics variant."""

    variant: str
    mode: str
    batch: int
    steps: int
    env_rate: float
    bare_rate: float
    dones_per_step: float  # sub-envs done (then reset) per env step, from an untimed pass

    @property
    def ratio(self) -> float:
        return self.env_rate / self.bare_rate

    def latency_us(self, rate: float) -> float:
        """Microseconds per step call (all ``batch`` sub-envs together)."""
        return US_PER_S * self.batch / rate


def make_actions(mode: str, batch: int, max_thrust: float | None) -> list[torch.Tensor]:
    """``ACTION_POOL`` action tensors ``[batch, 2]`` for the given mode (seeded)."""
    if mode == "zero":
        return [torch.zeros(batch, dynamics.ACTION_DIM)] * ACTION_POOL
    generator = torch.Generator().manual_seed(ACTION_SEED)
    high = 1.0 if max_thrust is None else min(1.0, max_thrust)
    return [high * torch.rand(batch, dynamics.ACTION_DIM, generator=generator) for _ in range(ACTION_POOL)]


def steps_for(batch: int, override: int | None) -> int:
    """Timed steps per repeat: ``override`` if given, else about ``TRANSITIONS_PER_REPEAT`` transitions."""
    if override is not None:
        return override
    return max(MIN_STEPS, min(MAX_STEPS, TRANSITIONS_PER_REPEAT // batch))


def time_env(
    env: DroneEnv, actions: Sequence[torch.Tensor], steps: int, warmup: int, repeats: int
) -> tuple[float, float]:
    """Median seconds per ``steps`` calls of ``step_and_maybe_reset``, and done sub-envs per step."""
    env.set_seed(ENV_SEED)
    td = env.reset()
    n_actions = len(actions)

    def run(n: int) -> None:
        nonlocal td
        for i in range(n):
            td.set("action", actions[i % n_actions])
            _, td = env.step_and_maybe_reset(td)

    run(warmup)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run(steps)
        times.append(time.perf_counter() - start)
    # Count resets in a separate, untimed pass so that the count does not slow the timed loop.
    done_count = 0
    for i in range(steps):
        td.set("action", actions[i % n_actions])
        stepped, td = env.step_and_maybe_reset(td)
        done_count += int(stepped["next", "done"].sum())
    return statistics.median(times), done_count / steps


def time_bare(
    step_fn: StepFn,
    params: dynamics.DroneParams,
    actions: Sequence[torch.Tensor],
    steps: int,
    warmup: int,
    repeats: int,
) -> float:
    """Median seconds per ``steps`` calls of ``step_fn`` on the same batch and actions.

    The state is chained from a floor reset without resets; over a few thousand steps its values stay
    far below the magnitudes where ``sin``/``cos`` slow down (about 1e5 rad), so the cost is that of
    in-domain states.
    """
    batch = actions[0].shape[0]
    state0 = dynamics.initial_state((batch,), "floor", torch.Generator().manual_seed(ENV_SEED))
    n_actions = len(actions)

    def run(n: int) -> None:
        state = state0
        for i in range(n):
            state, _, _ = step_fn(state, actions[i % n_actions], params)

    run(warmup)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run(steps)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def bench(variant: str, mode: str, batch: int, args: argparse.Namespace, step_fn: StepFn) -> Result:
    """Time the env and the bare step function for one batch size and action mode."""
    steps = steps_for(batch, args.steps)
    env = DroneEnv(batch_size=[batch], max_thrust=args.max_thrust)
    actions = make_actions(mode, batch, args.max_thrust)
    with torch.no_grad():
        env_time, resets = time_env(env, actions, steps, args.warmup, args.repeats)
        bare_time = time_bare(step_fn, env.params, actions, steps, args.warmup, args.repeats)
    env.close()
    transitions = batch * steps
    return Result(variant, mode, batch, steps, transitions / env_time, transitions / bare_time, resets)


def fmt_rate(rate: float) -> str:
    for scale, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if rate >= scale:
            return f"{rate / scale:.2f} {unit}"
    return f"{rate:.0f}"


def markdown_table(results: Sequence[Result]) -> str:
    header = (
        "| dynamics | actions | batch | steps/repeat | dones/step | env transitions/s "
        "| bare transitions/s | env / bare | env latency (us) | bare latency (us) |"
    )
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in results:
        latency = (f"{r.latency_us(r.env_rate):.0f}", f"{r.latency_us(r.bare_rate):.1f}")
        if r.batch != 1:
            latency = ("", "")
        lines.append(
            f"| {r.variant} | {r.mode} | {r.batch} | {r.steps} | {r.dones_per_step:.1f} "
            f"| {fmt_rate(r.env_rate)} | {fmt_rate(r.bare_rate)} | {r.ratio:.1%} "
            f"| {latency[0]} | {latency[1]} |"
        )
    return "\n".join(lines)


def _compilable_step(
    state: torch.Tensor, action: torch.Tensor, params: dynamics.DroneParams
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``dynamics.step`` with its one ``tensor != IntEnum`` comparison written as ``tensor != int``.

    TorchDynamo in torch 2.13 traces ``cause != TerminationCause.NONE`` (an ``IntEnum`` member) to a
    Python ``bool`` instead of a tensor, so ``torch.compile(dynamics.step)`` raises ``TypeError`` in
    ``torch.where``. The values are identical in eager mode; :func:`compiled_step` checks that.
    """
    next_state = dynamics.integrate(state, dynamics.clamp_action(action, params.max_thrust), params)
    cause = dynamics.termination_cause(next_state, params)
    terminated = cause != int(dynamics.TerminationCause.NONE)
    return next_state, dynamics.reward(next_state, terminated, params), cause


def _same_as_eager(step_fn: StepFn, max_thrust: float | None) -> bool:
    """Does ``step_fn`` give exactly ``dynamics.step``'s outputs on a small random batch?"""
    generator = torch.Generator().manual_seed(ACTION_SEED)
    state = 4.0 * torch.rand(COMPILE_PROBE_BATCH, dynamics.STATE_DIM, generator=generator) - 2.0
    action = torch.rand(COMPILE_PROBE_BATCH, dynamics.ACTION_DIM, generator=generator)
    params = DroneEnv(batch_size=[1], max_thrust=max_thrust).params
    expected = dynamics.step(state, action, params)
    got = step_fn(state, action, params)
    return all(
        torch.allclose(a.float(), b.float(), rtol=0.0, atol=COMPILE_ATOL)
        for a, b in zip(expected, got, strict=True)
    )


def compiled_step(max_thrust: float | None) -> tuple[StepFn, str]:
    """``torch.compile(dynamics.step)``; if that fails, the compiled :func:`_compilable_step`.

    Returns the function and a label for the table. Each batch size is a new static shape, so the
    recompile limit is raised.
    """
    import torch._dynamo

    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
    compiled = torch.compile(dynamics.step, dynamic=False)
    try:
        if _same_as_eager(compiled, max_thrust):
            return compiled, "compiled"
        print("torch.compile(dynamics.step) runs but its outputs differ from eager; not timed")
    except Exception as err:  # report any compiler failure and carry on
        message = str(err).strip().splitlines()[0] if str(err).strip() else ""
        print(f"torch.compile(dynamics.step) FAILS on this machine: {type(err).__name__}: {message}")
        print(
            "  cause: TorchDynamo traces `cause != TerminationCause.NONE` (IntEnum) in dynamics.step to a "
            "Python bool; fix: compare with int(TerminationCause.NONE)"
        )
    fallback = torch.compile(_compilable_step, dynamic=False)
    if not _same_as_eager(fallback, max_thrust):
        raise RuntimeError("the compiled fallback step differs from dynamics.step")
    print("  timing torch.compile of an equivalent step with that fix instead (row label compiled*)")
    return fallback, "compiled*"


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=list(DEFAULT_BATCH_SIZES))
    parser.add_argument("--actions", nargs="+", choices=ACTION_MODES, default=list(ACTION_MODES))
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS)
    parser.add_argument("--warmup", type=int, default=DEFAULT_WARMUP)
    parser.add_argument("--steps", type=int, default=None, help="timed steps per repeat (default: auto)")
    parser.add_argument("--max-thrust", type=float, default=None, help="DroneEnv max_thrust (default None)")
    parser.add_argument(
        "--compile", action="store_true", help="also time with dynamics.step wrapped in torch.compile"
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> list[Result]:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    print(
        f"torch {torch.__version__}, threads={torch.get_num_threads()}, max_thrust={args.max_thrust}, "
        f"repeats={args.repeats} (median), warmup={args.warmup}"
    )
    eager_step = dynamics.step
    variants: list[tuple[str, StepFn]] = [("eager", eager_step)]
    if args.compile:
        step_fn, label = compiled_step(args.max_thrust)
        variants.append((label, step_fn))
    results = []
    try:
        for variant, step_fn in variants:
            dynamics.step = step_fn  # DroneEnv calls dynamics.step through the module
            for mode in args.actions:
                for batch in args.batch_sizes:
                    start = time.perf_counter()
                    result = bench(variant, mode, batch, args, step_fn)
                    results.append(result)
                    print(
                        f"{variant:8s} {mode:6s} batch {batch:6d}: env {fmt_rate(result.env_rate)}/s, "
                        f"bare {fmt_rate(result.bare_rate)}/s, env/bare {result.ratio:.1%} "
                        f"({time.perf_counter() - start:.1f} s)",
                        flush=True,
                    )
    finally:
        dynamics.step = eager_step
    print()
    print(markdown_table(results))
    largest = max(args.batch_sizes)
    for r in results:
        if r.batch == largest:
            verdict = "meets" if r.ratio >= TARGET_RATIO else "misses"
            print(
                f"batch {largest} ({r.variant}, {r.mode}): env/bare = {r.ratio:.1%}, "
                f"{verdict} the {TARGET_RATIO:.0%} target"
            )
    return results


if __name__ == "__main__":
    main()
