"""Every bad input to drone-train, drone-eval, drone-report and drone-export is refused before any work.

Each row is one bad input. It must give a non-zero exit (here: a ``ConfigError``/``ReportError``
or exit code 2), a message of one line that names the offending key, flag or file, and write no
checkpoint, CSV, TensorBoard event file or figure. Most rows run in-process (the same checks the
commands run first); ``test_end_to_end`` runs a sample through the real console commands to show
that the one line reaches the terminal without a traceback. The fault tests below the tables
cover what is not a bad value: a checkpoint that carries code, a diverged run, a failed sweep, a
torn CSV row.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from test_run_folder import Disk, small_disk  # noqa: F401  (a fixture: a tmpfs to fill or make read-only)

from drone_torchrl import loggers
from drone_torchrl.apps import train as train_app
from drone_torchrl.apps.report import main as report_main
from drone_torchrl.comparison import run_eval
from drone_torchrl.config import ConfigError, check_overrides, config_dir, validate
from drone_torchrl.export import ONNX_MODULES, run_export
from drone_torchrl.io.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from drone_torchrl.io.episodes_csv import CSV_COLUMNS, read_episodes
from drone_torchrl.io.run_lock import release
from drone_torchrl.training.jobs import job_status, prepare
from drone_torchrl.training.trainer import train, train_population

# A tiny real run, resumed or evaluated by the rows that need one.
TINY = [
    "algo.episodes=2",
    "env.max_steps=20",
    "eval.episodes=1",
    "eval.video=false",
    "progress=false",
]
# ... and an algo=ppo one: a critic, and the TorchRL collector's RNG states.
PPO_TINY = [
    "algo=ppo",
    "algo.num_envs=2",
    "algo.steps_per_batch=20",
    "algo.minibatch_size=20",
    "algo.epochs=1",
]
WRITTEN = ("*.pt", "*.csv", "events.out.tfevents*", "*.gif", "*.mp4", "*.png", "*.md", "*.pt2", "*.onnx*")
# A path component no file system takes (NAME_MAX is 255 bytes on Linux's).
LONG_NAME = "x" * 300
# The ZIP local file header (APPNOTE 4.3.7): its fixed size, and where the lengths of the name and
# the extra field (16-bit little-endian) are in it; the record's bytes follow those two.
ZIP_HEADER_SIZE, ZIP_NAME_LENGTH_AT, ZIP_EXTRA_LENGTH_AT = 30, 26, 28


class Payload:
    """Unpickling this runs a command: what a crafted checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def storages(path: Path) -> dict[str, tuple[int, int]]:
    """Where each tensor storage of a checkpoint file lies: its zip record (``<archive>/data/<n>``)
    -> (offset of its first byte in the file, its size)."""
    raw = path.read_bytes()
    out = {}
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            if info.filename.rsplit("/", 2)[-2:-1] == ["data"]:
                at = info.header_offset
                name = int.from_bytes(raw[at + ZIP_NAME_LENGTH_AT : at + ZIP_NAME_LENGTH_AT + 2], "little")
                extra = int.from_bytes(raw[at + ZIP_EXTRA_LENGTH_AT : at + ZIP_EXTRA_LENGTH_AT + 2], "little")
                out[info.filename] = (at + ZIP_HEADER_SIZE + name + extra, info.file_size)
    return out


