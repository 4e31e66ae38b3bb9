"""The fast engine's work per update does not grow with the number of agents (on the tensor side)."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from hydra import compose, initialize_config_dir
from torch.utils._python_dispatch import TorchDispatchMode

from drone_torchrl.config import config_dir
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.optim import Adam
from drone_torchrl.training.trainer import Trainer

# Ops that copy a value to the host (item, bool(), nonzero sizes, ...), and Tensor.tolist and
# Tensor.numpy, which copy without passing through the dispatcher (counted by wrappers).
SYNC_OPS = ("_local_scalar_dense", "nonzero", "is_nonzero", "tolist", "numpy")


class CountOps(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func.__name__.split(".")[0]] += 1
        return func(*args, **(kwargs or {}))


def _ops_per_update(tmp_path, agents: int, monkeypatch) -> Counter:
    overrides = [
        "progress=false",
        "env.max_steps=20",
        "eval.every_episodes=0",
        "eval.video=false",
    ]
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    jobs = []
    for seed in range(agents):
        job = cfg.copy()
        job.seed = seed
        jobs.append(prepare(job, tmp_path / f"n{agents}" / f"agent{seed}"))
    trainer = Trainer(jobs)
    # The optimizer as on a GPU: masked arithmetic (the CPU's fused kernel is told who steps, a sync).
    monkeypatch.setattr(Adam, "step", Adam._masked_step)
    everyone = list(range(agents))
    trainer.step(everyone, 1)  # first update: lazy set-up
    tolist, numpy = torch.Tensor.tolist, torch.Tensor.numpy

    def counted(name, method):
        def call(tensor):
            counter.ops[name] += 1
            return method(tensor)

        return call

    monkeypatch.setattr(torch.Tensor, "tolist", counted("tolist", tolist))
    monkeypatch.setattr(torch.Tensor, "numpy", counted("numpy", numpy))
    with CountOps() as counter:
        trainer.step(everyone, 1)
    monkeypatch.setattr(torch.Tensor, "tolist", tolist)
    monkeypatch.setattr(torch.Tensor, "numpy", numpy)
    trainer.close()
    return counter.ops


@pytest.mark.parametrize("agents", [64])
def test_ops_and_host_syncs_per_update_do_not_grow_with_agents(tmp_path, monkeypatch, agents):
    one = _ops_per_update(tmp_path, 1, monkeypatch)
    many = _ops_per_update(tmp_path, agents, monkeypatch)
    syncs = {op: one[op] for op in SYNC_OPS if one[op]}
    # The one fetch of the update's episodes and metrics (the kernel flies and differentiates the
    # episodes in one call, with no check from Python in between).
    assert syncs == {"numpy": 1}, one
    assert {op: many[op] for op in SYNC_OPS if many[op]} == syncs
    # The same kernels for 64 agents as for one (a reshape of a size-1 dim may add a view).
    assert abs(sum(many.values()) - sum(one.values())) <= 2, (many - one) + (one - many)
    assert sum(many.values()) < 150  # a few ops per update, not per step
