"""The memory estimator (drone_torchrl/memory_estimate.py): its shapes are the code's, it is
within its stated factor of what real configs allocate, and a config that does not fit in the memory
this machine has free is refused in one line before any work."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl import algorithms, memory_estimate
from drone_torchrl.config import ConfigError, _plain, check_keys, config_dir, validate
from drone_torchrl.memory_estimate import STATED_FACTOR, estimate, policy_parameters
from drone_torchrl.modules.factory import build_critic, build_policy


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _estimate(*overrides: str, agents: int = 1):
    cfg = _plain(check_keys(_cfg(*overrides)))
    return estimate(cfg, agents, algorithms.get(cfg.algo.name).memory)


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        ["model.hidden_sizes=[7,5,3]", "env.disturbance.observed_actions=2"],
        ["algo=ppo", "algo.value_hidden_sizes=[9,4]"],
    ],
)
def test_parameter_counts_are_the_nets_own(overrides):
    """The estimator's P and Pv are the parameter counts of the nets the runs build (6 + 2k inputs)."""
    cfg = _cfg(*overrides)
    plain = _plain(check_keys(cfg))
    assert policy_parameters(plain) == sum(p.numel() for p in build_policy(cfg).parameters())
    if "value_hidden_sizes" in cfg.algo:
        weights = algorithms.get("ppo").memory(plain, 1)["the critic's weights"].bytes
        assert weights == memory_estimate.ADAM_COPIES * 4 * sum(
            p.numel() for p in build_critic(cfg).parameters()
        )


def test_the_parts_scale_as_derived():
    """By hand from the docstring's derivation: the default REINFORCE config (one episode of 300 steps,
    [32,32], float32) and PPO's batch (64 x 64 frames of 6-entry observations, [64,64] critic)."""
    est = _estimate("eval.video=false")
    p = 6 * 32 + 32 + 32 * 32 + 32 + 2 * (32 * 2 + 2)  # 1412
    assert est.parts["the policy's weights"].bytes == 5 * p * 4
    # backend=fast: the kernel's saved step (observation, hidden outputs, loc, pre, action, return),
    # the backward's gradients (hidden outputs, heads), its rewards and returns-to-go, the int64 cause.
    assert est.parts["REINFORCE's update"].bytes == 300 * ((6 + 64 + 7 + 64 + 4 + 2) * 4 + 8)
    reference = _estimate("eval.video=false", "backend=reference").parts["REINFORCE's update"]
    per_step = (39 * 4 + 24) + 6 * 4 + (64 + 3 * 32) * 4 + 12 * 4  # rollout, observation, graph, loss
    assert reference.bytes == 300 * per_step
    assert est.parts["evaluation"].bytes == 10 * 300 * (39 * 4 + 24 + 3 + 16)
    frame = (2 * 6 + 13) * 4 + 30
    ppo = _estimate("algo=ppo").parts
    assert ppo["the on-policy batch"].bytes == 64 * 64 * (3 * frame + 2 * (6 + 2 * 64) * 4)
    assert ppo["a minibatch"].bytes == 2048 * (frame + (256 + 3 * 64) * 4)
    # A population of 8 agents: 8 times each per-agent part; the video (one episode) once.
    one, eight = _estimate(), _estimate(agents=8)
    for name, part in one.parts.items():
        assert eight.parts[name].bytes == (part.bytes if part.host else 8 * part.bytes), name
    # float64 runs: every float twice as wide.
    assert _estimate("env.dtype=float64").parts["the policy's weights"].bytes == 5 * p * 8


# Configs whose episodes last env.max_steps (started in the air, 30 steps: none reaches the floor),
# so the estimate's upper bound is what they hold; large enough (~50-700 MB) that the libraries' own
# allocations do not matter.
MEASURED = [
    ["algo.episodes_per_update=1024", "algo.episodes=1024", "model.hidden_sizes=[256,256]"],
    [
        "algo.episodes_per_update=512",
        "algo.episodes=512",
        "model.hidden_sizes=[256,256]",
        "backend=reference",
    ],
    [
        "algo=ppo",
        "algo.num_envs=2048",
        "algo.steps_per_batch=100",
        "algo.minibatch_size=25600",
        "algo.epochs=1",
    ],
    ["algo=a2c", "algo.num_envs=2048", "algo.steps_per_batch=100", "algo.minibatch_size=204800"],
    ["eval.episodes=10000"],
]
AIR = [
    "env.max_steps=30",
    "env.reset_mode=air",
    "eval.video=false",
    "eval.episodes=1",
    "progress=false",
]
# One update and one evaluation of a learner, in a fresh process: the peak resident memory (VmHWM,
# reset through /proc/self/clear_refs once the learner is built) above what it held before.
PROBE = """
import sys, tempfile
import torch
from pathlib import Path
from hydra import compose, initialize_config_dir
from drone_torchrl import algorithms
from drone_torchrl.config import config_dir, env_kwargs
from drone_torchrl.evaluation import evaluate
from drone_torchrl.training.jobs import prepare

def status(key):
    return next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith(key))

with initialize_config_dir(config_dir(), version_base="1.3"):
    cfg = compose("config", overrides=sys.argv[1:])
learner = algorithms.get(cfg.algo.name).learner([prepare(cfg, Path(tempfile.mkdtemp()) / "run")])
before = status("VmRSS")
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")
learner.update(learner.state, 1, torch.ones(1, dtype=torch.bool))
evaluate(learner.eval_policy(), env_kwargs(cfg), cfg.eval.episodes, cfg.eval.seed, agents=learner.eval_agents)
print(status("VmHWM") - before)
"""