def flipped(source: Path, record: str, target: Path) -> Path:
    """A copy of ``source`` with one bit flipped in the middle of the storage ``record``: what a bad
    disk sector or a bit flip in transit does."""
    start, size = storages(source)[record]
    data = bytearray(source.read_bytes())
    data[start + size // 2] ^= 0x01
    target.write_bytes(data)
    return target


def _edited(source: Path, target: Path, edit) -> Path:
    """``source`` loaded, changed by ``edit(state)`` and saved as a checkpoint (with a digest of the
    changed tensors: what a hand-edited file or one written by a buggy tool is)."""
    state = torch.load(source, weights_only=True)
    edit(state)
    save_checkpoint(state, target)
    return target


def _put(tree, *path_and_value) -> None:
    """Set the entry at ``path`` of a nested checkpoint to ``value``; in a tensor, its first element."""
    *path, value = path_and_value
    for key in path[:-1]:
        tree = tree[key]
    if isinstance(tree[path[-1]], torch.Tensor):
        tree[path[-1]].view(-1)[0] = value
    else:
        tree[path[-1]] = value


def _snapshot(root: Path) -> dict[Path, str]:
    """Every file under ``root`` (hidden ones, .hydra/, tensorboard/ included) and its sha256."""
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


POPULATION_EXTRA = importlib.util.find_spec("pyarrow") is not None


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Fixture files: a finished tiny run (and a second one, B, with Hydra's record), files that
    are not checkpoints, and damaged or edited checkpoints."""
    root = tmp_path_factory.mktemp("inputs")
    with initialize_config_dir(config_dir(), version_base="1.3"):
        train(compose("config", overrides=TINY), root / "run")
        train(compose("config", overrides=[*TINY, "seed=1"]), root / "other")
        train(compose("config", overrides=[*TINY, *PPO_TINY]), root / "ppo")
        agents = [compose("config", overrides=[*TINY, f"seed={seed}"]) for seed in (0, 1)]
    for cfg in agents:
        validate(cfg)
    if POPULATION_EXTRA:  # hydra/launcher=population's (its rows skip without pyarrow)
        train_population(agents, ["seed=0", "seed=1"], root / "population")
    (root / "other" / ".hydra").mkdir()
    (root / "other" / ".hydra" / "overrides.yaml").write_text("- seed=1\n")
    shutil.copy(root / "other" / "config.yaml", root / "other" / ".hydra" / "config.yaml")
    (root / "other" / "train.log").write_text("[2025-01-01 00:00:00,000][HYDRA] run B\n")
    last, ppo = root / "run" / "checkpoints" / "last.pt", root / "ppo" / "checkpoints" / "last.pt"
    first_tensor = min(storages(last), key=lambda record: int(record.rsplit("/", 1)[1]))
    flipped(last, first_tensor, root / "flipped.pt")  # the actor's first weight
    for name, key, value in (("negative", "episodes_done", -5), ("fractional", "updates_done", 2.5)):
        torch.save({**torch.load(last, weights_only=True), key: value}, root / f"{name}.pt")
    torch.save({**torch.load(last, weights_only=True), "episodes_done": True}, root / "boolean.pt")
    _edited(last, root / "nan.pt", lambda s: _put(s, "actor", next(iter(s["actor"])), math.nan))
    _edited(last, root / "adam_inf.pt", lambda s: _put(s, "optimizer", "state", 0, "exp_avg_sq", math.inf))
    _edited(ppo, root / "critic_nan.pt", lambda s: _put(s, "critic", next(iter(s["critic"])), math.nan))
    _edited(last, root / "shapes.pt", lambda s: _put(s, "config", "model", "hidden_sizes", [16]))
    _edited(ppo, root / "critic_shapes.pt", lambda s: _put(s, "config", "algo", "value_hidden_sizes", [16]))
    (root / "empty.pt").write_bytes(b"")
    (root / "corrupt.pt").write_bytes(os.urandom(256))
    torch.save({"weights": torch.zeros(3)}, root / "foreign.pt")
    torch.save({"actor": Payload(root / "PWNED"), "config": {}}, root / "payload.pt")
    (root / "notes.txt").write_text("a file, not a folder\n")
    (root / "nofolder").mkdir()
    (root / "sweep").mkdir()
    (root / "sweep" / "multirun.yaml").write_text("hydra: {}\n")  # what marks a sweep's folder
    (root / "v99.pt").write_bytes(b"")
    state = torch.load(root / "run" / "checkpoints" / "last.pt", weights_only=True)
    torch.save({**state, "format_version": 99}, root / "v99.pt")
    return {
        "run": root / "run",
        "last": root / "run" / "checkpoints" / "last.pt",
        "empty": root / "empty.pt",
        "corrupt": root / "corrupt.pt",
        "foreign": root / "foreign.pt",
        "payload": root / "payload.pt",
        "v99": root / "v99.pt",
        "file": root / "notes.txt",
        "emptydir": root / "nofolder",
        "marker": root / "PWNED",
        "sweep": root / "sweep",
        "best": root / "run" / "checkpoints" / "best.pt",
        "other": root / "other",
        "ppo": root / "ppo",
        "population": root / "population",
        "long": root / LONG_NAME,
        **{name: root / f"{name}.pt" for name in DAMAGED},
    }


# Damaged or edited checkpoints of the fixture (see files()): name -> what the refusal must name.
DAMAGED = {
    "flipped": "flipped.pt",  # one bit of the actor's first weight
    "negative": "episodes_done=-5",
    "fractional": "updates_done=2.5",
    "boolean": "episodes_done=true",
    "nan": "nan.pt",  # a NaN in the actor
    "adam_inf": "adam_inf.pt",  # an inf among Adam's moments
    "critic_nan": "critic_nan.pt",  # a NaN in PPO's critic
    "shapes": "module.0.module.shared.0.weight",  # a config whose model.hidden_sizes the weights are not
    "critic_shapes": "critic/module.0.weight",  # ... whose algo.value_hidden_sizes
}


def _needs_missing_extra(args: list[str]) -> bool:
    """A row on the population run's fixture where pyarrow (the population extra) is not installed."""
    return not POPULATION_EXTRA and any("{population}" in a for a in args)


def _fill(args: list[str], files: dict[str, Path]) -> list[str]:
    if _needs_missing_extra(args):
        pytest.skip("the population run's fixture needs pyarrow: pip install 'drone_torchrl[population]'")
    return [a.format(**{k: str(v) for k, v in files.items()}) for a in args]


def _written(root: Path) -> set[Path]:
    return {p for pattern in WRITTEN for p in root.rglob(pattern)}


def _one_line(message: str, names: str) -> None:
    assert "\n" not in message.strip(), message
    assert "Traceback" not in message, message
    assert names in message, f"{names!r} not in {message!r}"


# ------------------------------------------------------------------------------------- drone-train
def MLFLOW_OR(names: str) -> str:  # noqa: N802  (read as a constant in the tables)
    """What a logger=mlflow row's message names: ``names``, or the extra when MLflow is not installed."""
    return names if importlib.util.find_spec("mlflow") is not None else "drone_torchrl[mlflow]"


# (overrides, what the message must name)
TRAIN = [
    # what Hydra's override grammar cannot parse (was Hydra's multi-line message)
    (["algo.lr=[1,"], "algo.lr"),
    (["algo.lr=${{oops"], "algo.lr"),
    (["model.hidden_sizes=[32,"], "model.hidden_sizes"),
    # the optimiser
    (["algo.lr=0"], "algo.lr"),
    (["algo.lr=-1e-4"], "algo.lr"),
    (["algo.lr=abc"], "algo.lr"),
    (["algo.lr=1e30"], "algo.lr"),  # was accepted and diverged into NaN weights
    (["algo.lr=1.5"], "algo.lr"),
    (["algo.lr=nan"], "algo.lr"),
    (["algo.lr=inf"], "algo.lr"),
    (["algo.lr=null"], "algo.lr"),
    (["algo.gamma=1.5"], "algo.gamma"),
    (["algo.gamma=-0.1"], "algo.gamma"),
    (["algo.gamma=abc"], "algo.gamma"),
    (["algo.gamma=null"], "algo.gamma"),
    (["algo.episodes=0"], "algo.episodes"),
    (["algo.episodes=-5"], "algo.episodes"),
    (["algo.episodes=1.5"], "algo.episodes"),
    (["algo.episodes=10", "algo.episodes_per_update=4"], "algo.episodes"),
    (["algo.episodes_per_update=0"], "algo.episodes_per_update"),
    (["algo.episodes_per_update=true"], "algo.episodes_per_update"),
    (["algo.adam_eps=0"], "algo.adam_eps"),
    (["algo.adam_eps=2"], "algo.adam_eps"),
    (["algo.optimizer=sgd"], "algo.optimizer"),
    (["algo.log_prob_reduction=max"], "algo.log_prob_reduction"),
    (["algo.weight_decay=-1"], "algo.weight_decay"),
    (["algo.weight_decay=5"], "algo.weight_decay"),
    (["algo.max_grad_norm=0"], "algo.max_grad_norm"),
    (["algo.max_grad_norm=-1"], "algo.max_grad_norm"),
    (["algo.baseline=critic"], "algo.baseline"),
    (["algo.discount_weight=off"], "algo.discount_weight"),
    (["algo.discount_weight=1"], "algo.discount_weight"),
    (["algo.normalize_returns=yes"], "algo.normalize_returns"),
    (["algo.normalize_returns=no"], "algo.normalize_returns"),
    # the policy
    (["model.distribution=beta"], "model.distribution"),
    (["model.distribution=tanh_normal"], "model.distribution"),  # needs env.max_thrust
    (["model.activation=sigmoid"], "model.activation"),
    (["model.min_std=-1"], "model.min_std"),
    (["model.distribution_eps=-1e-6"], "model.distribution_eps"),
    (["model.distribution_eps=0.5"], "model.distribution_eps"),  # above its bound, 1e-2
    (["model.distribution_eps=nan"], "model.distribution_eps"),
    (["model.distribution_eps=inf"], "model.distribution_eps"),
    (["model.distribution_eps=tiny"], "model.distribution_eps"),
    (["model.distribution_eps=true"], "model.distribution_eps"),
    (["model.hidden_sizes=32"], "model.hidden_sizes"),
    (["model.hidden_sizes=[]"], "model.hidden_sizes"),
    (["model.hidden_sizes=[0]"], "model.hidden_sizes"),
    (["model.hidden_sizes=[32,-1]"], "model.hidden_sizes"),
    (["model.hidden_sizes=[a]"], "model.hidden_sizes"),
    (["model.hidden_sizes=[1.5]"], "model.hidden_sizes"),
    # the env
    (["env.mass=0"], "env.mass"),
    (["env.mass=-1"], "env.mass"),
    (["env.gravity=0"], "env.gravity"),  # thrust is a fraction of the weight: nothing moves
    (["env.gravity=-9.81"], "env.gravity"),
    (["env.gravity=1000"], "env.gravity"),
    (["env.dt=0"], "env.dt"),
    (["env.dt=-0.02"], "env.dt"),
    (["env.dt=10"], "env.dt"),
    (["env.max_steps=0"], "env.max_steps"),
    (["env.max_steps=1.5"], "env.max_steps"),
    # Equal to values other rows validate (20, 1.0), but a float and a bool: the env check's cache
    # must not take them for those.
    (["env.max_steps=20.0"], "env.max_steps"),
    (["env.mass=true"], "env.mass"),
    (["env.reset_mode=sky"], "env.reset_mode"),
    (["env.reset_mode=null"], "env.reset_mode"),
    (["env.max_thrust=0"], "env.max_thrust"),
    (["env.max_thrust=-1"], "env.max_thrust"),
    (["env.max_thrust=abc"], "env.max_thrust"),
    (["env.floor_tolerance=-1"], "env.floor_tolerance"),
    (["env.floor_tolerance=100"], "env.floor_tolerance"),
    (["env.motor_distance=0"], "env.motor_distance"),
    # the arena: the zone inside the domain, each range the right way round, sizes positive
    (["env.zone_x_limit=3.0"], "env.zone_x_limit"),  # wider than the domain (x_limit 2)
    (["env.x_limit=0.5"], "env.zone_x_limit"),  # a domain narrower than the zone
    (["env.zone_x_limit=0"], "env.zone_x_limit"),
    (["env.zone_x_limit=-0.6"], "env.zone_x_limit"),
    (["env.x_limit=0"], "env.x_limit"),
    (["env.x_limit=inf"], "env.x_limit"),
    (["env.z_min=4.0"], "env.z_max"),  # z_min >= z_max
    (["env.z_max=-1"], "env.z_max"),
    (["env.z_min=abc"], "env.z_min"),
    (["env.zone_z_min=3.2"], "env.zone_z_max"),  # an empty zone: zone_z_min >= zone_z_max
    (["env.zone_z_min=3.5", "env.zone_z_max=3.0"], "env.zone_z_max"),
    (["env.zone_z_max=4.5"], "env.zone_z_max"),  # above the ceiling
    (["env.zone_z_min=-0.5"], "env.zone_z_min"),  # below the floor
    (["env.z_max=3.0"], "env.zone_z_max"),  # a ceiling through the zone
    (["env.alpha_limit=0"], "env.alpha_limit"),
    (["env.alpha_limit=4"], "env.alpha_limit"),  # past pi
    (["env.alpha_limit=null"], "env.alpha_limit"),
    (["env.bounds=open"], "env.bounds"),
    (["env.bounds=true"], "env.bounds"),
    (["env.dtype=float16"], "env.dtype"),
    (["env.dtype=double"], "env.dtype"),
    (["env.dtype=64"], "env.dtype"),
    # disturbances (conf/disturbance/, drone_torchrl/envs/disturbances.py)
    (["disturbance=gale"], "disturbance"),
    (["env.disturbance.wind=-0.1"], "env.disturbance.wind"),
    (["env.disturbance.mass=0.95"], "env.disturbance.mass"),  # a drone of 5% of its mass
    (["env.disturbance.motor_gain=1"], "env.disturbance.motor_gain"),  # a dead motor
    (["env.disturbance.gust_time=0"], "env.disturbance.gust_time"),
    (["env.disturbance.action_delay=1.5"], "env.disturbance.action_delay"),
    (["env.disturbance.observed_actions=26"], "env.disturbance.observed_actions"),
    (["env.disturbance.noise_angle=nan"], "env.disturbance.noise_angle"),
    (["env.disturbance.gusts=0.1"], "env.disturbance.gust"),  # did you mean
    (["env.num_workers=-1"], "env.num_workers"),
    (["env.num_workers=2"], "env.num_workers"),  # backend=fast has no worker processes
    (["backend=reference", "env.num_workers=3", "algo.episodes_per_update=2"], "env.num_workers"),
    # the process
    (["backend=jax"], "backend"),
    (["seed=-1"], "seed"),
    (["seed=1.5"], "seed"),
    (["seed=abc"], "seed"),
    (["seed=18446744073709551616"], "seed"),  # beyond 64 bits: was a traceback
    (["seed=9223372036854775808"], "seed"),
    (["threads=0"], "threads"),
    (["threads=abc"], "threads"),
    (["device=cuda:0" if not torch.cuda.is_available() else "device=cuda:999"], "device"),
    (["device=tpu"], "device"),
    (["device=mps"], "device"),  # a torch device this code does not run on: was a traceback
    (["device=meta"], "device"),
    (["progress=sometimes"], "progress"),
    # checkpoints, evaluation, metrics, logging
    (["checkpoint.every_episodes=0"], "checkpoint.every_episodes"),
    (["checkpoint.every_episodes=abc"], "checkpoint.every_episodes"),
    (["checkpoint.keep_best=no"], "checkpoint.keep_best"),
    (["eval.every_episodes=-1"], "eval.every_episodes"),
    (["eval.every_episodes=1.5"], "eval.every_episodes"),
    (["eval.episodes=0"], "eval.episodes"),
    (["eval.seed=-1"], "eval.seed"),
    (["eval.video=off"], "eval.video"),
    (["metrics.running_mean_window=0"], "metrics.running_mean_window"),
    (["logger.video_fps=0"], "logger.video_fps"),
    (["logger.video_stride=0"], "logger.video_stride"),
    (["logger.every_updates=0"], "logger.every_updates"),
    (["logger.flush_every_s=-1"], "logger.flush_every_s"),
    # Keys removed with the one value every run had (drone_torchrl.migrations.FIXED): another is refused
    (["metrics.running_mean_window=50"], "metrics.running_mean_window"),
    (["logger.video_fps=30"], "logger.video_fps"),
    (["metrics.running_mean_window=5,10"], "metrics.running_mean_window"),  # a sweep of it
    (["logger.exp_name=null"], "logger.exp_name"),  # was a traceback
    (["logger.exp_name=../../outside"], "logger.exp_name"),  # wrote outside the run folder
    (["logger.exp_name=/tmp/abs"], "logger.exp_name"),
    (["logger.exp_name=''"], "logger.exp_name"),
    (["logger.exp_name=episodes.csv"], "logger.exp_name"),  # collided with the run's CSV mid-run
    (["logger.exp_name=checkpoints"], "logger.exp_name"),
    (["sweep_name=../../escape"], "sweep_name"),  # a sweep written outside the working folder
    (["threads=100000"], "threads"),  # was a segfault
    (["eval.episodes=100000000"], "eval.episodes"),  # was out of memory after training
    (["algo.episodes_per_update=100000", "algo.episodes=100000"], "algo.episodes_per_update"),
    (["~algo.lr"], "algo.lr"),  # a deleted key: was a traceback
    (["algo.lr=${{oops}}"], "algo.lr"),  # an interpolation to nothing: was a traceback
    (["logger.exp_name=???"], "logger.exp_name"),  # a missing value
    (["algo.lr=???"], "algo.lr"),
    # PPO (algo=ppo)
    (["algo=ppo", "algo.minibatch_size=1000"], "algo.minibatch_size"),  # must divide 64 x 64
    (["algo=ppo", "algo.num_envs=0"], "algo.num_envs"),
    (["algo=ppo", "algo.steps_per_batch=0"], "algo.steps_per_batch"),
    (["algo=ppo", "algo.epochs=0"], "algo.epochs"),
    (["algo=ppo", "algo.clip_epsilon=0"], "algo.clip_epsilon"),
    (["algo=ppo", "algo.target_kl=0"], "algo.target_kl"),
    (["algo=a2c", "algo.target_kl=0.01"], "algo.target_kl"),
    (["algo=ppo", "algo.dual_clip=1"], "algo.dual_clip"),
    (["algo=ppo", "algo.dual_clip=0.5"], "algo.dual_clip"),
    (["algo=ppo", "algo.dual_clip=high"], "algo.dual_clip"),
    # eval.stop_return ends a run at a periodic evaluation: none, nothing would stop it.
    (["eval.stop_return=2685", "eval.every_episodes=0"], "eval.stop_return"),
    (["eval.stop_return=high"], "eval.stop_return"),
    (["eval.stop_return=[2685]"], "eval.stop_return"),
    # eval.rollback_drop acts at a periodic evaluation, on an on-policy learner's state.
    (["algo=ppo", "eval.rollback_drop=1000", "eval.every_episodes=0"], "eval.rollback_drop"),
    (["algo=ppo", "eval.rollback_drop=0"], "eval.rollback_drop"),
    (["eval.rollback_drop=1000"], "eval.rollback_drop"),  # algo=reinforce: its learner has none
    (["experiment=bounded", "algo=sac", "eval.rollback_drop=1000"], "eval.rollback_drop"),
    (["algo=ppo", "algo.gae_lambda=2"], "algo.gae_lambda"),
    (["algo=ppo", "algo.critic_coeff=0"], "algo.critic_coeff"),
    (["algo=ppo", "algo.reward_scale=-1"], "algo.reward_scale"),
    (["algo=ppo", "algo.value_hidden_sizes=[]"], "algo.value_hidden_sizes"),
    (["algo=ppo", "algo.anneal_lr=off"], "algo.anneal_lr"),
    (["algo=ppo", "env.num_workers=2"], "env.num_workers"),
    (["algo=ppo", "+algo.baseline=mean"], "algo.baseline"),  # a REINFORCE key: not PPO's
    (["algo=ppo", "algo.lr=2"], "algo.lr"),
    # A2C (algo=a2c): the on-policy keys; PPO's clipping is not among them
    (["algo=a2c", "algo.num_envs=0"], "algo.num_envs"),
    (["algo=a2c", "algo.minibatch_size=1000"], "algo.minibatch_size"),
    (["algo=a2c", "algo.clip_epsilon=0.1"], "algo.clip_epsilon"),
    (["algo=a2c", "algo.loss_critic_type=huber"], "algo.loss_critic_type"),
    (["algo=a2c", "algo.advantage_scaling=whiten"], "algo.advantage_scaling"),
    (["algo=a2c", "algo.critic_max_grad_norm=0"], "algo.critic_max_grad_norm"),
    # SAC (algo=sac, bounded thrust only)
    (["experiment=bounded", "algo=sac", "algo.buffer_size=1000000000000"], "algo.buffer_size"),  # > memory
    (["experiment=bounded", "algo=sac", "algo.buffer_size=500", "algo.batch_size=600"], "algo.batch_size"),
    (["experiment=bounded", "algo=sac", "algo.buffer_size=0"], "algo.buffer_size"),
    (["experiment=bounded", "algo=sac", "backend=reference"], "backend"),
    (["algo=sac"], "model.distribution"),  # the default Normal head: unbounded thrust
    (["experiment=bounded", "algo=sac", "algo.tau=0"], "algo.tau"),
    (["experiment=bounded", "algo=sac", "algo.tau=1.5"], "algo.tau"),
    (["experiment=bounded", "algo=sac", "algo.updates_per_batch=0"], "algo.updates_per_batch"),
    (["experiment=bounded", "algo=sac", "algo.alpha_init=0"], "algo.alpha_init"),
    (["experiment=bounded", "algo=sac", "algo.target_entropy=abc"], "algo.target_entropy"),
    (["experiment=bounded", "algo=sac", "algo.qvalue_hidden_sizes=[]"], "algo.qvalue_hidden_sizes"),
    (["experiment=bounded", "algo=sac", "env.num_workers=2"], "env.num_workers"),
    (["experiment=bounded", "algo=sac", "algo.minibatch_size=64"], "algo.minibatch_size"),  # PPO's key
    (["experiment=bounded", "algo=sac", "algo.n_steps=0"], "algo.n_steps"),
    (["experiment=bounded", "algo=sac", "algo.n_steps=21"], "algo.n_steps"),  # > env.max_steps (TINY's 20)
    (
        ["experiment=bounded", "algo=sac", "algo.n_steps=3", "algo.gamma=0"],
        "algo.gamma",
    ),  # MultiStep raises at gamma 0
    (["algo.name=dqn"], "algo.name"),
    # logger plug-ins: a backend's own key, and another backend's
    (["logger=csv", "logger.float_format=abc"], "logger.float_format"),
    (["logger=csv", "logger.float_format='%d %d'"], "logger.float_format"),
    (["logger.float_format='%.3g'"], "logger.float_format"),  # logger=csv's key, not tensorboard's
    (["logger=wandb", "logger.mode=cloud"], "logger.mode"),  # its schema's: refused with or without W&B
    (["logger=wandb", "logger.project=''"], "logger.project"),
    (["logger=wandb", "logger.project=null"], "logger.project"),
    (["logger.project=drone"], "logger.project"),  # logger=wandb's key, not tensorboard's
    (["logger.backend='no such-backend'"], "logger.backend"),  # a name no plug-in can be registered as
    # a plug-in is chosen with its group: its name key alone said another key was "missing"
    (["algo.name=ppo"], "algo=ppo"),
    (["logger.backend=csv"], "logger=csv"),
    (["model.init_std=0"], "model.init_std"),
    (["model.init_std=-1"], "model.init_std"),
    # keys and groups that do not exist
    (["+algo.lrr=1"], "algo.lr"),  # was accepted silently; the hint names the real key
    (["+foo=1"], "foo"),
    (["algo.lrr=1"], "algo.lr"),
    (["algoo=ppo"], "did you mean algo=a2c|ppo|"),  # a group misspelt: was "did you mean algo.lr?"
    (["+model.hidden=[8]"], "model.hidden"),
    (["experiment=nope"], "experiment"),
    (["algo=ppo2"], "algo"),
    (["hydra.run.dir={file}"], "hydra.run.dir"),  # a run folder that is a file: was a traceback
    (["hydra.run.dir={file}/run"], "hydra.run.dir"),  # under a file: was a traceback
    (["hydra.run.dir=''"], "hydra.run.dir"),  # wrote the run into the current folder
    # resume targets
    (["resume={emptydir}/nothing"], "resume"),
    (["resume={emptydir}"], "resume"),  # a folder without checkpoints/last.pt
    # A population run's checkpoint: which agent to continue (0 or 1); agent=K of one run's checkpoint.
    (["resume={population}"], "agent=null is not allowed"),
    (
        ["resume={population}", "algo.episodes=4"],
        "to train the whole population on, run its sweep's command again",
    ),
    (["resume={population}", "agent=2"], "agent"),
    (["resume={population}", "agent=-1"], "agent"),
    (["resume={run}", "agent=0"], "agent"),
    (["resume={empty}"], "empty.pt"),
    (["resume={corrupt}"], "corrupt.pt"),
    (["resume={foreign}"], "foreign.pt"),
    (["resume={payload}"], "payload.pt"),
    (["resume={v99}"], "format_version"),
    (["resume={file}"], "notes.txt"),
    (["resume=true"], "resume"),  # not a path: was a traceback
    (["resume=1"], "resume"),
    (["resume=''"], "resume"),
    # a continued run keeps its hyper-parameters (only the budget and logging may change)
    (["resume={run}", "algo.lr=0.5"], "algo.lr"),
    (["resume={run}", "algo.gamma=0.9"], "algo.gamma"),
    (["resume={run}", "backend=reference"], "backend"),
    (["resume={run}", "experiment=bounded"], "model.distribution"),
    (["resume={last}", "env.max_steps=300"], "env.max_steps"),
    # A fork into another run's folder: overwrote run B (its checkpoints, CSV, config; issue 34).
    (["resume={best}", "hydra.run.dir={other}"], "hydra.run.dir"),
    (["resume={best}", "hydra.run.dir={run}"], "hydra.run.dir"),  # into its own parent
    # Checkpoints that are damaged or hold what no run saves (each was loaded, flown or trained on).
    *[([f"resume={{{name}}}"], names) for name, names in DAMAGED.items()],
    # Names the file system refuses (ENAMETOOLONG tracebacks).
    (["hydra.run.dir={long}"], "hydra.run.dir"),
    (["hydra.run.dir={long}/run"], "hydra.run.dir"),
    ([f"logger.exp_name={LONG_NAME}"], "logger.exp_name"),
    ([f"sweep_name={LONG_NAME}"], "sweep_name"),
    (["resume={long}"], "resume"),
    # Issue 34, the config side. A preset made for one algorithm, with another (was Hydra's
    # ConfigKeyError in several lines); experiment=paper_code takes any algorithm (test_paper_code.py).
    (["experiment=hover_optimal", "algo=reinforce"], "experiment=bounded algo=reinforce"),
    (["experiment=hover_optimal", "algo=reinforce_plus"], "experiment=bounded algo=reinforce_plus"),
    (["experiment=randomised", "algo=reinforce"], "experiment=bounded algo=reinforce"),
    (["experiment=randomised", "algo=a2c"], "experiment=bounded algo=a2c"),  # was accepted silently
    (["experiment=hover_optimal", "algo=a2c"], "experiment=bounded algo=a2c"),
    # A config section (or Hydra group) set to null, a scalar or a list, or deleted (was Hydra's
    # merge error in several lines, or a traceback for hydra/launcher)
    (["env.disturbance=null"], "env.disturbance"),
    (["env.disturbance=5"], "env.disturbance"),
    (["env.disturbance=[]"], "env.disturbance"),
    (["env.disturbance={{gale:1}}"], "env.disturbance.gale"),
    (["eval=null"], "eval"),
    (["checkpoint=5"], "checkpoint"),
    (["metrics=[]"], "metrics"),
    (["~env.disturbance"], "env.disturbance"),
    (["~algo"], "algo"),
    (["hydra/launcher=null"], "hydra/launcher"),
    (["hydra/sweeper=[]"], "hydra/sweeper"),
    (["algo=null"], "algo"),
    (["model=3"], "model"),
    (["logger=[]"], "logger"),
    # Numbers no float32 holds, and physical bounds (were overflow tracebacks, NaN "diverged" runs
    # that blamed algo.lr, or episodes that ended at their first step)
    (["env.max_thrust=1e300"], "env.max_thrust"),
    (["env.mass=1e300"], "env.mass"),
    (["env.mass=1e-40"], "env.mass"),
    (["env.motor_distance=1e-30"], "env.motor_distance"),
    (["env.x_limit=1e300"], "env.x_limit"),
    (["env.z_min=-1e300"], "env.z_min"),
    (["env.disturbance.wind=1e300"], "env.disturbance.wind"),
    (["env.disturbance.noise_angle=1e300"], "env.disturbance.noise_angle"),
    (["env.disturbance.motor_lag=1e300"], "env.disturbance.motor_lag"),
    (["model.min_std=1e300"], "model.min_std"),
    (["algo.max_grad_norm=1e300"], "algo.max_grad_norm"),
    (["algo=ppo", "algo.reward_scale=1e39"], "algo.reward_scale"),
    (["algo.lr=1" + "0" * 400], "algo.lr"),  # an int no float holds: was an OverflowError traceback
    # Counts no int64 holds (were accepted)
    (["algo.episodes=99999999999999999999"], "algo.episodes"),
    (["env.max_steps=99999999999999999999"], "env.max_steps"),
    (["checkpoint.every_episodes=99999999999999999999"], "checkpoint.every_episodes"),
    (["metrics.running_mean_window=99999999999999999999"], "metrics.running_mean_window"),
    # Sizes no memory holds (were an allocator traceback after start-up, or the process killed)
    (["algo=ppo", "algo.steps_per_batch=1000000000"], "algo.steps_per_batch"),
    (["model.hidden_sizes=[1000000,1000000]"], "model.hidden_sizes"),
    (["env.max_steps=1000000000000", "eval.video=false"], "env.max_steps"),
    (["eval.episodes=10000", "env.max_steps=1000000000", "eval.video=false"], "eval.episodes"),
    (["eval.video=true", "env.max_steps=1000000000"], "eval.video=false"),  # its frames
    # MLflow (without the extra: refused naming it)
    (["logger=mlflow", "logger.tracking_uri=foo://bar"], MLFLOW_OR("logger.tracking_uri")),
    (
        ["logger=mlflow", "logger.tracking_uri=sqlite:///{emptydir}/missing/x.db"],
        MLFLOW_OR("logger.tracking_uri"),
    ),
]


@pytest.mark.parametrize(("overrides", "names"), TRAIN, ids=[" ".join(o) for o, _ in TRAIN])
def test_drone_train_refuses(overrides, names, files, tmp_path):
    overrides = TINY + _fill(overrides, files)
    # The job's folder: hydra.run.dir's, as in the command, else a new one.
    run_dir = next((Path(o.split("=", 1)[1]) for o in overrides if o.startswith("hydra.run.dir=")), None)
    before = _snapshot(files["run"].parent)
    with pytest.raises(ConfigError) as info:
        check_overrides(overrides)
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("config", overrides=overrides)
        prepare(cfg, run_dir or tmp_path / "job", requested=overrides)
    _one_line(str(info.value), names)
    assert not (tmp_path / "job").exists()
    assert _snapshot(files["run"].parent) == before  # byte for byte: nothing written, nothing lost
    assert not files["marker"].exists()


@pytest.mark.parametrize(
    ("override", "choose"),
    [("algo.name=ppo", "algo=ppo"), ("algo.name=a2c", "algo=a2c"), ("logger.backend=csv", "logger=csv")],
)
def test_a_plugin_is_chosen_with_its_group_not_its_name_key(override, choose):
    """``algo.name=ppo`` kept REINFORCE's keys and named one of PPO's as missing; the one line now says
    what to type instead."""
    with pytest.raises(ConfigError) as info:
        check_overrides([override])
    _one_line(str(info.value), choose)
    assert str(info.value).startswith(override.split("=")[0])


@pytest.mark.parametrize("backend", [b for b in loggers.BACKENDS.names() if loggers.get(b).extra])
def test_a_logger_whose_extra_is_missing_is_one_line(backend, monkeypatch, tmp_path):
    """Refused before any work, naming the extra (``logger=mlflow`` failed when its run started)."""
    import importlib.util

    extra = loggers.get(backend).extra
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == extra else find_spec(name, *a)
    )
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, f"logger={backend}"])
    with pytest.raises(ConfigError) as info:
        prepare(cfg, tmp_path / "job")
    _one_line(str(info.value), f"pip install 'drone_torchrl[{extra}]'")
    assert not (tmp_path / "job").exists()


