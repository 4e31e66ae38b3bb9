"""``drone-train``: REINFORCE on the 2D drone, configured by Hydra (``conf/``).

drone-train                                  # the paper: alpha 1e-4, gamma 0.99, 6000 episodes
drone-train algo.lr=3e-4 seed=1              # any key from the command line
drone-train experiment=bounded               # positive thrust only (TanhNormal, max_thrust 1)
drone-train resume=outputs/<date>/<run>      # continue an interrupted run
"""

from __future__ import annotations

import sys
import time
from collections import deque
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm import tqdm

from drone_torchrl.checkpoint import (
    BEST,
    CHECKPOINT_DIR,
    LAST,
    load_checkpoint,
    resolve_checkpoint,
    run_dir_of,
    save_checkpoint,
)
from drone_torchrl.config import ConfigError, config_dir, env_kwargs, run_config, validate
from drone_torchrl.envs.dynamics import TerminationCause
from drone_torchrl.envs.factory import make_env
from drone_torchrl.evaluation import evaluate, write_eval_video
from drone_torchrl.metrics import EpisodeCSV, episode_stats
from drone_torchrl.modules.policy import make_actor
from drone_torchrl.objectives.reinforce import ReinforceLoss, valid_steps
from drone_torchrl.sweep import clear_failure, record_failure
from drone_torchrl.tb_logger import RunLogger, log_update
from hydra_plugins.drone_torchrl_launcher.fused_launcher import FusedLauncher

# Hydra finds launcher plugins by listing the hydra_plugins folders; an editable install's import
# hook is not a folder, so register ours explicitly (harmless for a normal install).
Plugins.instance().register(FusedLauncher)

ENGINE = "torchrl"
CSV_NAME = "episodes.csv"


def build_actor(cfg: DictConfig):
    return make_actor(
        distribution=cfg.model.distribution,
        hidden_sizes=list(cfg.model.hidden_sizes),
        activation=cfg.model.activation,
        min_std=cfg.model.min_std,
        max_thrust=cfg.env.max_thrust,
        device=cfg.device,
    )


def build_loss(cfg: DictConfig, actor) -> ReinforceLoss:
    return ReinforceLoss(
        actor,
        gamma=cfg.algo.gamma,
        discount_weight=cfg.algo.discount_weight,
        normalize_returns=cfg.algo.normalize_returns,
        baseline=cfg.algo.baseline,
    )


def _command_line_keys() -> set[str] | None:
    """Keys set on the command line of this Hydra job, or None outside a Hydra app."""
    if not HydraConfig.initialized():
        return None
    return {o.split("=", 1)[0].lstrip("+~") for o in HydraConfig.get().overrides.task}


def _prepare(cfg: DictConfig, run_dir: Path | None) -> tuple[DictConfig, Path, dict | None]:
    """Validate the config and find the checkpoint to continue from, if any.

    Returns (config to run, run folder, checkpoint or None). A run continues from a checkpoint when
    ``resume`` names one, or when its own folder already holds ``checkpoints/last.pt``: that makes
    re-running a sweep skip finished jobs and resume unfinished ones.
    """
    if run_dir is None and cfg.resume is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
    location = cfg.resume
    if location is None and (run_dir / CHECKPOINT_DIR / LAST).is_file():
        location = run_dir
    if location is None:
        validate(cfg)
        return cfg, run_dir, None
    try:
        path = resolve_checkpoint(location)
    except FileNotFoundError as err:
        raise ConfigError(f"resume={cfg.resume!r} is not allowed; {err}") from None
    checkpoint = load_checkpoint(path)
    saved = run_config(checkpoint["config"])
    # The run's own config wins. From the command line only the episode budget (to extend a run)
    # and the process settings are taken.
    keys = _command_line_keys()
    with open_dict(saved):
        if keys is None or "algo.episodes" in keys:
            saved.algo.episodes = cfg.algo.episodes
        for key in ("progress", "threads", "device"):
            saved[key] = cfg[key]
        saved.resume = cfg.resume
    validate(saved)
    return saved, run_dir_of(path), checkpoint


