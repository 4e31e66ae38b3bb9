"""Flight under disturbances: the PD controller, a PID tuned per condition, PPO and PPO trained under them.

    python benchmarks/disturbances.py --train                  # train both PPO runs (seed 0), then the table
    python benchmarks/disturbances.py --train --population --seeds 0 1 2 3   # and REINFORCE+ randomised
    python benchmarks/disturbances.py --nominal RUN --randomised RUN

For each condition of ``conf/disturbance/`` (``none``, ``mild``, ``strong``), with bounded thrust
(``experiment=bounded``: ``max_thrust=1``), every controller flies the same 100 seeded episodes
(evaluation seed 0: the same start states and, per condition, the same disturbance draws):

- **PD**: the nominal PD controller (its gains were designed for the perfect model);
- **PID, tuned**: :func:`pid_tuning.tune_pid` (``benchmarks/pid_tuning.py``) for that condition on its own seeds (1000),
  so RL is compared with the best classical controller this search finds for that condition;
- **PPO**: ``drone-train algo=ppo experiment=bounded`` (trained on the nominal drone);
- **PPO, randomised**: ``drone-train experiment=randomised``, trained under ``disturbance=strong``
  (domain randomisation: every episode draws its disturbances), the last 2 commands observed;
- with ``--population``, **REINFORCE+, randomised**: the same preset with ``algo=reinforce_plus``,
  the seeds trained as one population of the fused engine (``hydra/launcher=fused``).

Each row: mean return, crashes (episodes that ended before ``max_steps``), and the mean first step
in the zone over the episodes that reach it. Timings: the tuning per condition and each training.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

CONDITIONS = ("none", "mild", "strong")
EPISODES = 100
SEED = 0
NOMINAL = ["algo=ppo", "experiment=bounded"]
# The strong preset during training, the last 2 commands observed, twice the budget.
RANDOMISED = ["experiment=randomised"]
# The same preset on the population engine: REINFORCE+ agents trained side by side.
POPULATION = ["-m", "experiment=randomised", "algo=reinforce_plus", "hydra/launcher=fused"]


def _train(out: Path, name: str, overrides: list[str], seeds: list[int]) -> tuple[list[Path], float]:
    """Train ``seeds`` (one run, or one sweep with ``-m`` in ``overrides``): the run folders and seconds."""
    sweep = overrides[0] == "-m"
    folder = out / (name if sweep else f"{name}_s{seeds[0]}")
    where = [f"hydra.sweep.dir={folder}", f"hydra.sweep.subdir={name}_s${{seed}}"]
    cmd = [
        str(Path(sys.executable).parent / "drone-train"),
        *overrides,
        f"seed={','.join(map(str, seeds))}",
        *(where if sweep else [f"hydra.run.dir={folder}"]),
        "eval.video=false",
        "progress=false",
    ]
    start = time.perf_counter()
    with open(folder.with_suffix(".log"), "w") as log:
        subprocess.run(
            cmd,
            check=True,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
        )
    runs = sorted(p.parent for p in folder.glob(f"{name}_s*/config.yaml")) if sweep else [folder]
    return runs, time.perf_counter() - start


def _condition(name: str) -> dict:
    """The env arguments of ``experiment=bounded disturbance=<name>`` (composed from conf/)."""
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import config_dir, env_kwargs

    with initialize_config_dir(config_dir(), version_base="1.3"):
        return env_kwargs(compose("config", ["experiment=bounded", f"disturbance={name}"]))


def _actor(run: Path):
    """The run's last actor and the number of past commands it observes."""
    from drone_torchrl.config import env_kwargs, run_config
    from drone_torchrl.io.checkpoint import load_checkpoint
    from drone_torchrl.modules.factory import build_actor

    state = load_checkpoint(run / "checkpoints" / "last.pt")
    cfg = run_config(state["config"])
    actor = build_actor(cfg)
    actor.load_state_dict(state["actor"])
    return actor.eval(), env_kwargs(cfg)["disturbance"]["observed_actions"]


def _row(stats: dict, max_steps: int) -> tuple[float, int, float]:
    returns, first = stats["return"].float(), stats["first_zone_step"].float()
    reached = first > 0
    crashes = int((stats["length"] < max_steps).sum())
    return float(returns.mean()), crashes, float(first[reached].mean()) if reached.any() else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", action="store_true", help="train both PPO runs first (seed 0)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds with --train")
    parser.add_argument(
        "--nominal", type=Path, nargs="*", default=[], help="PPO run folders trained nominally"
    )
    parser.add_argument(
        "--randomised", type=Path, nargs="*", default=[], help="run folders trained under disturbances"
    )
    parser.add_argument(
        "--population", action="store_true", help="with --train: also REINFORCE+ randomised (fused engine)"
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/benchmarks/disturbances"))
    args = parser.parse_args()

    from pid_tuning import PIDController, tune_pid  # a sibling script: benchmarks/ is sys.path[0]

    from drone_torchrl.config import physics_params
    from drone_torchrl.envs.heuristic import PDController
    from drone_torchrl.evaluation import evaluate

    args.out.mkdir(parents=True, exist_ok=True)
    nominal, randomised = list(args.nominal), list(args.randomised)
    if args.train:
        for seed in args.seeds:
            for name, overrides, runs in (
                ("ppo", NOMINAL, nominal),
                ("ppo_randomised", RANDOMISED, randomised),
            ):
                (run,), seconds = _train(args.out, name, overrides, [seed])
                print(f"trained {run}: {seconds:.0f} s")
                runs.append(run)
        if args.population:
            runs, seconds = _train(args.out, "reinforce_plus_randomised", POPULATION, args.seeds)
            print(f"trained {len(runs)} agents as one population in {args.out}: {seconds:.0f} s")
            randomised.extend(runs)

    policies = {}
    for run in (*nominal, *randomised):
        policies[run.name] = _actor(run)

    print(
        f"\n{EPISODES} seeded episodes (seed {SEED}), max_thrust 1: return / crashes / first step in the zone\n"
    )
    print("| condition | controller | return | crashes | first zone step |")
    print("|---|---|---|---|---|")
    for condition in CONDITIONS:
        kwargs = _condition(condition)
        params = physics_params(kwargs)
        start = time.perf_counter()
        gains, record = tune_pid(kwargs)
        tuning = time.perf_counter() - start
        rows = {
            "PD": (PDController(params), 0),
            f"PID, tuned ({tuning:.0f} s)": (PIDController(params, gains), 0),
        }
        rows.update(policies)
        for name, (policy, observed) in rows.items():
            flown = {**kwargs, "disturbance": {**kwargs["disturbance"], "observed_actions": observed}}
            stats, _ = evaluate(policy, flown, EPISODES, SEED)
            mean, crashes, first = _row(stats, kwargs["max_steps"])
            print(f"| {condition} | {name} | {mean:.1f} | {crashes} | {first:.1f} |", flush=True)


if __name__ == "__main__":
    main()
