"""The PID controller (drone_torchrl.envs.pid) and its tuner (drone_torchrl.tuning)."""

from __future__ import annotations

import pytest
import torch

from drone_torchrl.envs.dynamics import DroneParams
from drone_torchrl.envs.heuristic import PDGains, pd_action
from drone_torchrl.envs.pid import PIDController, PIDGains

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