# -------------------------------------------------------------------------------------- drone-eval
EVAL = [
    (["env.max_thrust=1e300"], "env.max_thrust"),
    (["env.mass=1e-40"], "env.mass"),
    (["env.max_steps=1000000000000"], "env.max_steps"),  # its rollouts: no memory holds them
    (["video=true", "env.max_steps=1000000000"], "video=false"),  # its GIF's frames
    (["env.disturbance=null"], "env.disturbance"),
    (["disturbance=gale"], "disturbance"),
    (["env.disturbance.motor_lag=-0.02"], "env.disturbance.motor_lag"),
    (["checkpoint={emptydir}/nothing"], "checkpoint"),
    (["checkpoint={emptydir}"], "checkpoint"),
    (["checkpoint={empty}"], "empty.pt"),
    (["checkpoint={corrupt}"], "corrupt.pt"),
    (["checkpoint={foreign}"], "foreign.pt"),
    (["checkpoint={payload}"], "payload.pt"),
    (["checkpoint={v99}"], "format_version"),
    (["episodes=0"], "episodes"),
    (["episodes=-1"], "episodes"),
    (["episodes=abc"], "episodes"),
    (["episodes=100000000"], "episodes"),  # ran out of memory after minutes
    (["checkpoint=true"], "checkpoint"),  # not a path: was a traceback
    (["seed=-1"], "seed"),
    (["seed=18446744073709551616"], "seed"),
    (["device=tpu"], "device"),
    (["device=mps"], "device"),
    (["video=off"], "video"),
    (["plot=maybe"], "plot"),
    (["video_fps=0"], "video_fps"),
    (["env.gravity=0"], "env.gravity"),
    (["env.dt=0"], "env.dt"),
    (["env.max_thrust=-1"], "env.max_thrust"),
    (["env.reset_mode=sky"], "env.reset_mode"),
    (["env.zone_x_limit=2.5"], "env.zone_x_limit"),
    (["env.zone_z_min=3.2"], "env.zone_z_max"),
    (["env.bounds=closed"], "env.bounds"),
    (["env.dtype=float16"], "env.dtype"),
    (["+foo=1"], "foo"),
    (["+episode=3"], "episodes"),
    # Damaged or edited checkpoints: flown (damaged weights silently; NaN: "thrust mean nan"), or a
    # size-mismatch traceback.
    *[([f"checkpoint={{{name}}}"], names) for name, names in DAMAGED.items()],
    (["checkpoint={long}"], "checkpoint"),  # ENAMETOOLONG tracebacks
    (["hydra.run.dir={long}"], "hydra.run.dir"),
    # A population run's checkpoint: which agent (0 or 1) to fly; agent=K of one run's checkpoint.
    (["checkpoint={population}"], "agent"),
    (["checkpoint={population}", "agent=2"], "agent"),
    (["checkpoint={population}", "agent=-1"], "agent"),
    (["checkpoint={population}", "agent=one"], "agent"),
    (["checkpoint={run}", "agent=0"], "agent"),
]


