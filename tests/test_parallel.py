"""``DroneEnv`` inside TorchRL's ``ParallelEnv`` / ``SerialEnv`` and the ``make_env`` factory.

``ParallelEnv`` starts ``spawn`` worker processes (seconds each), so only one is ever started here;
the factory is a ``functools.partial`` of the importable ``DroneEnv`` class, hence picklable.
"""

from __future__ import annotations

from functools import partial

import pytest
import torch
from torchrl.data import Bounded
from torchrl.envs import ParallelEnv, SerialEnv

from drone_torchrl.envs import DroneEnv, make_env

WORKERS, BATCH, T = 2, 3, 12


def _actions():
    # Mean thrust 0.3 per motor: drones sink and hit the floor within T steps, so the rollouts
    # cross auto-resets inside the sub-envs.
    gen = torch.Generator().manual_seed(0)
    return [0.6 * torch.rand(WORKERS, BATCH, 2, generator=gen) for _ in range(T)]


def _sequence_policy(actions):
    it = iter(actions)
    return lambda td: td.set("action", next(it).clone())


def _rollout(env):
    env.set_seed(17)
    return env.rollout(T, _sequence_policy(_actions()), break_when_any_done=False)


@pytest.fixture(scope="module")
def serial_rollout():
    env = SerialEnv(WORKERS, partial(DroneEnv, batch_size=[BATCH]))
    try:
        yield _rollout(env)
    finally:
        env.close(raise_if_closed=False)


def test_serial_env_rollout_shape(serial_rollout):
    td = serial_rollout
    assert td.batch_size == (WORKERS, BATCH, T)
    assert td["next", "observation"].shape == (WORKERS, BATCH, T, 6)
    assert td["next", "step_count"].shape == (WORKERS, BATCH, T, 1)
    assert td["next", "done"].any(), "the rollout should cross at least one auto-reset"
    # each done sub-env restarts: the root step_count after a done step is 0
    done = td["next", "done"][..., :-1, 0]
    assert (td["step_count"][..., 1:, 0][done] == 0).all()
    # the two workers are seeded differently (seed, then TorchRL's next seed)
    assert not torch.equal(td["observation"][0, :, 0], td["observation"][1, :, 0])


def test_parallel_env_matches_serial_env(serial_rollout):
    env = ParallelEnv(WORKERS, partial(DroneEnv, batch_size=[BATCH]), mp_start_method="spawn")
    try:
        assert env.batch_size == (WORKERS, BATCH)
        td = _rollout(env)
    finally:
        env.close(raise_if_closed=False)
    assert td.batch_size == (WORKERS, BATCH, T)
    # Same seeds (both chain TorchRL's seed_generator over the workers) and same actions:
    # the same trajectories, bit for bit.
    for key in [
        "observation",
        ("next", "observation"),
        ("next", "reward"),
        ("next", "done"),
        ("next", "step_count"),
    ]:
        assert torch.equal(td[key], serial_rollout[key]), key


def test_make_env_native():
    env = make_env(4)
    assert type(env) is DroneEnv and env.batch_size == (4,)
    env = make_env()
    assert type(env) is DroneEnv and env.batch_size == ()
    env = make_env(2, max_thrust=1.0, reset_mode="air", max_steps=7)
    assert isinstance(env.action_spec, Bounded)
    assert (env.reset_mode, env.max_steps, env.max_thrust) == ("air", 7, 1.0)


def test_make_env_serial():
    env = make_env(num_envs=3, num_workers=2, parallel="serial", max_steps=9)
    try:
        assert type(env) is SerialEnv and env.batch_size == (2, 3)
        td = env.rollout(3, _sequence_policy([torch.full((2, 3, 2), 0.5)] * 3))
        assert td.batch_size == (2, 3, 3)
        assert all(sub.max_steps == 9 for sub in env._envs)
    finally:
        env.close(raise_if_closed=False)
    env = make_env(None, 1, "serial")
    assert env.batch_size == (1,)
    env.close(raise_if_closed=False)


def test_make_env_process_is_not_started():
    # The ParallelEnv object is built (types and shapes from a probe env) but no worker is started.
    env = make_env(num_envs=3, num_workers=2)
    try:
        assert type(env) is ParallelEnv and env.batch_size == (2, 3)
        assert env.is_closed
    finally:
        env.close(raise_if_closed=False)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"num_envs": 0}, "num_envs"),
        ({"num_envs": -2}, "num_envs"),
        ({"num_envs": 1.5}, "num_envs"),
        ({"num_envs": True}, "num_envs"),
        ({"num_envs": "4"}, "num_envs"),
        ({"num_workers": -1}, "num_workers"),
        ({"num_workers": 1.0}, "num_workers"),
        ({"num_workers": True}, "num_workers"),
        ({"num_workers": 1, "parallel": "thread"}, "parallel"),
        ({"num_envs": 2, "num_workers": 2, "mass": -1.0}, "mass"),  # env args fail in this process
        ({"reset_mode": "x"}, "reset_mode"),
    ],
)
def test_make_env_validates(kwargs, name):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        make_env(**kwargs)