@pytest.mark.slow  # four processes of 5-10 s
@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="needs Linux's /proc/self/clear_refs")
@pytest.mark.parametrize("overrides", MEASURED, ids=lambda o: " ".join(o))
def test_the_estimate_is_within_its_stated_factor_of_a_real_update(overrides, tmp_path):
    args = [*AIR, *overrides]
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    measured = int(proc.stdout.split()[-1])
    estimated = _estimate(*args).total
    print(f"{' '.join(overrides)}: estimated {estimated / 1e6:.0f} MB, measured {measured / 1e6:.0f} MB")
    assert 1 / STATED_FACTOR <= estimated / measured <= STATED_FACTOR


def test_a_config_larger_than_the_free_ram_is_refused_in_one_line(monkeypatch):
    """The check against MemAvailable, patched: just enough passes, a byte less is refused, naming the
    estimate and the keys of its largest part (PPO's batch)."""
    overrides = ["algo=ppo", "eval.video=false"]
    needed = _estimate(*overrides).total
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (needed, "MemAvailable"))
    validate(_cfg(*overrides))
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (needed - 1, "MemAvailable"))
    with pytest.raises(ConfigError) as info:
        validate(_cfg(*overrides))
    message = str(info.value)
    assert "\n" not in message
    assert f"needs about {memory_estimate.size(needed)}" in message and "(MemAvailable)" in message
    assert "the on-policy batch" in message and "lower algo.num_envs or algo.steps_per_batch" in message


def test_the_gpu_s_free_memory_bounds_what_lives_on_it(monkeypatch):
    """device=cuda: the device's parts against the GPU's free memory, the video (host) against the RAM."""
    memory = _estimate()  # with its video
    on_gpu, on_host = memory.on(host=False), memory.on(host=True)
    assert on_host > 0 and on_gpu + on_host == memory.total
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (on_host, "MemAvailable"))
    monkeypatch.setattr(memory_estimate, "available_gpu", lambda device: (on_gpu, f"free on {device}"))
    memory_estimate.check(memory, "cuda:0")
    monkeypatch.setattr(memory_estimate, "available_gpu", lambda device: (on_gpu - 1, f"free on {device}"))
    with pytest.raises(ConfigError, match=r"of GPU memory available \(free on cuda:0\)"):
        memory_estimate.check(memory, "cuda:0")
    monkeypatch.setattr(memory_estimate, "available_gpu", lambda device: (on_gpu, f"free on {device}"))
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (on_host - 1, "MemAvailable"))
    with pytest.raises(
        ConfigError,
        match=r"of RAM available .*the largest part is an evaluation video, .*: set eval.video=false",
    ):
        memory_estimate.check(memory, "cuda:0")


def test_a_population_too_large_for_memory_fails_before_training(monkeypatch, tmp_path):
    """Each job fits alone; the 3 agents trained together in one process do not: refused (recorded
    per job) before any episode, nothing trained."""
    from drone_torchrl.training.jobs import prepare
    from drone_torchrl.training.trainer import train_jobs

    overrides = ["algo.episodes=2", "env.max_steps=20", "eval.video=false", "progress=false"]
    one = _estimate(*overrides).total
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (2 * one, "MemAvailable"))
    jobs = [prepare(_cfg(*overrides, f"seed={seed}"), tmp_path / str(seed)) for seed in range(3)]
    outcomes = train_jobs(jobs)
    for seed, outcome in enumerate(outcomes):
        assert isinstance(outcome.error, ConfigError) and "needs about" in str(outcome.error)
        assert not (tmp_path / str(seed) / "episodes.csv").exists()


def test_drone_eval_does_not_need_the_training_s_memory_or_logger(monkeypatch):
    """drone-eval reads a checkpoint's config for its values: a run trained where its batch fitted, or
    with a logger whose extra is not installed here, is still evaluated (only its own rollouts are
    sized against this machine's memory)."""
    from drone_torchrl import loggers

    cfg = _cfg("algo=ppo", "eval.video=false")
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (1, "MemAvailable"))
    with pytest.raises(ConfigError, match="needs about"):
        validate(cfg)
    validate(cfg, training=False)
    mlflow = _cfg("logger=mlflow", "eval.video=false")
    monkeypatch.setattr(loggers.Backend, "installed", property(lambda self: self.needs is None))
    validate(mlflow, training=False)