@pytest.mark.parametrize(("overrides", "names"), EVAL, ids=[" ".join(o) for o, _ in EVAL])
def test_drone_eval_refuses(overrides, names, files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    quiet = [o for o in ("video=false", "plot=false") if not overrides[0].startswith(o.split("=")[0])]
    overrides = _fill(overrides, files) + quiet
    before = _snapshot(files["run"].parent)
    with pytest.raises(ConfigError) as info:
        check_overrides(overrides, "eval")
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("eval", overrides=overrides)
        run_eval(cfg)
    _one_line(str(info.value), names)
    assert not _written(tmp_path)
    assert _snapshot(files["run"].parent) == before
    assert not files["marker"].exists()


# ------------------------------------------------------------------------------------ drone-export
EXPORT = [
    ([], "checkpoint"),  # no checkpoint named
    (["checkpoint=true"], "checkpoint"),
    (["checkpoint={emptydir}/nothing"], "checkpoint"),
    (["checkpoint={corrupt}"], "corrupt.pt"),
    (["checkpoint={payload}"], "payload.pt"),
    (["checkpoint={v99}"], "format_version"),
    (["checkpoint={run}", "format=zip"], "format"),
    (["checkpoint={run}", "format=ONNX"], "format"),
    (["checkpoint={run}", "format=true"], "format"),
    (["checkpoint={run}", "format=[onnx]"], "format"),
    (["checkpoint={run}", "format=onnx", "output=policy.pt2"], "output"),  # the suffix names the format
    (["checkpoint={run}", "format=pt2", "output=policy.onnx"], "output"),
    (["checkpoint={run}", "output=policy.zip"], "output"),  # no format to infer
    (["checkpoint={run}", "output=policy"], "output"),
    (["checkpoint={run}", "format=pt2", "output=policy"], "output"),
    (["checkpoint={run}", "output={emptydir}"], "output"),  # a folder
    (["checkpoint={run}", "output=''"], "output"),
    (["checkpoint={run}", "output=1"], "output"),
    (["checkpoint={run}", "+foo=1"], "foo"),
    (["checkpoint={run}", "formats=onnx"], "format"),  # the hint names the real key
    # Damaged or edited checkpoints: exported (damaged weights silently), or a traceback.
    *[([f"checkpoint={{{name}}}"], names) for name, names in DAMAGED.items()],
    (["checkpoint={long}"], "checkpoint"),  # ENAMETOOLONG tracebacks
    (["checkpoint={run}", "output={long}.pt2"], "output"),
    (["checkpoint={run}", "output={long}/policy.onnx"], "output"),
    (["checkpoint={population}"], "agent"),  # which agent of the population run
    (["checkpoint={population}", "agent=2"], "agent"),
    (["checkpoint={run}", "agent=0"], "agent"),
]


@pytest.mark.parametrize(("overrides", "names"), EXPORT, ids=[" ".join(o) or "none" for o, _ in EXPORT])
def test_drone_export_refuses(overrides, names, files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    overrides = _fill(overrides, files)
    before = _snapshot(files["run"].parent)
    with pytest.raises(ConfigError) as info:
        check_overrides(overrides, "export")
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("export", overrides=overrides)
        run_export(cfg)
    _one_line(str(info.value), names)
    assert list(tmp_path.iterdir()) == []
    assert _snapshot(files["run"].parent) == before
    assert not files["marker"].exists()


# ------------------------------------------------------------------------------------ drone-report
def _sweep(root: Path, config: str | bytes | None = "seed: 0\n", csv: str | None = None) -> Path:
    job = root / "sweep" / "seed=0"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
    if config is not None:
        (job / "config.yaml").write_bytes(config if isinstance(config, bytes) else config.encode())
    (job / "episodes.csv").write_text(csv if csv is not None else "episode,return\n0,1\n")
    return root / "sweep"


VALID_CSV = ",".join(CSV_COLUMNS) + "\n0,0,300.0,300,0.0,0.0,NONE,1.0\n"
REPORT = [
    (lambda r, f: [str(r / "missing")], "missing"),
    (lambda r, f: [str(f["file"])], "notes.txt"),
    (lambda r, f: [str(f["emptydir"])], "nofolder"),  # no job folders
    (lambda r, f: [str(f["run"].parent), "--window", "0"], "--window"),
    (lambda r, f: [str(f["run"].parent), "--window", "-3"], "--window"),
    (lambda r, f: [str(f["run"].parent), "--window", "abc"], "--window"),
    (lambda r, f: [str(f["run"].parent), "--return-threshold", "abc"], "--return-threshold"),
    (lambda r, f: [str(f["run"].parent), "--return-threshold", "nan"], "--return-threshold"),
    (lambda r, f: [str(f["run"].parent), "--return-threshold", "inf"], "--return-threshold"),
    (lambda r, f: [str(f["run"].parent), "--out", str(f["file"])], "--out"),
    (lambda r, f: [], "sweeps"),
    (lambda r, f: [str(f["run"].parent), "--bogus"], "--bogus"),
    (lambda r, f: [str(_sweep(r, csv=VALID_CSV)), str(r / "missing")], "missing"),  # checked before any work
    (lambda r, f: [str(_sweep(r, config="a: [1, 2\n"))], "config.yaml"),  # malformed: was a traceback
    (lambda r, f: [str(_sweep(r, config="- a\n- b\n"))], "config.yaml"),
    (lambda r, f: [str(_sweep(r, config=None))], "config.yaml"),
    (lambda r, f: [str(_sweep(r))], "episodes.csv"),  # lacks columns
    (lambda r, f: [str(f["run"].parent), "--out", ""], "--out"),  # was the current folder
    (lambda r, f: [str(f["run"].parent), "--out", "  "], "--out"),
    (lambda r, f: [str(f["run"]), "--out", str(f["long"])], "--out"),  # ENAMETOOLONG, after the work
    (lambda r, f: [str(f["run"]), "--out", str(f["long"] / "report")], "--out"),
    (lambda r, f: [str(_sweep(r, config=b"seed: 0\nnote: caf\xe9\n"))], "config.yaml"),  # not UTF-8
]


@pytest.mark.parametrize(("argv", "names"), REPORT, ids=[n + str(i) for i, (_, n) in enumerate(REPORT)])
def test_drone_report_refuses(argv, names, files, tmp_path, capsys):
    argv = argv(tmp_path, files)
    before = _snapshot(files["run"].parent)
    with pytest.raises(SystemExit) as info:
        report_main(argv)
    assert info.value.code == 2
    _one_line(capsys.readouterr().err, names)
    assert not _written(tmp_path) - {tmp_path / "sweep" / "seed=0" / "episodes.csv"}
    assert _snapshot(files["run"].parent) == before


# hydra/launcher=pbt's, halving's and pbt_replay's settings (drone_torchrl.training.pbt), by their
# hydra.launcher.search: refused when Hydra makes the launcher, before any job starts.
SEARCH_LAUNCHERS = [
    ("pbt", {"quantile": 0.6}, "hydra.launcher.quantile"),
    ("pbt", {"quantile": 0}, "hydra.launcher.quantile"),
    ("pbt", {"every_updates": 0}, "hydra.launcher.every_updates"),
    ("pbt", {"perturb": []}, "hydra.launcher.perturb"),
    ("pbt", {"perturb": [0.8, -1.2]}, "hydra.launcher.perturb"),
    ("pbt", {"resample_probability": 1.5}, "hydra.launcher.resample_probability"),
    ("pbt", {"keys": ["seed"]}, "'seed' is a per-agent key PBT cannot search"),
    ("pbt", {"keys": ["model.hidden_sizes"]}, "'model.hidden_sizes' is not a per-agent key"),
    ("pbt", {"keys": []}, "hydra.launcher.keys"),
    ("halving", {"rungs": []}, "hydra.launcher.rungs"),
    ("halving", {"rungs": [1500, 500]}, "hydra.launcher.rungs"),
    ("halving", {"rungs": [0, 5]}, "hydra.launcher.rungs"),
    ("halving", {"fraction": 1}, "hydra.launcher.fraction"),
    ("halving", {"keys": ["seed"]}, "'seed' is a per-agent key successive halving cannot search"),
    ("replay", {"run": "/nowhere"}, "hydra.launcher.run"),
    # The one launcher's own keys: a search it does not have, a key its search does not read
    ("bogus", {}, "hydra.launcher.search=bogus"),
    ([1], {}, "hydra.launcher.search=[1]"),
    ("halving", {"every_updates": 5}, "hydra.launcher.search=halving has no key 'every_updates'"),
    ("none", {"folders": "jobs"}, "hydra.launcher.folders"),
    ("pbt", {"folders": "job"}, "hydra.launcher.search=pbt"),
]


@pytest.mark.parametrize(
    ("launcher", "params", "names"), SEARCH_LAUNCHERS, ids=[f"{n}-{p}" for n, p, _ in SEARCH_LAUNCHERS]
)
def test_the_search_launchers_refuse(launcher, params, names):
    from hydra_plugins.drone_torchrl_launcher.population_launcher import PopulationLauncher

    with pytest.raises(SystemExit) as info:
        PopulationLauncher(search=launcher, **params)
    _one_line(str(info.value.code), names)
    assert str(info.value.code).startswith("drone-train: error: hydra.launcher.")


@pytest.mark.parametrize(
    ("search", "names"),
    [
        (
            {"rungs": [100, 500]},
            "hydra.launcher.rungs=[100, 500] is not allowed; expected rungs below the budget of 2 updates",
        ),
        (
            {"every_updates": 2},
            "hydra.launcher.every_updates=2 is not allowed; expected fewer than the budget's 2 updates",
        ),
    ],
)
def test_a_search_longer_than_the_budget_is_refused_before_the_folder_exists(search, names, tmp_path):
    """A rung schedule (or a PBT interval) past algo.episodes: no search step would run."""
    from drone_torchrl.training.pbt import HalvingSettings, PBTSettings

    settings = HalvingSettings.of(search) if "rungs" in search else PBTSettings.of(search)
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfgs = [compose("config", overrides=[*TINY, "backend=fast", f"seed={s}"]) for s in (0, 1)]
    with pytest.raises(ConfigError) as info:
        train_population(cfgs, ["seed=0", "seed=1"], tmp_path / "pop", search=settings)
    _one_line(str(info.value), names)
    assert not (tmp_path / "pop").exists()


def test_a_population_run_refuses_stop_return_before_the_folder_exists(tmp_path):
    """eval.stop_return ends one run early; a population's agents train their whole budget together."""
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfgs = [
            compose("config", overrides=[*TINY, "backend=fast", f"seed={s}", "eval.stop_return=100"])
            for s in (0, 1)
        ]
    with pytest.raises(ConfigError) as info:
        train_population(cfgs, ["seed=0", "seed=1"], tmp_path / "pop")
    _one_line(
        str(info.value), "eval.stop_return=100 is not allowed; expected null with hydra/launcher=population"
    )
    assert not (tmp_path / "pop").exists()


def test_the_pbt_launcher_refuses_through_the_command(tmp_path, command_here):
    """The same line reaches the terminal, and no sweep folder is made (drone-train in this process)."""
    pytest.importorskip("pyarrow")  # without it the extras check refuses first (tests/test_extras.py)
    proc = command_here(
        train_app.run, "drone-train", "-m", "hydra/launcher=pbt", "hydra.launcher.quantile=0.7", "seed=0,1",
        *TINY, f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path,
    )  # fmt: skip
    _refused(proc, "hydra.launcher.quantile=0.7", "(0, 0.5]")
    assert not (tmp_path / "sweep").exists()


# ------------------------------------------------------------------ searches and populations (issue 50)
@pytest.fixture(scope="module")
def pbt_run(tmp_path_factory) -> Path:
    """A finished tiny PBT population run (two agents, an exploit step after each update): what
    hydra/launcher=pbt_replay replays."""
    if not POPULATION_EXTRA:
        pytest.skip("a population run needs pyarrow: pip install 'drone_torchrl[population]'")
    from drone_torchrl.training.pbt import PBTSettings

    run = tmp_path_factory.mktemp("pbt") / "population_0"
    names = ["seed=0 algo.lr=0.0001", "seed=1 algo.lr=0.001"]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        agents = [compose("config", overrides=[*TINY, *name.split()]) for name in names]
    for cfg in agents:
        validate(cfg)
    search = PBTSettings.of({"every_updates": 1, "quantile": 0.5, "keys": ["algo.lr"]})
    train_population(agents, names, run, search=search)
    return run


def _drone_train(command_here, tmp_path: Path, args: list[str], pbt_run: Path | None = None):
    """``drone-train <args> <TINY>`` in this process from ``tmp_path``, its sweep in ``tmp_path/sweep``;
    ``{pbt}`` in an argument is the PBT run's folder. Flags come first, as argparse needs them."""
    args = [a.format(pbt=pbt_run) for a in args]
    sweep = [f"hydra.sweep.dir={tmp_path / 'sweep'}"] if "-m" in args else []
    return command_here(train_app.run, "drone-train", *args, *TINY, *sweep, cwd=tmp_path)


# (the command line before TINY, what its one stderr line must name). Each was a traceback, Hydra's
# message in several lines, the reason on stdout, or a command that went on (exit 0).
LAUNCHER_REFUSALS = [
    # The launcher's refusals: were on stdout, then "1 population run(s) not started (the reason is above)"
    (
        ["-m", "hydra/launcher=halving", "seed=0,1"],
        ["hydra.launcher.rungs=[500, 1500]", "below the budget of 2"],
    ),
    (
        [
            "-m",
            "hydra/launcher=pbt",
            "seed=0,1",
            "hydra.launcher.every_updates=2",
            "hydra.launcher.quantile=0.5",
        ],
        ["hydra.launcher.every_updates=2", "fewer than the budget's 2 updates"],
    ),
    (["-m", "hydra/launcher=population", "algo=ppo", "seed=0,1"], ["algo=ppo", "algo=reinforce"]),
    # A search or population launcher without -m: trained a plain run (exit 0)
    (["hydra/launcher=pbt", "hydra.launcher.every_updates=0"], ["hydra/launcher=pbt", "-m"]),
    (["hydra/launcher=population"], ["hydra/launcher=population", "-m"]),
    # Tracebacks
    (
        ["-m", "hydra/launcher=pbt", "hydra.launcher.keys=[algo.lr,algo.lr]", "algo.lr=1e-4,1e-3", "seed=0"],
        ["hydra.launcher.keys", "each key once"],
    ),
    (["--cfg", "job", "-m", "hydra/launcher=pbt", "seed=0,1"], ["--cfg", "-m"]),
    (["--info", "-m", "hydra/launcher=pbt", "seed=0,1"], ["--info", "-m"]),
    (["--cfg", "job", "algo.lr=1e-4,1e-3"], ["algo.lr=1e-4,1e-3", "-m"]),  # Hydra's ambiguous value
    (
        ["--cfg", "job", "hydra/launcher=pbt", "algo.lr=interval(1e-4,1e-3)"],
        ["algo.lr=interval(1e-4,1e-3)", "-m"],
    ),
    # Hydra's multi-line errors, or accepted silently (+)
    (
        ["-m", "hydra/launcher=pbt", "hydra.launcher.bogus=1", "seed=0,1"],
        ["hydra.launcher.bogus=1", "every_updates, keys, perturb, quantile, resample_probability"],
    ),
    (
        ["-m", "hydra/launcher=pbt", "hydra.launcher.rungs=[1]", "seed=0,1"],
        ["hydra.launcher.rungs=[1]", "quantile"],
    ),
    (
        [
            "-m",
            "hydra/launcher=pbt",
            "+hydra.launcher.bogus=1",
            "hydra.launcher.every_updates=1",
            "hydra.launcher.quantile=0.5",
            "seed=0,1",
        ],
        ["+hydra.launcher.bogus=1", "hydra/launcher=pbt"],
    ),  # fmt: skip
    (["-m", "hydra/launcher=population", "+hydra.launcher.bogus=1", "seed=0,1"], ["+hydra.launcher.bogus=1"]),
    # Accepted nonsense
    (
        ["-m", "hydra/launcher=pbt", "hydra.launcher.perturb=[inf]", "seed=0,1"],
        ["hydra.launcher.perturb=[inf]"],
    ),
    (["-m", "hydra/launcher=pbt", "hydra.launcher.perturb=[1e300]", "seed=0,1"], ["hydra.launcher.perturb"]),
    (
        ["-m", "hydra/launcher=halving", "hydra.launcher.rungs=[1]", "seed=0"],
        ["hydra.launcher.fraction=0.5", "at least 2 agents"],
    ),
    (["agent=1"], ["agent=1", "resume="]),
    (["-m", "hydra/launcher=population", "agent=1", "seed=0,1"], ["agent=1", "resume="]),
    (
        ["-m", "hydra/launcher=pbt_replay", "hydra.launcher.run={pbt}", "algo.lr=3e-4", "seed=5,6"],
        ["algo.lr=0.0003", "hydra/launcher=pbt_replay"],
    ),
]


@pytest.mark.parametrize(
    ("args", "names"), LAUNCHER_REFUSALS, ids=[" ".join(a) for a, _ in LAUNCHER_REFUSALS]
)
def test_a_search_or_population_command_refuses_in_one_stderr_line(
    args, names, tmp_path, command_here, request
):
    """Through drone-train (in this process): exit 1, one stderr line naming the key, the value and what
    is allowed, nothing on stdout about it, and nothing written (no sweep or run folder)."""
    if any("launcher=p" in a or "launcher=h" in a for a in args):
        pytest.importorskip("pyarrow")  # without it the extras check refuses first (tests/test_extras.py)
    pbt_run = request.getfixturevalue("pbt_run") if any("{pbt}" in a for a in args) else None
    proc = _drone_train(command_here, tmp_path, args, pbt_run)
    _refused(proc, *names)
    assert "not started" not in proc.stdout
    assert list(tmp_path.iterdir()) == []


def test_a_population_larger_than_the_memory_is_one_line_before_the_folder(
    tmp_path, command_here, monkeypatch
):
    """The memory check of a population (each agent alone fits; 8 together do not): was on stdout."""
    pytest.importorskip("pyarrow")
    from drone_torchrl import algorithms, memory_estimate

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=TINY)
    plain = OmegaConf.to_container(cfg, resolve=True)
    learner = algorithms.get("reinforce").memory
    one, eight = (memory_estimate.estimate(plain, n, learner).total for n in (1, 8))
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: ((one + eight) // 2, "MemAvailable"))
    proc = _drone_train(command_here, tmp_path, ["-m", "hydra/launcher=population", "seed=range(0,8)"])
    _refused(proc, "8 agents trained together in one population run", "more than the")
    assert list(tmp_path.iterdir()) == []


def test_a_refused_sweep_leaves_an_existing_sweep_folder_byte_for_byte(tmp_path, command_here):
    """A refused command in a finished sweep's folder: its multirun.yaml (and the rest) is not rewritten."""
    pytest.importorskip("pyarrow")
    done = _drone_train(command_here, tmp_path, ["-m", "hydra/launcher=population", "seed=0,1"])
    assert done.returncode == 0, done.stderr

    def files() -> dict[Path, bytes]:
        # .lock holds the last owner's process id, rewritten by whoever takes the folder
        return {
            p: p.read_bytes() for p in (tmp_path / "sweep").rglob("*") if p.is_file() and p.name != ".lock"
        }

    before = files()
    assert tmp_path / "sweep" / "multirun.yaml" in before
    proc = _drone_train(command_here, tmp_path, ["-m", "hydra/launcher=halving", "seed=0,1"])
    assert files() == before
    _refused(proc, "hydra.launcher.rungs")


@pytest.mark.parametrize(
    ("launcher", "extra"),
    [
        ("population", []),
        ("pbt", ["hydra.launcher.every_updates=1", "hydra.launcher.quantile=0.5"]),
        ("halving", ["hydra.launcher.rungs=[1]"]),
        ("pbt_replay", ["hydra.launcher.run={pbt}"]),
        ("fused", []),  # these two took old keys already
        ("basic", []),
    ],
)
def test_an_old_key_means_the_same_under_every_launcher(launcher, extra, tmp_path, command_here, request):
    """``engine=fused`` (today's backend=fast) with a note, as in a single run: the population launchers
    said "not started: legacy.engine is not a config key" per job, "0 finished", and exited 0."""
    if launcher not in ("fused", "basic"):
        pytest.importorskip("pyarrow")
    pbt_run = request.getfixturevalue("pbt_run") if launcher == "pbt_replay" else None
    args = ["-m", f"hydra/launcher={launcher}", "engine=fused", "compile=true", "seed=0,1", *extra]
    proc = _drone_train(command_here, tmp_path, args, pbt_run)
    assert proc.returncode == 0, proc.stderr
    assert "note: engine=fused is now backend=fast" in proc.stderr
    assert "not started" not in proc.stdout
    runs = sorted(p.parent.parent for p in (tmp_path / "sweep").rglob("checkpoints/last.pt"))
    assert len(runs) == (2 if launcher in ("fused", "basic") else 1), proc.stdout
    for run in runs:
        saved = OmegaConf.load(run / "config.yaml")
        assert saved.backend == "fast" and "legacy" not in saved and "engine" not in saved


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_the_gpu_check_without_cuda_is_one_line():
    """``bash benchmarks/gpu_check.sh`` where torch has no CUDA: was an AssertionError traceback."""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    proc = subprocess.run(
        ["bash", str(root / "benchmarks" / "gpu_check.sh")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert proc.stderr.strip().count("\n") == 0 and "--device cuda needs a GPU" in proc.stderr, proc.stderr
    assert "--device cpu" in proc.stderr


def test_at_least_100_rows():
    assert len(TRAIN) + len(EVAL) + len(REPORT) + len(EXPORT) >= 100


# ------------------------------------------------------------------------------------- end to end
def _command(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    module = {
        "drone-train": "train",
        "drone-eval": "evaluate",
        "drone-report": "report",
        "drone-export": "export",
    }[name]
    return subprocess.run(
        [sys.executable, "-m", f"drone_torchrl.apps.{module}", *args],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=cwd,
        env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
    )


E2E = [
    ("drone-train", ["+algo.lrr=1"], "algo.lr"),
    ("drone-train", ["eval.video=off"], "eval.video"),
    ("drone-train", ["seed=18446744073709551616"], "seed"),
    ("drone-train", ["hydra.run.dir={file}"], "hydra.run.dir"),
    ("drone-train", ["resume={payload}"], "payload.pt"),
    ("drone-train", ["resume={run}", "algo.lr=0.5"], "algo.lr"),
    ("drone-train", ["engine=jax"], "engine"),  # an old key with a value it never took
    ("drone-train", ["algo=ppo", "algo.collector=jax"], "algo.collector"),
    ("drone-train", ["engine=torchrl", "backend=fast"], "backend"),  # the old key and the new one
    ("drone-train", ["-m", "seed=0,1", "sweep_name=../../escape"], "sweep_name"),  # wrote outside the folder
    ("drone-eval", ["checkpoint={run}", "env.max_thrust=1.0"], "env.max_thrust"),
    ("drone-eval", ["episodes=0"], "episodes"),
    # Refused before Hydra writes anything (issue: run folders, signals, the last silent inputs).
    ("drone-train", ["hydra.run.dir={sweep}/new"], "hydra.run.dir"),  # a run folder inside a sweep folder
    ("drone-train", ["-m", "resume={run}", "seed=0,1"], "resume"),  # was not refused
    ("drone-train", ["--cfg", "job", "algo.lr=-1"], "algo.lr"),  # printed without validating
    ("drone-train", ["--cfg", "all", "model.min_std=-1"], "model.min_std"),
    ("drone-train", ["algo.lr=[1,"], "algo.lr"),  # Hydra's grammar error: several lines
    ("drone-train", ["algo.name=ppo"], "algo=ppo"),  # said algo.anneal_lr was missing
    ("drone-train", ["logger.backend=csv"], "logger=csv"),  # said logger.float_format was missing
    ("drone-train", ["algo.lr=${{oops"], "algo.lr"),
    ("drone-train", ["--bogus"], "--bogus"),  # argparse's usage text and error
    ("drone-train", ["seed=0", "--config-name"], "--config-name"),
    ("drone-train", ["seed=1", "--cfg", "job", "algo.lr=1e-3"], "algo.lr=1e-3"),  # a flag between overrides
    ("drone-train", ["ppo"], "algo=ppo"),  # a bare word: Hydra's parser error in 4-5 lines
    ("drone-eval", ["{run}"], "checkpoint="),  # a run folder without its key
    ("drone-report", ["{file}"], "notes.txt"),
    ("drone-report", ["{run}", "--window", "abc"], "--window"),
    ("drone-export", ["checkpoint={run}", "format=zip"], "format"),
    ("drone-export", ["checkpoint={run}", "format=onnx", "output=policy.pt2"], "output"),
    # Issue 34, one of each class (all its TRAIN, EVAL and EXPORT rows run through the real commands
    # in the slow stage): a fork into another run's folder (it was overwritten), a damaged and a
    # reshaped checkpoint (flown silently; a size-mismatch traceback), names too long (ENAMETOOLONG).
    ("drone-train", ["resume={best}", "hydra.run.dir={other}"], "hydra.run.dir"),
    ("drone-eval", ["checkpoint={flipped}"], "flipped.pt"),
    ("drone-eval", ["checkpoint={shapes}"], "module.0.module.shared.0.weight"),
    ("drone-train", [f"logger.exp_name={LONG_NAME}"], "logger.exp_name"),
    ("drone-report", ["{run}", "--out", "{long}"], "--out"),
    # Issue 34, the config side.
    ("drone-train", ["experiment=hover_optimal", "algo=reinforce"], "experiment=bounded algo=reinforce"),
    ("drone-train", ["env.disturbance=null"], "env.disturbance"),
    ("drone-train", ["metrics.running_mean_window=50"], "metrics.running_mean_window"),  # a removed key
    ("drone-train", ["hydra/launcher=null"], "hydra/launcher"),  # was a traceback
    ("drone-train", ["env.max_thrust=1e300"], "env.max_thrust"),
    ("drone-train", ["algo.episodes=99999999999999999999"], "algo.episodes"),
    ("drone-train", ["algo=ppo", "algo.steps_per_batch=1000000000"], "algo.steps_per_batch"),
    ("drone-train", ["model.hidden_sizes=[1000000,1000000]"], "model.hidden_sizes"),
    ("drone-train", ["logger=mlflow", "logger.tracking_uri=foo://bar"], MLFLOW_OR("logger.tracking_uri")),
    ("drone-eval", ["env.max_steps=1000000000", "video=true"], "video=false"),
]


def _clean_refusal(proc: subprocess.CompletedProcess, names: str) -> bool:
    """A clean one-line refusal: a non-zero exit, no traceback, and stderr one line (no usage text,
    no grammar hint, no per-job report) that names the input."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    return (
        proc.returncode != 0
        and "Traceback" not in proc.stderr + proc.stdout
        and len(lines) == 1
        and "error" in lines[0]
        and names in lines[0]
    )


@pytest.mark.slow
def test_every_row_through_the_real_commands(files, tmp_path):
    """The review harness: every drone-train, drone-eval and drone-export row above, run through the real
    console command; prints how many end in a clean one-line refusal (the E2E rows: test_end_to_end)."""
    cases = [("drone-train", [*TINY, *o], n) for o, n in TRAIN]
    quiet = ("video=false", "plot=false")  # as test_drone_eval_refuses: unless the row sets the key
    cases += [
        ("drone-eval", [*o, *(q for q in quiet if not o[0].startswith(q.split("=")[0]))], n) for o, n in EVAL
    ]
    cases += [("drone-export", o, n) for o, n in EXPORT]
    cases = [case for case in cases if not _needs_missing_extra(case[1])]

    def one(i):
        name, args, names = cases[i]
        cwd = tmp_path / str(i)
        cwd.mkdir()
        # Each case resumes a copy of the run (and of the population run): the real commands run four
        # at a time, and two of them resuming one folder would be refused for that (it belongs to one
        # process at a time).
        own = dict(files, run=cwd / "run", last=cwd / "run" / "checkpoints" / "last.pt")
        if any("{run}" in a or "{last}" in a for a in args):
            shutil.copytree(files["run"], own["run"], ignore=shutil.ignore_patterns(".lock"))
        if any("{population}" in a for a in args):
            own["population"] = cwd / "population"
            shutil.copytree(files["population"], own["population"], ignore=shutil.ignore_patterns(".lock"))
        return _command(name, *_fill(args, own), cwd=cwd)

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(one, range(len(cases))))
    unclean = [
        f"{name} {' '.join(args)}"
        for (name, args, n), p in zip(cases, results, strict=True)
        if not _clean_refusal(p, n)
    ]
    print(f"review: {len(cases) - len(unclean)} of {len(cases)} bad inputs refused in one clean line")
    for (name, args, n), p in zip(cases, results, strict=True):
        if not _clean_refusal(p, n):
            print(f"unclean: {name} {' '.join(args)}: rc={p.returncode} {p.stderr.strip()[-300:]!r}")
    assert unclean == []


@pytest.mark.slow  # about 70 s on 2 cores; test_train.py's CLI tests keep a real command in the default run
def test_end_to_end(files, tmp_path):
    """The real commands: exit != 0, no traceback, the one line on stderr, nothing written."""

    def one(row):
        name, args, names = row
        cwd = tmp_path / f"{name}-{E2E.index(row)}"
        cwd.mkdir()
        # A row that starts with a flag comes before TINY: argparse takes Hydra's overrides as one group.
        base = TINY if name == "drone-train" else []
        argv = [*_fill(args, files), *base] if args[0].startswith("-") else [*base, *_fill(args, files)]
        return cwd, _command(name, *argv, cwd=cwd)

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(one, E2E))
    for (name, args, names), (cwd, proc) in zip(E2E, results, strict=True):
        where = f"{name} {' '.join(args)}: {proc.stderr}"
        assert proc.returncode != 0, where
        assert "Traceback" not in proc.stderr + proc.stdout, where
        errors = [line for line in proc.stderr.splitlines() if "error" in line]
        assert len(errors) == 1 and names in errors[0], where
        assert not _written(cwd), where
        if args[:2] != [
            "-m",
            "hydra/launcher=fused",
        ]:  # no folder (a sweep keeps its failed job's FAILED.txt)
            assert sorted(p.name for p in cwd.iterdir()) == [], where
    assert not files["marker"].exists()


# ------------------------------------------------------------------------------------- fault tests
def _train(*overrides: str, run_dir: Path, requested: list[str] | None = None) -> float:
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, *overrides])
    from drone_torchrl.training.trainer import train_jobs

    (outcome,) = train_jobs([prepare(cfg, run_dir, requested=requested)])
    assert outcome.error is None, outcome.error
    return outcome.final_return


def test_a_checkpoint_copied_anywhere_resumes_as_a_fork(files, tmp_path, capsys):
    """A checkpoint outside its run folder continues from its episode in the new run's folder."""
    copy = tmp_path / "elsewhere" / "model.pt"
    copy.parent.mkdir()
    copy.write_bytes(files["last"].read_bytes())
    _train(f"resume={copy}", "algo.episodes=4", run_dir=tmp_path / "fork")
    assert "continuing as a fork" in capsys.readouterr().out
    state = torch.load(tmp_path / "fork" / "checkpoints" / "last.pt", weights_only=True)
    assert (state["episodes_done"], state["final"] is not None) == (4, True)
    rows = (tmp_path / "fork" / "episodes.csv").read_text().splitlines()
    # The copy has no episodes.csv beside it: the fork logs from the checkpoint's episode on.
    assert [r.split(",")[0] for r in rows[1:]] == ["2", "3"]
    assert sorted(p.name for p in copy.parent.iterdir()) == ["model.pt"]  # nothing written beside it


def test_a_torn_csv_row_is_dropped_on_resume(files, tmp_path, capsys):
    run = tmp_path / "run"
    _train("checkpoint.every_episodes=2", "algo.episodes=4", run_dir=run)
    last = torch.load(run / "checkpoints" / "last.pt", weights_only=True)
    # As if killed after the episode-2 checkpoint, in the middle of writing episode 3's row.
    complete = (run / "episodes.csv").read_text().splitlines()[:4]  # header + episodes 0-2
    (run / "episodes.csv").write_text("\n".join(complete) + "\n3,3,1")
    torch.save(
        {**last, "episodes_done": 2, "updates_done": 2, "final": None}, run / "checkpoints" / "last.pt"
    )
    _train("checkpoint.every_episodes=2", "algo.episodes=4", run_dir=run)
    assert "line 5 is not a complete row" in capsys.readouterr().err
    lines = (run / "episodes.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in lines[1:]] == ["0", "1", "2", "3"]
    assert all(len(line.split(",")) == len(CSV_COLUMNS) and "" not in line.split(",") for line in lines)


def test_report_skips_unreadable_rows_and_reads_past_them(tmp_path, capsys):
    from drone_torchrl.io.episodes_csv import read_episodes

    header = ",".join(CSV_COLUMNS)
    rows = [f"{e},{e},{10.0 * e},{e + 1},0.0,0.0,NONE,{e}.5" for e in range(20)]
    rows.insert(4, "garbage line")
    rows.insert(9, "7,7,nan,8,0.0,0.0,NONE,7.5")  # a nan: skipped, never a crash (episode 7 has its row)
    path = tmp_path / "episodes.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    columns, notes = read_episodes(path)
    assert columns["episode"].tolist() == list(range(20))  # the garbage hid 16 of 20 episodes before
    assert columns["return"].tolist() == [10.0 * e for e in range(20)]
    assert notes == [
        f"{path}: line 6 is not a complete row; skipped",
        f"{path}: line 11 is not a complete row; skipped",
    ]


def test_a_finished_job_re_run_with_another_value_is_refused(files, tmp_path):
    """Re-running a finished run's folder with a changed hyper-parameter names it; nothing is rewritten."""
    run = tmp_path / "run"
    _train(run_dir=run)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, "algo.gamma=0.9"])
    with pytest.raises(ConfigError, match=r"algo\.gamma 0\.99 -> 0\.9"):
        prepare(cfg, run, requested=["algo.gamma=0.9"])
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    # The budget may change: the same run, extended.
    _train("algo.episodes=4", run_dir=run, requested=["algo.episodes=4"])
    assert torch.load(run / "checkpoints" / "last.pt", weights_only=True)["episodes_done"] == 4


def test_a_refused_re_run_in_a_run_s_folder_keeps_its_hydra_record(files, tmp_path, command_here):
    """``drone-train hydra.run.dir=<finished run> <changed key>``: refused in one line, and the run's
    ``.hydra/`` (how it was started) is not rewritten first, as Hydra would (drone-train in this
    process)."""
    run = tmp_path / "run"
    shutil.copytree(files["run"], run)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text("- algo.episodes=2\n")
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    proc = command_here(
        train_app.run, "drone-train", *TINY, f"hydra.run.dir={run}", "algo.gamma=0.5", cwd=tmp_path
    )
    assert proc.returncode == 1
    _one_line(proc.stderr.strip(), "algo.gamma")
    after = {
        p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name not in ("train.log", ".lock")
    }
    assert after == {p: b for p, b in before.items() if p.name not in ("train.log", ".lock")}


def test_a_launcher_whose_extra_is_missing_is_one_line(monkeypatch):
    """hydra/launcher=local_parallel without the joblib extra: Hydra would list its plugins in many lines."""
    from drone_torchrl import command_line

    found = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == "hydra_plugins.hydra_joblib_launcher" else found(name, *a),
    )
    with pytest.raises(ConfigError) as info:
        command_line.check_extras({"hydra/launcher": "local_parallel"})
    _one_line(str(info.value), "hydra/launcher=local_parallel")
    assert "drone_torchrl[joblib]" in str(info.value)
    # An installed plugin is accepted; the README's install (".[test]") has no submitit extra.
    if found("hydra_plugins.hydra_submitit_launcher") is not None:
        command_line.check_extras({"hydra/launcher": "slurm"})
    else:
        with pytest.raises(ConfigError, match=r"drone_torchrl\[submitit\]"):
            command_line.check_extras({"hydra/launcher": "slurm"})


def test_report_lists_the_jobs_that_failed_before_their_first_episode(files, tmp_path, capsys):
    """A job that failed before writing episodes.csv has no place in the figures; the report says so."""
    sweep = tmp_path / "sweep"
    shutil.copytree(files["run"], sweep / "seed=0")
    (sweep / "seed=0" / ".hydra").mkdir()
    (sweep / "seed=0" / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
    (sweep / "seed=1" / ".hydra").mkdir(parents=True)
    (sweep / "seed=1" / ".hydra" / "overrides.yaml").write_text("- seed=1\n")
    (sweep / "seed=1" / "FAILED.txt").write_text(
        "Traceback ...\nStorageError: cannot write x: No space left\n"
    )
    report_main([str(sweep), "--no-pd", "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert "failed before its first episode (not in the report)" in out
    assert "seed=1: StorageError: cannot write x: No space left" in out
    shutil.rmtree(sweep / "seed=0")
    with pytest.raises(SystemExit):
        report_main([str(sweep), "--no-pd"])
    err = capsys.readouterr().err
    _one_line(err.strip(), "1 job(s) failed before their first episode")


def test_a_budget_below_an_unfinished_checkpoint_is_refused_and_one_at_it_finishes(files, tmp_path):
    """A run killed after its last checkpoint but before its final evaluation: a smaller budget was a
    KeyError that crashed the whole fused sweep; now it is refused, and the same budget finishes it."""
    run = tmp_path / "run"
    _train("algo.episodes=4", "checkpoint.every_episodes=2", run_dir=run)
    last = run / "checkpoints" / "last.pt"
    torch.save({**torch.load(last, weights_only=True), "final": None}, last)
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*TINY, f"resume={run}"])
    with pytest.raises(ConfigError, match=r"^algo\.episodes=2 is not allowed; expected >= 4"):
        prepare(cfg, requested=["algo.episodes=2"])
    final = _train(f"resume={run}", run_dir=None, requested=[f"resume={run}"])
    state = torch.load(last, weights_only=True)
    assert state["episodes_done"] == 4 and state["final"]["final_return"] == final
    assert len((run / "episodes.csv").read_text().splitlines()) == 1 + 4  # no episode trained twice


# ------------------------------------------------------------------- issue 34: files and checkpoints
def test_a_fork_into_another_run_s_folder_leaves_it_byte_for_byte(files, tmp_path):
    """``drone-train resume=<run A>/checkpoints/best.pt hydra.run.dir=<run B>`` continued A as a fork
    inside B and replaced B's checkpoints, CSV and config (exit 0). Refused in one line, in-process
    and through the real command, and every file of B (.hydra/, tensorboard/, .lock) is unchanged."""
    run_b = tmp_path / "B"
    shutil.copytree(files["other"], run_b)
    before = _snapshot(run_b)
    assert {".hydra", "checkpoints", "episodes.csv", "config.yaml", "tensorboard"} <= {
        p.name for p in run_b.iterdir()
    }
    overrides = [*TINY, f"resume={files['best']}"]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    with pytest.raises(ConfigError) as info:
        prepare(cfg, run_b, requested=overrides)
    _one_line(str(info.value), f"hydra.run.dir={run_b}")
    proc = _command("drone-train", *overrides, f"hydra.run.dir={run_b}", cwd=tmp_path)
    assert proc.returncode == 1 and "continues as a fork" in proc.stderr, proc.stderr
    _one_line(proc.stderr.strip(), "hydra.run.dir")
    assert _snapshot(run_b) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["B"]  # no folder of the refused command's
    # A new or empty folder takes the fork.
    (tmp_path / "empty").mkdir()
    assert prepare(cfg, tmp_path / "empty", requested=overrides).parent_dir == files["run"]
    release(tmp_path / "empty")


@pytest.mark.parametrize("run", ["run", "ppo"])
def test_a_flipped_byte_in_any_tensor_is_refused_on_load(files, tmp_path, run):
    """One bit flipped inside each tensor's storage of a real checkpoint (``torch.load`` reads it
    without noticing) is refused in one line naming the file: by the digest written with the
    tensors, and in a checkpoint from before the digest, by the zip's CRC-32 of the record."""
    last = files[run] / "checkpoints" / "last.pt"
    state = torch.load(last, weights_only=True)
    records = storages(last)
    tensors = [t for entry in ("actor", "critic") for t in state.get(entry, {}).values()]
    assert len(records) >= len(tensors) >= 8  # every weight has a storage of its own, and more (Adam, RNG)
    old = tmp_path / "old.pt"  # as written before the digest existed
    torch.save({k: v for k, v in state.items() if k != "tensor_sha256"}, old)
    load_checkpoint(last), load_checkpoint(old)  # intact: both load
    for source in (last, old):
        for record in storages(source):
            damaged = flipped(source, record, tmp_path / "damaged.pt")
            with pytest.raises(CheckpointError) as info:
                load_checkpoint(damaged)
            _one_line(str(info.value), f"{damaged}: ")
            assert "damaged file" in str(info.value)


@pytest.mark.parametrize("name", [n for n in DAMAGED if n not in ("flipped", "shapes", "critic_shapes")])
def test_counters_and_weights_are_checked_on_load(files, name):
    """Counters a run cannot have (episodes_done=-5, 2.5, true) and NaN or infinite weights in the
    actor, Adam's moments or the critic: refused on load, in one line naming the file and what."""
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(files[name])
    _one_line(str(info.value), str(files[name]))
    what = {
        "nan": "tensor actor/",
        "adam_inf": "tensor optimizer/state/0/exp_avg_sq",
        "critic_nan": "tensor critic/",
    }
    assert what.get(name, DAMAGED[name]) in str(info.value)


@pytest.mark.parametrize("name", ["shapes", "critic_shapes"])
def test_a_checkpoint_of_other_shapes_is_refused_naming_the_first_tensor(files, tmp_path, monkeypatch, name):
    """Weights of other shapes than the checkpoint's config describes were a multi-line ``size
    mismatch`` traceback: drone-eval, drone-export and resume refuse them in one line naming the
    file, the first tensor and both shapes."""
    monkeypatch.chdir(tmp_path)
    tensor, shapes = {
        "shapes": ("actor/module.0.module.shared.0.weight", "[32, 6], but the networks its config describes"),
        "critic_shapes": ("critic/module.0.weight", "[64, 6], but the networks its config describes"),
    }[name]
    path = str(files[name])
    with initialize_config_dir(config_dir(), version_base="1.3"):
        commands = [
            lambda: run_eval(compose("eval", overrides=[f"checkpoint={path}", "video=false", "plot=false"])),
            lambda: run_export(compose("export", overrides=[f"checkpoint={path}"])),
            lambda: prepare(compose("config", overrides=[f"resume={path}"]), tmp_path / "job"),
        ]
        for command in commands:
            with pytest.raises(ConfigError) as info:
                command()
            _one_line(str(info.value), path)
            assert f"the tensor {tensor} has shape {shapes}" in str(info.value)
            assert "need [16, 6]" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def _refused(proc: subprocess.CompletedProcess, *words: str) -> str:
    """A one-line refusal naming ``words``: non-zero exit, no traceback."""
    assert proc.returncode not in (0, -signal.SIGABRT), proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "error" in lines[0], proc.stderr
    for word in words:
        assert word in lines[0], proc.stderr
    return lines[0]


@pytest.mark.slow
@pytest.mark.parametrize("how", ["full", "read-only"])
def test_eval_export_report_on_a_full_or_read_only_disk_are_one_line(files, small_disk, tmp_path, how):  # noqa: F811
    """drone-eval, drone-export and drone-report writing into a full or read-only folder: OSError
    tracebacks (and ``drone-export`` on a full disk aborted in C++, exit -6). Refused in one line
    before any work, nothing written; a read-only or full working folder too (Hydra's own folder)."""
    disk = Disk(small_disk, how)
    disk.break_()
    try:
        run = files["run"]
        _refused(
            _command("drone-export", f"checkpoint={run}", f"output={small_disk}/p.pt2", cwd=tmp_path),
            "output",
        )
        _refused(
            _command("drone-export", f"checkpoint={run}", f"output={small_disk}/sub/p.onnx", cwd=tmp_path),
            "output",
        )
        _refused(
            _command("drone-eval", f"checkpoint={run}", f"hydra.run.dir={small_disk}/eval", cwd=tmp_path),
            "hydra.run.dir",
        )
        _refused(_command("drone-eval", f"checkpoint={run}", "episodes=2", cwd=small_disk), "hydra.run.dir")
        _refused(_command("drone-train", *TINY, cwd=small_disk), "hydra.run.dir")
        _refused(_command("drone-report", str(run), "--out", f"{small_disk}/report", cwd=tmp_path), "--out")
        left = sorted(p.name for p in small_disk.iterdir())
    finally:
        disk.repair()
    assert left == ([] if how == "read-only" else ["filler", "filler2"])
    assert [p.name for p in tmp_path.iterdir()] == ["disk"]  # the tmpfs's mount point, nothing else


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_a_write_that_runs_out_of_room_leaves_no_partial_file(files, small_disk, tmp_path, capsys):  # noqa: F811
    """A disk with a page free passes the checks before the work, then fills up under the write:
    one line naming the file, and no partial or temporary file (drone-export: exit -6 before)."""
    disk = Disk(small_disk, "full", room=4096)
    disk.break_()
    try:
        run = files["run"]
        # ONNX where its extra is installed (the plain ".[test]" install refuses format=onnx first).
        onnx = all(importlib.util.find_spec(name) is not None for name in ONNX_MODULES)
        for output in ("p.pt2", "sub/p.onnx") if onnx else ("p.pt2",):
            line = _refused(
                _command("drone-export", f"checkpoint={run}", f"output={small_disk / output}", cwd=tmp_path),
                f"cannot write {small_disk / output}",
            )
            assert "No space left on device (ENOSPC)" in line
        with pytest.raises(SystemExit):
            report_main([str(files["other"]), "--no-pd", "--out", str(small_disk / "report")])
        line = capsys.readouterr().err
        _one_line(line, f"cannot write {small_disk / 'report'}/")
        assert "(ENOSPC)" in line
        left = sorted(str(p.relative_to(small_disk)) for p in small_disk.rglob("*") if p.is_file())
    finally:
        disk.repair()
    assert left == ["filler", "filler2"]
    assert [p.name for p in tmp_path.iterdir()] == ["disk"]


# Stops drone-export with SIGTERM in the middle: once the program is serialised (the .pt2 was
# written straight into a temporary file beside the output), or half-way through writing the file.
SIGTERM_EXPORT = """
import os, pathlib, signal, sys, time
import torch

def stop():
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(30)

if sys.argv[1] == "serialised":
    save = torch.export.save
    def save(*args, save=save, **kwargs):
        save(*args, **kwargs)
        stop()
    torch.export.save = save
else:
    def write_half(self, data):
        with open(self, "wb") as f:
            f.write(bytes(data)[: len(data) // 2])
        stop()
    pathlib.Path.write_bytes = write_half
sys.argv = ["drone-export", f"checkpoint={sys.argv[2]}", "output=out/policy.pt2"]
from drone_torchrl.apps.export import run
run()
"""


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
@pytest.mark.parametrize("when", ["serialised", "writing"])
def test_sigterm_during_an_export_leaves_no_file(files, tmp_path, when):
    """SIGTERM during drone-export left a partial file (``policy.pt2.tmp.pt2``): the export exits
    143 with one line, and its folder holds nothing."""
    script = tmp_path / "stop.py"
    script.write_text(SIGTERM_EXPORT)
    (tmp_path / "cwd").mkdir()
    proc = subprocess.run(
        [sys.executable, str(script), when, str(files["run"])],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=tmp_path / "cwd",
    )
    left = [str(p.relative_to(tmp_path / "cwd")) for p in (tmp_path / "cwd").rglob("*") if p.is_file()]
    assert (proc.returncode, left) == (128 + signal.SIGTERM, []), proc.stderr
    assert proc.stderr.strip() == "drone-export: stopped by SIGTERM; nothing written"


def test_a_row_that_is_not_utf8_is_skipped_by_the_report_and_dropped_on_resume(files, tmp_path, capsys):
    """A byte that is not UTF-8 in episodes.csv was a UnicodeDecodeError in drone-report and on
    resume: the row is skipped with a note, like any unreadable row; a FAILED.txt that is not UTF-8
    still says the job failed."""
    job = tmp_path / "sweep" / "seed_0"  # no '=': resume= names it on the command line
    shutil.copytree(files["run"], job, ignore=shutil.ignore_patterns(".lock"))
    (job / ".hydra").mkdir()
    (job / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
    csv_path = job / "episodes.csv"
    lines = csv_path.read_bytes().splitlines(keepends=True)
    cause = len(CSV_COLUMNS) - 2  # termination_cause: text, which parsed whatever it held
    fields = lines[2].split(b",")
    fields[cause] = fields[cause][:2] + b"\xff" + fields[cause][2:]
    lines[2] = b",".join(fields)  # episode 1
    csv_path.write_bytes(b"".join(lines))
    note = f"{csv_path}: line 3 is not UTF-8 text; skipped"
    columns, notes = read_episodes(csv_path)
    assert columns["episode"].tolist() == [0.0] and notes == [note]
    report_main([str(tmp_path / "sweep"), "--no-pd", "--out", str(tmp_path / "report")])
    assert note in capsys.readouterr().out
    _train(f"resume={job}", "algo.episodes=4", run_dir=None, requested=[f"resume={job}", "algo.episodes=4"])
    assert f"resume: {note}" in capsys.readouterr().err
    text = csv_path.read_bytes().decode("utf-8")  # all of it UTF-8 again
    assert [line.split(",")[0] for line in text.splitlines()[1:]] == ["0", "2", "3"]
    (job / "FAILED.txt").write_bytes(b"Traceback ...\nStorageError: cannot write caf\xe9\n")
    assert job_status(job) == ("failed", "StorageError: cannot write caf\ufffd")


@pytest.mark.slow  # two real processes, about 30 s on 2 cores
def test_two_runs_that_open_a_new_mlflow_store_together_both_complete(tmp_path):
    """Two processes that start together on a new SQLite store: the second died while MLflow created the
    tables (``duplicate column name: step``, or alembic's ``expected to match one row``) and its run was
    lost. Both complete now, each an MLflow run with every episode's step once."""
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    store = tmp_path / "mlflow.db"
    args = [
        *TINY,
        "algo.episodes=4",
        "eval.every_episodes=0",
        "logger=mlflow",
        f"logger.tracking_uri=sqlite:///{store}",
    ]
    runs = [tmp_path / name for name in ("a", "b")]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "drone_torchrl.apps.train", *args, f"hydra.run.dir={run}"],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for run in runs
    ]
    results = [proc.communicate(timeout=180) for proc in procs]
    for proc, (_, err) in zip(procs, results, strict=True):
        assert proc.returncode == 0, err[-2000:]
    client = MlflowClient(tracking_uri=f"sqlite:///{store}")
    (experiment,) = [e for e in client.search_experiments() if e.name == "adhoc"]
    found = {r.data.tags["run_dir"]: r for r in client.search_runs([experiment.experiment_id])}
    assert sorted(found) == sorted(str(run) for run in runs)
    for run in found.values():
        assert run.info.status == "FINISHED"
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "episode/return")]
        assert sorted(steps) == [1, 2, 3, 4]  # every episode once


# ----------------------------------------------------------------------- population runs: storage
# A two-agent population sweep, as a user types it (in a folder named by the test).
POPULATION_SWEEP = [
    "-m",
    "hydra/launcher=population",
    "algo.lr=1e-4,3e-4",
    "seed=0",
    *TINY[1:],
    "checkpoint.keep_best=false",
    "hydra.sweep.dir=sweep",
]
# A file-size limit (bytes) below a two-agent population checkpoint's (about 45 KB), above its other files.
FILE_SIZE_LIMIT = 20_000


def _continue_command(line: str) -> list[str]:
    """The arguments of the command a one-line refusal says continues the run (``continue with: ...``)."""
    words = shlex.split(line.rsplit("continue with: ", 1)[1])
    assert words[0] == "drone-train", line
    return words[1:]


@pytest.mark.slow  # a drone-train process of its own (the limit is per process): about 10 s on 2 cores
def test_a_file_size_limit_at_a_population_checkpoint_is_one_line(tmp_path, command_here):
    """``drone-train -m hydra/launcher=population ...`` under a file-size limit (RLIMIT_FSIZE: EFBIG,
    as a full disk) fails at its first checkpoint: a StorageError traceback before. Now one stderr
    line naming the file and the command that continues, no temporary file; that command, without
    the limit, trains it."""
    pytest.importorskip("pyarrow")
    limited = subprocess.run(
        [sys.executable, "-m", "drone_torchrl.apps.train", *POPULATION_SWEEP, "algo.episodes=2"],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=tmp_path,
        env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT, FILE_SIZE_LIMIT)),
    )
    last = tmp_path / "sweep" / "population_0" / "checkpoints" / "last.pt"
    line = _refused(limited, f"cannot write {last.resolve()}", "File too large (EFBIG)", "continue with: ")
    assert not last.exists() and not list(tmp_path.rglob("*.tmp"))
    again = command_here(train_app.run, "drone-train", *_continue_command(line), cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert load_checkpoint(last)["episodes_done"] == [2, 2]


@pytest.mark.parametrize("launcher", ["population", "fused"])
def test_a_read_only_disk_under_a_sweep_is_one_line(small_disk, command_here, monkeypatch, launcher):  # noqa: F811
    """The disk remounted read-only under a sweep (after its first checkpoint). ``population``: a
    StorageError traceback, a second one from closing its logger on top; ``fused``: exit 0, every
    job "unfinished", no line at all. Now one stderr line naming the file and the command that
    continues; once the disk is writable again, that command finishes every agent's episodes, each once."""
    pytest.importorskip("pyarrow")
    from drone_torchrl.training import population_record, run

    record = population_record.PopulationRecord if launcher == "population" else run.RunRecord
    disk, save = Disk(small_disk, "read-only"), record.save

    def break_at_the_second(self, state):
        if list(small_disk.glob("sweep/*/checkpoints/last.pt")):
            disk.break_()
        return save(self, state)

    monkeypatch.setattr(record, "save", break_at_the_second)
    args = [*POPULATION_SWEEP, f"hydra/launcher={launcher}", "algo.episodes=8", "checkpoint.every_episodes=2"]
    try:
        proc = command_here(train_app.run, "drone-train", *args, cwd=small_disk)
    finally:
        disk.repair()
    monkeypatch.setattr(record, "save", save)
    line = _refused(
        proc, "Read-only file system (EROFS)", "every checkpoint written is intact", "continue with:"
    )
    again = command_here(train_app.run, "drone-train", *_continue_command(line), cwd=small_disk)
    assert again.returncode == 0, again.stderr
    if launcher == "population":
        rows = population_record.read_episodes(small_disk / "sweep" / "population_0")
        assert sorted(zip(rows["agent"], rows["episode"], strict=True)) == [
            (a, e) for a in (0, 1) for e in range(8)
        ]
    else:
        jobs = sorted(small_disk.glob("sweep/*/episodes.csv"))
        assert len(jobs) == 2 and all(
            read_episodes(job)[0]["episode"].tolist() == list(range(8)) for job in jobs
        )


def _damage_population(files: dict[str, Path], root: Path, how: str) -> Path:
    """A copy of the fixture's population run as a sweep's job, damaged ``how``; returns the sweep."""
    run = root / "sweep" / "population_0"
    shutil.copytree(files["population"], run)
    (run / ".hydra").mkdir()
    part = run / "episodes" / "part-000001.parquet"
    if how == "part_torn":
        part.write_bytes(part.read_bytes()[: part.stat().st_size // 2])
    elif how == "part_missing":
        part.unlink()
    elif how == "agents_missing":
        (run / "agents.parquet").unlink()
    elif how == "agents_foreign":
        (run / "agents.parquet").write_bytes(b"PAR1 not a table")
    elif how == "checkpoint_torn":
        last = run / "checkpoints" / "last.pt"
        last.write_bytes(last.read_bytes()[:1000])
    return root / "sweep"


@pytest.mark.parametrize(
    ("how", "names"),
    [
        ("part_torn", "part-000001.parquet is not a readable Parquet file"),  # a pyarrow traceback
        ("part_missing", "part-000001.parquet is missing"),  # reported without its episodes
        ("agents_missing", "agents.parquet is missing"),  # "no job folder with an episodes.csv"
        ("agents_foreign", "agents.parquet is not a readable Parquet file"),  # a pyarrow traceback
        ("checkpoint_torn", "last.pt is not a readable checkpoint"),  # reported as "no checkpoint"
    ],
)
def test_drone_report_on_a_damaged_population_run_is_one_line(files, tmp_path, capsys, how, names):
    """drone-report on a population run with a damaged or missing Parquet file or checkpoint: one
    line naming the file, exit 2, no report written."""
    if not POPULATION_EXTRA:
        pytest.skip("the population run's fixture needs pyarrow: pip install 'drone_torchrl[population]'")
    sweep = _damage_population(files, tmp_path, how)
    with pytest.raises(SystemExit) as info:
        report_main([str(sweep), "--no-pd"])
    assert info.value.code == 2
    _one_line(capsys.readouterr().err, names)
    assert not (sweep / "report").exists()


# ----------------------------------------------------------------- resume refusals that name the truth
def test_a_resume_with_another_logger_names_only_what_the_command_changes(files, tmp_path, command_here):
    """``resume=<run> logger=csv``: the refusal listed env.max_steps 20 -> 300 and eval.episodes
    1 -> 10 too (keys the command never set: the run's values against the defaults). Now only the
    keys the logger choice sets; the run is left byte for byte."""
    run = tmp_path / "run"
    shutil.copytree(files["run"], run)

    def run_files() -> dict[Path, str]:  # but the lock, which the command claims
        return {p: d for p, d in _snapshot(run).items() if p.name != ".lock"}

    before = run_files()
    proc = command_here(
        train_app.run, "drone-train", f"resume={run}", "logger=csv", "algo.episodes=4", cwd=tmp_path
    )
    line = _refused(proc, "logger.backend 'tensorboard' -> 'csv'")
    assert "env.max_steps" not in line and "eval.episodes" not in line
    assert run_files() == before


def test_a_ppo_run_s_own_keys_are_its_algo_s_on_resume(files, tmp_path, command_here):
    """``resume=<a PPO run> algo.target_kl=0.02`` was "algo.target_kl is not a key of this algo; it
    belongs to algo=ppo" (the command line was checked against the default algo, REINFORCE). Now it
    is refused as a continued run's changed hyper-parameter, with both values; the same value is
    taken, and the run goes on to its new budget."""
    run = tmp_path / "ppo"
    shutil.copytree(files["ppo"], run)
    proc = command_here(train_app.run, "drone-train", f"resume={run}", "algo.target_kl=0.02", cwd=tmp_path)
    _refused(proc, "algo.target_kl None -> 0.02", "keeps its hyper-parameters")
    proc = command_here(
        train_app.run, "drone-train", f"resume={run}", "algo.target_kl=null", "algo.episodes=4", cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert load_checkpoint(run / "checkpoints" / "last.pt")["episodes_done"] >= 4


@pytest.mark.parametrize(
    ("prog", "word", "hint"),
    [
        ("drone-train", "ppo", "did you mean algo=ppo?"),
        ("drone-train", "hover_optimal", "did you mean experiment=hover_optimal?"),
        ("drone-train", "{here}", "did you mean resume={here}?"),
        ("drone-eval", "{here}", "did you mean checkpoint={here}?"),
        ("drone-train", "fly", "see drone-train --help"),
    ],
)
def test_a_bare_word_is_refused_with_the_override_it_meant(prog, word, hint, tmp_path):
    """An argument without ``=`` (Hydra answers with its parser's error in several lines): one line."""
    from drone_torchrl.command_line import parse_flags

    word, hint = word.format(here=tmp_path), hint.format(here=tmp_path)
    with pytest.raises(ConfigError) as err:
        parse_flags(prog, ["seed=1", word])
    assert str(err.value) == f"{word!r} is not KEY=VALUE; {hint}"
    assert parse_flags(prog, ["seed=1", "~logger"]).overrides == ["seed=1", "~logger"]  # deletion needs no =
