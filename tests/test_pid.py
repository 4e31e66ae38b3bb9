"""The PID controller and its tuner (``benchmarks/pid_tuning.py``, benchmarks/disturbances.py's baseline)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

from drone_torchrl.envs.dynamics import DroneParams
from drone_torchrl.envs.heuristic import PDGains, pd_action


def _load_benchmark_module():
    spec = importlib.util.spec_from_file_location(
        "pid_tuning", Path(__file__).resolve().parents[1] / "benchmarks" / "pid_tuning.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up while it loads
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[spec.name]
    return module


pid_tuning = _load_benchmark_module()
PIDController, PIDGains = pid_tuning.PIDController, pid_tuning.PIDGains
PARAMS = DroneParams(max_thrust=1.0)


def test_without_integral_gains_it_is_the_pd_controller():
    obs = torch.randn(64, 6) * torch.tensor([0.5, 0.5, 1.0, 0.5, 0.2, 0.5]) + torch.tensor(
        [0, 0, 2.0, 0, 0, 0]
    )
    pid = PIDController(PARAMS)
    for _ in range(3):  # the integrals grow but are multiplied by ki = 0
        torch.testing.assert_close(pid.act(obs), pd_action(obs, PARAMS), rtol=0, atol=0)


def test_the_integral_moves_the_set_point_by_ki_over_kp_times_the_accumulated_error():
    gains = PIDGains(ki_x=0.2, ki_z=8.0)
    pid = PIDController(PARAMS, gains)
    obs = torch.tensor([[0.3, 0.0, 2.5, 0.0, 0.0, 0.0]])
    pid.act(obs)
    pid.act(obs)
    # Two steps of error (0 - 0.3, 2.7 - 2.5) times dt = 0.02 each, then the third command uses them.
    ix, iz = 2 * -0.3 * 0.02, 2 * 0.2 * 0.02
    assert pid.integral[0].tolist() == pytest.approx([ix, iz], rel=1e-5)
    moved = PDGains(x_target=0.2 / 0.4 * ix, z_target=2.7 + 8.0 / 64.0 * iz)
    torch.testing.assert_close(pid.act(obs), pd_action(obs, PARAMS, moved), rtol=1e-6, atol=1e-7)
    pid.reset()
    assert pid.integral is None


def test_the_integrals_are_clamped():
    pid = PIDController(PARAMS, PIDGains(ki_x=0.1, integral_limit=0.05))
    obs = torch.tensor([[1.5, 0.0, 2.7, 0.0, 0.0, 0.0]])
    for _ in range(10):
        pid.act(obs)
    assert pid.integral[0, 0].item() == pytest.approx(-0.05)


def test_the_tuner_keeps_the_pd_gains_unless_a_candidate_flies_better():
    """Candidate 0 of the first round is the nominal PD: the result is never worse than PD."""
    space = pid_tuning.SearchSpace(candidates=4, rounds=2, episodes=3)
    gains, record = pid_tuning.tune_pid({"max_thrust": 1.0, "max_steps": 40}, space)
    assert len(record["rounds"]) == 2
    assert record["rounds"][0] >= record["nominal_return"]
    assert record["rounds"][1] >= record["rounds"][0]  # each round keeps the best so far as candidate 0
    assert isinstance(gains.ki_x, float) and gains.pd.kp_z == pytest.approx(
        record["gains"]["altitude_frequency"] ** 2
    )