def train(cfg: DictConfig, run_dir: str | Path | None = None) -> float:
    """Train one agent; returns the final running-mean return (the metric sweepers optimise).

    ``run_dir`` defaults to the Hydra job's output folder; with ``resume`` set, the resumed run's.
    """
    cfg, run_dir, checkpoint = _prepare(cfg, None if run_dir is None else Path(run_dir))
    if cfg.engine == "fused":
        from drone_torchrl.fused import train_fused

        (result,) = train_fused([(cfg, run_dir)])
        if result is None:
            raise ConfigError((run_dir / "FAILED.txt").read_text().strip().splitlines()[-1])
        return result
    if checkpoint is not None and checkpoint.get("engine", ENGINE) != ENGINE:
        raise ConfigError(
            f"engine={ENGINE!r} cannot continue {run_dir}: it was written by engine={checkpoint['engine']!r}"
        )
    if checkpoint is not None and "final" in checkpoint and checkpoint["episodes_done"] >= cfg.algo.episodes:
        print(f"{run_dir}: already finished ({checkpoint['episodes_done']} episodes); nothing to do")
        return checkpoint["final"]["final_return"]
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)

    env = make_env(
        num_envs=cfg.algo.episodes_per_update,
        num_workers=cfg.env.num_workers,
        device=cfg.device,
        **env_kwargs(cfg),
    )
    env.set_seed(cfg.seed)
    actor = build_actor(cfg)
    loss_module = build_loss(cfg, actor)
    optimizer = torch.optim.Adam(actor.parameters(), lr=cfg.algo.lr, eps=cfg.algo.adam_eps)
    window = cfg.metrics.running_mean_window
    recent_returns: deque[float] = deque(maxlen=window)
    recent_lengths: deque[float] = deque(maxlen=window)
    episodes_done = updates_done = 0
    elapsed_before = 0.0
    best_eval = -float("inf")
    if checkpoint is not None:
        actor.load_state_dict(checkpoint["actor"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        episodes_done, updates_done = checkpoint["episodes_done"], checkpoint["updates_done"]
        elapsed_before, best_eval = checkpoint["wall_clock_s"], checkpoint["best_eval_return"]
        recent_returns.extend(checkpoint["recent_returns"])
        recent_lengths.extend(checkpoint["recent_lengths"])
        torch.set_rng_state(checkpoint["torch_rng"])
        if hasattr(env, "_generator"):
            env._generator.set_state(checkpoint["env_rng"])
        else:  # ParallelEnv workers own their generators: reseed deterministically instead.
            env.set_seed(cfg.seed + episodes_done)

    (run_dir / CHECKPOINT_DIR).mkdir(parents=True, exist_ok=True)
    clear_failure(run_dir)
    OmegaConf.save(cfg, run_dir / "config.yaml")
    logger = RunLogger(cfg.logger.exp_name, run_dir, purge_step=episodes_done if checkpoint else None)
    csv_file = EpisodeCSV(run_dir / CSV_NAME, keep_episodes=episodes_done if checkpoint else 0)
    show = sys.stderr.isatty() if cfg.progress == "auto" else bool(cfg.progress)
    bar = tqdm(
        total=cfg.algo.episodes, initial=episodes_done, disable=not show, unit="ep", dynamic_ncols=True
    )

    def state() -> dict:
        return {
            "engine": ENGINE,
            "actor": actor.state_dict(),
            "optimizer": optimizer.state_dict(),
            "episodes_done": episodes_done,
            "updates_done": updates_done,
            "wall_clock_s": elapsed_before + time.perf_counter() - start,
            "best_eval_return": best_eval,
            "recent_returns": list(recent_returns),
            "recent_lengths": list(recent_lengths),
            "torch_rng": torch.get_rng_state(),
            "env_rng": env._generator.get_state() if hasattr(env, "_generator") else None,
            "config": OmegaConf.to_container(cfg, resolve=True),
        }

    def run_eval() -> float:
        nonlocal best_eval
        stats, _ = evaluate(actor, env_kwargs(cfg), cfg.eval.episodes, cfg.eval.seed, cfg.device)
        mean_return = float(stats["return"].float().mean())
        logger.log_scalar("eval/return", mean_return, step=episodes_done)
        logger.log_scalar("eval/length", float(stats["length"].float().mean()), step=episodes_done)
        logger.log_scalar("eval/time_in_zone", float(stats["time_in_zone"].mean()), step=episodes_done)
        if cfg.eval.video:
            write_eval_video(actor, cfg, run_dir, episodes_done, logger)
        if cfg.checkpoint.keep_best and mean_return > best_eval:
            best_eval = mean_return
            save_checkpoint(state(), run_dir / CHECKPOINT_DIR / BEST)
        return mean_return

    start = time.perf_counter()
    next_checkpoint = episodes_done + cfg.checkpoint.every_episodes
    next_eval = episodes_done + cfg.eval.every_episodes if cfg.eval.every_episodes else None
    try:
        while episodes_done < cfg.algo.episodes:
            with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                rollout = env.rollout(cfg.env.max_steps, actor, break_when_all_done=True)
            losses = loss_module(rollout)
            optimizer.zero_grad(set_to_none=True)
            losses["loss_reinforce"].backward()
            max_norm = cfg.algo.max_grad_norm if cfg.algo.max_grad_norm is not None else float("inf")
            grad_norm = torch.nn.utils.clip_grad_norm_(actor.parameters(), max_norm)
            optimizer.step()
            updates_done += 1

            stats = episode_stats(rollout)
            wall = elapsed_before + time.perf_counter() - start
            rows = []
            for i in range(stats["return"].shape[0]):
                row = {name: stats[name][i].item() for name in stats}
                row["termination_cause"] = TerminationCause(row["termination_cause"]).name
                row.update(episode=episodes_done, update=updates_done, wall_clock_s=round(wall, 3))
                rows.append(row)
                recent_returns.append(row["return"])
                recent_lengths.append(row["length"])
                episodes_done += 1
            csv_file.write(rows)
            if updates_done % cfg.logger.every_updates == 0:
                valid, scale = valid_steps(rollout.get(("next", "done"))), rollout.get("scale")
                train_metrics = {
                    "train/loss": losses["loss_reinforce"].item(),
                    "train/grad_norm": grad_norm.item(),
                    "policy/std_mean": (scale * valid).sum().item() / (scale.shape[-1] * valid.sum().item()),
                    "train/running_mean_return": float(np.mean(recent_returns)),
                    "train/running_mean_length": float(np.mean(recent_lengths)),
                }
                log_update(logger, rows, train_metrics, step=episodes_done)
            bar.update(len(rows))
            bar.set_postfix_str(
                f"return({window})={np.mean(recent_returns):.0f} length={np.mean(recent_lengths):.0f}"
            )
            if next_eval is not None and episodes_done >= next_eval:
                run_eval()
                next_eval += cfg.eval.every_episodes
            if episodes_done >= next_checkpoint:
                csv_file.flush()
                save_checkpoint(state(), run_dir / CHECKPOINT_DIR / LAST)
                next_checkpoint += cfg.checkpoint.every_episodes
        final_eval = run_eval()
        csv_file.flush()
        final = {
            "final_return": float(np.mean(recent_returns)),
            "final_length": float(np.mean(recent_lengths)),
            "eval_return": final_eval,
            "wall_clock_s": elapsed_before + time.perf_counter() - start,
        }
        save_checkpoint({**state(), "final": final}, run_dir / CHECKPOINT_DIR / LAST)
        logger.log_final_hparams(cfg, final)
        print(
            f"{run_dir}: {episodes_done} episodes, running-mean({window}) return {final['final_return']:.1f}, "
            f"length {final['final_length']:.1f}, eval return {final_eval:.1f}, {final['wall_clock_s']:.0f} s"
        )
        return final["final_return"]
    finally:
        bar.close()
        csv_file.close()
        logger.experiment.close()
        env.close(raise_if_closed=False)


@hydra.main(config_path=config_dir(), config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    try:
        return train(cfg)
    except ConfigError as err:
        if not multirun:
            sys.exit(f"drone-train: error: {err}")
        reason = record_failure(Path(HydraConfig.get().runtime.output_dir), err)
        print(f"drone-train: job failed: {reason}", file=sys.stderr)
        return None
    except Exception as err:
        if not multirun:
            raise
        # In a sweep one failing job must not stop the others: record it, and let the sweep go on.
        reason = record_failure(Path(HydraConfig.get().runtime.output_dir), err)
        print(f"drone-train: job failed: {reason}", file=sys.stderr)
        return None


if __name__ == "__main__":
    main()
