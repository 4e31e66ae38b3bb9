"""Every algorithm option (``conf/algo/*``: REINFORCE, REINFORCE+, PPO, A2C, SAC, ...) with bounded thrust, 4
seeds each, against the PD controller.

    python benchmarks/algorithms.py                      # every algorithm, 4 seeds, their default budgets
    python benchmarks/algorithms.py --algos ppo --seeds 0 1     # a shorter run
    python benchmarks/algorithms.py --reuse       # train only the algorithms not in --out yet
    python benchmarks/algorithms.py --sb3 --sb3-steps 200000   # also SB3's PPO (pip install ".[bench]")

Each algorithm trains with ``experiment=bounded`` (TanhNormal head, thrust in [0, 1] x weight per
motor) through ``drone-train -m seed=... hydra/launcher=fused``, one algorithm after another, so
every wall-clock is measured on the same machine in one run. From each run's ``episodes.csv`` it
draws the running-mean return against env steps and against wall-clock (median over seeds, the
band from min to max) with the PD controller's return on the same task as a line, and prints a
table: env steps and seconds until the running mean reaches full-length episodes and 90% of PD,
the final running mean, and the deterministic evaluation of each run's last checkpoint over 100
seeded episodes (``drone-eval``'s evaluator), with the crashes among them.

With ``--sb3`` (``pip install ".[bench]"``), Stable-Baselines3's PPO (its defaults, an MLP policy,
8 envs) trains on the Gymnasium twin ``Drone2D-v0`` with ``max_thrust=1.0`` for the env-step budget
of our PPO's first seed (or ``--sb3-steps``), timed in the same run: the reference a user would
compare with. Its rows compare at equal env steps: the running mean each reached by SB3's last
step, and the seconds each took to a running mean of 2000.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from drone_torchrl.config import group_options

BOUNDED = {"max_thrust": 1.0}
FULL_LENGTH = 300
PD_SHARE = 0.9
RETURN_MARK = 2000.0
WINDOW = 100
EVAL_EPISODES = 100


def _train(algo: str, seeds: list[int], out: Path, overrides: list[str]) -> float:
    sweep = out / algo
    cmd = [
        str(Path(sys.executable).parent / "drone-train"),
        "-m",
        f"algo={algo}",
        "experiment=bounded",
        f"seed={','.join(map(str, seeds))}",
        "hydra/launcher=fused",
        f"hydra.sweep.dir={sweep}",
        "eval.video=false",
        "progress=false",
        *overrides,
    ]
    start = time.perf_counter()
    with open(out / f"{algo}.log", "w") as log:
        subprocess.run(
            cmd,
            check=True,
            stdout=log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
        )
    return time.perf_counter() - start


def _curves(sweep: Path) -> list[dict[str, np.ndarray]]:
    from drone_torchrl.io.episodes_csv import read_episodes
    from drone_torchrl.training.jobs import sweep_jobs

    runs = []
    for job in sweep_jobs(sweep):
        columns, _ = read_episodes(job / "episodes.csv")
        returns, lengths = columns["return"], columns["length"]
        kernel = np.ones(WINDOW)
        count = np.convolve(np.ones_like(returns), kernel)[: len(returns)]
        runs.append(
            {
                "job": job,
                "steps": np.cumsum(lengths),
                "seconds": columns["wall_clock_s"],
                "return": np.convolve(returns, kernel)[: len(returns)] / count,
                "length": np.convolve(lengths, kernel)[: len(lengths)] / count,
            }
        )
    return runs


def _first(run: dict[str, np.ndarray], key: str, level: float) -> tuple[float, float]:
    hit = np.nonzero(run[key] >= level)[0]
    return (float(run["steps"][hit[0]]), float(run["seconds"][hit[0]])) if hit.size else (np.nan, np.nan)


def _evaluate(job: Path) -> tuple[float, int]:
    from drone_torchrl.config import env_kwargs, run_config
    from drone_torchrl.evaluation import evaluate
    from drone_torchrl.io.checkpoint import load_checkpoint
    from drone_torchrl.modules.factory import build_actor

    state = load_checkpoint(job / "checkpoints" / "last.pt")
    cfg = run_config(state["config"])
    actor = build_actor(cfg)
    actor.load_state_dict(state["actor"])
    stats, _ = evaluate(actor, env_kwargs(cfg), EVAL_EPISODES, 0)
    return float(stats["return"].float().mean()), int((stats["length"] < cfg.env.max_steps).sum())


def _sb3(budget: int, out: Path) -> dict[str, np.ndarray] | None:
    try:
        from stable_baselines3 import PPO
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.env_util import make_vec_env
    except ImportError:
        print('--sb3: stable-baselines3 is not installed (pip install ".[bench]"); skipped')
        return None
    import drone_torchrl.envs  # noqa: F401  (registers Drone2D-v0)

    class Episodes(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.rows: list[tuple[int, float, float, int]] = []
            self.start = time.perf_counter()

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                if "episode" in info:
                    episode = info["episode"]
                    self.rows.append(
                        (self.num_timesteps, time.perf_counter() - self.start, episode["r"], episode["l"])
                    )
            return True

    env = make_vec_env("Drone2D-v0", n_envs=8, seed=0, env_kwargs=BOUNDED)
    callback = Episodes()
    PPO("MlpPolicy", env, seed=0, device="cpu").learn(total_timesteps=budget, callback=callback)
    steps, seconds, returns, lengths = (np.array(c, dtype=float) for c in zip(*callback.rows, strict=True))
    kernel = np.ones(WINDOW)
    count = np.convolve(np.ones_like(returns), kernel)[: len(returns)]
    return {
        "job": out / "sb3",
        "steps": steps,
        "seconds": seconds,
        "return": np.convolve(returns, kernel)[: len(returns)] / count,
        "length": np.convolve(lengths, kernel)[: len(lengths)] / count,
    }


def _band(runs: list[dict[str, np.ndarray]], x: str, grid: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(grid, r[x], r["return"], right=np.nan) for r in runs])


def _figure(results: dict[str, list[dict[str, np.ndarray]]], pd_return: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, x, label in ((axes[0], "steps", "env steps"), (axes[1], "seconds", "wall-clock [s]")):
        for name, runs in results.items():
            grid = np.linspace(0, max(r[x][-1] for r in runs), 400)
            band = _band(runs, x, grid)
            (line,) = ax.plot(
                grid, np.nanmedian(band, 0), label=f"{name} ({len(runs)} seed{'s' if len(runs) > 1 else ''})"
            )
            ax.fill_between(grid, np.nanmin(band, 0), np.nanmax(band, 0), color=line.get_color(), alpha=0.2)
        ax.axhline(pd_return, color="black", ls="--", lw=1, label=f"PD controller ({pd_return:.0f})")
        ax.set(xlabel=label, ylabel=f"running mean return ({WINDOW} episodes)", xscale="log")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper left")
    fig.suptitle("Bounded thrust (thrust-to-weight 2): median over seeds, band = min..max")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    # Every option of the algo group (conf/algo/*.yaml): each registered algorithm, some with several
    # (reinforce_plus is REINFORCE), so a new one is benchmarked without an edit here.
    algos = group_options("algo")
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/algorithms"))
    parser.add_argument("--algos", nargs="+", choices=algos, default=algos)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    parser.add_argument(
        "--sb3", action="store_true", help="also train Stable-Baselines3's PPO (pip install '.[bench]')"
    )
    parser.add_argument(
        "--sb3-steps", type=int, default=None, help="SB3's env-step budget (default: our PPO's first seed's)"
    )
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="an algorithm whose sweep is in --out already is not trained again",
    )
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every algorithm")
    return parser.parse_args(argv)


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    from drone_torchrl.evaluation import evaluate_pd

    pd_return = evaluate_pd(BOUNDED, EVAL_EPISODES, 0)["return_mean"]
    results: dict[str, list[dict[str, np.ndarray]]] = {}
    for algo in args.algos:
        if args.reuse and (args.out / algo).is_dir():
            print(f"{algo}: the runs in {args.out / algo} (--reuse)")
        else:
            seconds = _train(algo, args.seeds, args.out, args.overrides)
            print(f"{algo}: {len(args.seeds)} seeds trained in {seconds:.0f} s")
        results[algo] = _curves(args.out / algo)
    if args.sb3 and "ppo" in results:
        sb3 = _sb3(args.sb3_steps or int(results["ppo"][0]["steps"][-1]), args.out)
        if sb3 is not None:
            results["sb3 ppo"] = [sb3]

    print(f"\nPD controller, bounded thrust, {EVAL_EPISODES} seeded episodes: {pd_return:.1f}")
    at = int(results["sb3 ppo"][0]["steps"][-1]) if "sb3 ppo" in results else None
    print(
        "| algorithm | seed | steps / s to full length | steps / s to 2000 | steps / s to 90% PD "
        f"| final running mean |{f' running mean at {at} steps |' if at else ''} eval (100 episodes) | crashes |"
    )
    print("|---|---|---|---|---|---|" + ("---|" if at else "") + "---|---|")
    for name, runs in results.items():
        for run in runs:
            cells = [
                "{:.0f} / {:.1f}".format(*_first(run, key, level))
                for key, level in (
                    ("length", FULL_LENGTH),
                    ("return", RETURN_MARK),
                    ("return", PD_SHARE * pd_return),
                )
            ]
            if at:
                cells.append(f"{np.interp(at, run['steps'], run['return']):.1f}")
            evaluated, crashes = _evaluate(run["job"]) if name in args.algos else (np.nan, "")
            print(
                f"| {name} | {run['job'].name.rsplit('seed=', 1)[-1]} | {cells[0]} | {cells[1]} | {cells[2]} | {run['return'][-1]:.1f} |"
                + (f" {cells[3]} |" if at else "")
                + f" {evaluated:.1f} ({100 * evaluated / pd_return:.1f}% of PD) | {crashes} |"
            )
    path = args.out / "algorithms.png"
    _figure(results, pd_return, path)
    print(f"\nfigure: {path}")


if __name__ == "__main__":
    main()
