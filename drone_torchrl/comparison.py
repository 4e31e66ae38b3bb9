"""drone-eval's work: fly a checkpoint (or the PD controller) on seeded episodes, compare, and plot.

``run_eval(cfg)`` takes the ``conf/eval.yaml`` config; the command-line shell is
:mod:`drone_torchrl.apps.evaluate`. Besides the printed table it writes, in its output folder,
the same table as :data:`TABLE_NAME` (a CSV, one row per policy: ``pandas.read_csv``) and
:data:`SETTINGS_NAME` (JSON: what was flown, and the rows), beside the plot and the video.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from tensordict import TensorDictBase

from drone_torchrl import memory_estimate
from drone_torchrl.config import (
    ConfigError,
    check_device,
    check_keys,
    check_networks,
    check_values,
    command_line_keys,
    env_kwargs,
    physics_params,
    run_config,
    validate,
)
from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.envs.drone_env import check_env_args
from drone_torchrl.envs.heuristic import PDController
from drone_torchrl.envs.params import DroneParams
from drone_torchrl.evaluation import evaluate, max_return, reference_optimum, summarize
from drone_torchrl.io.storage import new_figure, write_atomically, write_csv, write_figure
from drone_torchrl.io.streams import console
from drone_torchrl.io.video import record_video, save_gif
from drone_torchrl.modules.factory import build_actor
from drone_torchrl.objectives.reinforce import valid_steps
from drone_torchrl.optimum import Optimum
from drone_torchrl.training.population_record import open_agent

PLOT_NAME = "trajectory.png"
VIDEO_NAME = "episode.gif"
#: The PD hover controller's name in the table (and in :func:`run_eval`'s results).
PD_NAME = "PD controller"
#: The printed table as a CSV file in the output folder, one row per policy.
TABLE_NAME = "results.csv"
#: What was flown (checkpoint, episodes, seed, env, ceiling, optimum) and the rows, as JSON.
SETTINGS_NAME = "results.json"
#: The summaries' keys (:func:`~drone_torchrl.evaluation.summarize`) the table leaves out; the causes
#: become its last columns, ``ends_<CAUSE>`` each.
NOT_IN_TABLE = ("terminated_fraction", "causes")


def plot_trajectory(rollout: TensorDictBase, path: Path, title: str, p: DroneParams) -> Path:
    """Plot the first episode's x-z path over the domain and target zone, and both thrusts over time.

    The domain and zone are those of ``p``, the env's parameters.
    """
    from matplotlib.patches import Rectangle

    first = rollout[0]
    valid = valid_steps(first.get(("next", "done"))).squeeze(-1)
    states = torch.cat([first.get("observation")[:1], first.get(("next", "observation"))[valid]]).numpy()
    actions = first.get("action")[valid].numpy()
    fig = new_figure((11, 4.5))
    ax_path, ax_thrust = fig.subplots(1, 2)
    zone = (-p.zone_x_limit, p.zone_z_min), 2 * p.zone_x_limit, p.zone_z_max - p.zone_z_min
    ax_path.add_patch(Rectangle(*zone, color="tab:green", alpha=0.2, label="target zone"))
    ax_path.plot(states[:, dynamics.X], states[:, dynamics.Z], color="tab:blue", label="path")
    ax_path.plot(states[0, dynamics.X], states[0, dynamics.Z], "o", color="tab:blue", label="start")
    ax_path.set(xlim=(-p.x_limit, p.x_limit), ylim=(p.z_min, p.z_max), xlabel="x [m]", ylabel="z [m]")
    ax_path.set(aspect="equal", title="path")
    ax_path.grid(alpha=0.3)
    ax_path.legend(loc="lower right", fontsize=8)
    steps = np.arange(1, len(actions) + 1)
    ax_thrust.plot(steps, actions[:, 0], label="left motor")
    ax_thrust.plot(steps, actions[:, 1], label="right motor")
    ax_thrust.axhline(0.5, color="gray", ls="--", lw=0.8, label="hover (0.5)")
    ax_thrust.axhline(0.0, color="black", lw=0.6)
    ax_thrust.set(xlabel="step", ylabel="thrust / weight", title="motor commands")
    ax_thrust.grid(alpha=0.3)
    ax_thrust.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return write_figure(fig, path, dpi=100)


def _flown_env(cfg: DictConfig, run_env: dict, path: Path, keys: set[str]) -> dict:
    """The checkpoint's run's env under the disturbances drone-eval was asked for.

    The disturbances are ``disturbance=...``'s, the evaluation's conditions; the run's
    ``observed_actions`` is kept, since it is the policy's input layout, not a condition. Any other
    ``env.*`` override that differs from the run's is refused, not ignored: the checkpoint flies in
    its own env. ``keys``: those the caller set.
    """
    changed = [
        f"env.{name} {run_env[name]!r} -> {cfg.env[name]!r}"
        for name in run_env
        if name != "disturbance"
        and ("env" in keys or f"env.{name}" in keys)
        and cfg.env[name] != run_env[name]
    ]
    if changed:
        raise ConfigError(
            f"checkpoint={str(path)!r} flies in the env it was trained in; the command line changes "
            f"{'; '.join(changed)}: drop those overrides"
        )
    asked = env_kwargs(cfg)["disturbance"]
    trained = disturbances.make(run_env["disturbance"]).observed_actions
    if asked["observed_actions"] != trained and "env.disturbance.observed_actions" in keys:
        raise ConfigError(
            f"checkpoint={str(path)!r} reads {trained} past command(s) in its observations; "
            f"env.disturbance.observed_actions={asked['observed_actions']} cannot change that: drop the override"
        )
    return {**run_env, "disturbance": {**asked, "observed_actions": trained}}


def optimum_line(kwargs: dict, optimum: Optimum | None, ceiling: float) -> str:
    """The line that says what the best achievable return of these episodes is (docs/optimum.md)."""
    if physics_params(kwargs).max_thrust is None:
        return (
            f"optimum: with unbounded thrust the best achievable return is the ceiling {ceiling:.0f} (a thrust "
            "pulse of hundreds of weights on step 1 puts the drone in the zone), so the PD controller is the reference"
        )
    if optimum is None and disturbances.make(kwargs.get("disturbance")).active:
        return "optimum: derived for the nominal drone only, not under disturbances; the PD controller is the reference"
    if optimum is None:
        return "optimum: not derived for these settings (max_thrust below the hover thrust)"
    return (
        f"optimum: the best achievable return of each of these episodes is {optimum.best_return:.0f} "
        f"({optimum.describe()}; docs/optimum.md)"
    )


def write_table(out_dir: Path, results: dict[str, dict], settings: dict[str, Any]) -> tuple[Path, Path]:
    """Write the table as :data:`TABLE_NAME` and, with the settings, :data:`SETTINGS_NAME`, atomically.

    One row per policy: ``policy``, its :func:`~drone_torchrl.evaluation.summarize` but
    :data:`NOT_IN_TABLE`, then ``ends_<CAUSE>``. A number that is not one (no optimum, no episode
    reached the zone) is ``nan`` in the CSV and ``null`` in the JSON (which has no NaN).
    """
    rows = [
        {k: v for k, v in r.items() if k not in NOT_IN_TABLE}
        | {f"ends_{cause}": count for cause, count in r["causes"].items()}
        for r in results.values()
    ]
    table = write_csv(out_dir / TABLE_NAME, list(rows[0]), (list(row.values()) for row in rows))
    # JSON has no NaN: json writes it as NaN, and reading that back as None writes it as null.
    document = json.loads(json.dumps({**settings, "policies": rows}), parse_constant=lambda _: None)
    text = json.dumps(document, indent=2, allow_nan=False) + "\n"
    return table, write_atomically(out_dir / SETTINGS_NAME, text.encode())


def run_eval(
    cfg: DictConfig, out_dir: Path | None = None, requested: set[str] | None = None
) -> dict[str, dict]:
    """Evaluate ``cfg.checkpoint`` (or the PD controller); write the table, the plot and the video.

    Returns each policy's :func:`~drone_torchrl.evaluation.summarize` by its name in the table.
    ``out_dir``: where the files go (default: the Hydra job's folder, else the working folder);
    ``requested``: the keys the caller set (default: those of the Hydra command line). The table is
    written as :data:`TABLE_NAME` and :data:`SETTINGS_NAME` when run as ``drone-eval`` (a Hydra job
    choosing the folder); a Python call writes only the plot and video it asks for.
    """
    table = out_dir is None and HydraConfig.initialized()
    if out_dir is None:
        out_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path.cwd()
    keys = (command_line_keys() or set()) if requested is None else requested
    check_values(check_keys(cfg, "eval"), "eval")  # the keys and the bounds of conf/eval.yaml's schema
    check_device(cfg.device)
    if cfg.checkpoint is not None:
        path, checkpoint = open_agent("checkpoint", cfg.checkpoint, cfg.agent)
        try:
            run_cfg = run_config(checkpoint["config"])
            run_cfg.device = cfg.device
            validate(run_cfg, training=False)  # its values; its training's logger and memory are not ours
            check_networks("checkpoint", path, checkpoint, run_cfg)
            actor = build_actor(run_cfg).eval()
            actor.load_state_dict(checkpoint["actor"])
        except ConfigError:
            raise
        except Exception as err:  # noqa: BLE001  (not one of our checkpoints, or a damaged one)
            raise ConfigError(
                f"checkpoint={str(path)!r} cannot be used: {type(err).__name__}: {err}"
            ) from None
        kwargs = _flown_env(cfg, env_kwargs(run_cfg), path, keys)
        policies = {f"checkpoint ({path.name}, episode {checkpoint['episodes_done']})": actor}
    else:
        kwargs = env_kwargs(cfg)
        try:
            check_env_args(**kwargs)
        except ValueError as err:
            raise ConfigError(f"env.{err}") from None
        policies = {}
    policies[PD_NAME] = PDController(physics_params(kwargs))
    # Every policy's rollout is kept (for the plot), and a GIF draws every step of one episode.
    memory = memory_estimate.evaluation_parts(
        memory_estimate.FLOAT_BYTES[kwargs["dtype"]],
        len(policies) * cfg.episodes,
        kwargs["max_steps"],
        1 if cfg.video else None,
        "lower episodes or env.max_steps",
        "set video=false or lower env.max_steps",
    )
    memory_estimate.check(memory_estimate.MemoryEstimate(memory), cfg.device)
    ceiling = max_return(kwargs)
    optimum = reference_optimum(kwargs)
    best = None if optimum is None else optimum.best_return

    stats, rollouts = {}, {}
    for name, policy in policies.items():
        stats[name], rollouts[name] = evaluate(policy, kwargs, cfg.episodes, cfg.seed, cfg.device)
    pd_return = float(stats[PD_NAME]["return"].float().mean())  # summarize's return_mean of PD
    results = {name: {"policy": name, **summarize(s, ceiling, best, pd_return)} for name, s in stats.items()}
    console.info(f"{cfg.episodes} deterministic episodes, seed {cfg.seed}, env {kwargs}")
    console.info(optimum_line(kwargs, optimum, ceiling))
    for name, r in results.items():
        vs_optimum = "" if best is None else f"{r['pct_of_optimum']:.1f}% of the optimum {best:.0f}, "
        causes = ", ".join(f"{k} {v}" for k, v in r["causes"].items() if v)
        console.info(
            f"{name}: return {r['return_mean']:.1f} +- {r['return_std']:.1f} "
            f"({r['pct_of_max']:.1f}% of {ceiling:.0f}, {vs_optimum}{r['pct_of_pd']:.1f}% of PD), length {r['length_mean']:.1f}, "
            f"time in zone {100 * r['time_in_zone']:.1f}%, first in the zone at step {r['first_zone_step_mean']:.1f} "
            f"(reached in {100 * r['reached_fraction']:.0f}%), thrust mean {r['thrust_mean']:.3f} max {r['thrust_max']:.3f} "
            f"x weight, negative thrust {100 * r['negative_thrust_fraction']:.1f}%; "
            f"episode ends: {causes} (NONE = truncated; the others are crashes)"
        )
    if table:
        settings = {"checkpoint": None if cfg.checkpoint is None else str(path)}
        settings |= {key: cfg[key] for key in ("agent", "episodes", "seed", "device")}
        settings |= {"env": kwargs, "ceiling": ceiling, "optimum": best, "pd_return": pd_return}
        csv_file, json_file = write_table(out_dir, results, settings)
        console.info(f"wrote {csv_file} and {json_file}")
    main_name = next(iter(policies))
    if cfg.plot:
        plot = plot_trajectory(rollouts[main_name], out_dir / PLOT_NAME, main_name, physics_params(kwargs))
        console.info(f"plot: {plot}")
    if cfg.video:
        frames = record_video(policies[main_name], kwargs, cfg.seed, cfg.device)
        console.info(f"video: {save_gif(frames, out_dir / VIDEO_NAME, cfg.video_fps)}")
    return results
