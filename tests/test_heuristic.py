"""The PD hover controller (drone_torchrl.envs.heuristic): conventions, batching, and that it flies."""

from __future__ import annotations

import math

import pytest
import torch

from drone_torchrl.envs import DroneEnv, dynamics
from drone_torchrl.envs.drone_env import make_params
from drone_torchrl.envs.heuristic import PDController, PDGains, pd_action
from drone_torchrl.evaluation import evaluate_pd

BATCH = 16
SEED = 0
THRUST_SETTINGS = [None, 1.0]
# A PD law approaches its set point smoothly, not with the time-optimal bang-bang profile; it is
# allowed this many times the bang-bang climb time to enter the zone.
CLIMB_SLACK = 2.0


def bang_bang_entry_time(accel_up: float, accel_down: float, z_centre: float, z_entry: float) -> float:
    """Time to go from rest at z=0 into the zone (z >= z_entry) when flying the time-optimal profile
    that comes to rest at the zone centre: full ``accel_up`` up to the switch height, then full
    braking ``accel_down``. Solves the two constant-acceleration phases in closed form."""
    switch = z_centre * accel_down / (accel_up + accel_down)
    speed = math.sqrt(2.0 * accel_up * switch)
    t_up = speed / accel_up
    if z_entry <= switch:
        return math.sqrt(2.0 * z_entry / accel_up)
    rest = z_entry - switch
    return t_up + (speed - math.sqrt(speed**2 - 2.0 * accel_down * rest)) / accel_down


def entry_step_budget(max_thrust: float | None, gains: PDGains, env: DroneEnv) -> int:
    """Steps the controller may take to first enter the zone, derived from how fast it can climb.

    The vertical acceleration the controller can get is bounded by its own command limit
    ``max_accel_z`` and, with a thrust limit, by physics: at most ``(2 max_thrust - 1) g`` up
    (both motors full) and ``g`` down (motors off). The budget is ``CLIMB_SLACK`` times the
    bang-bang time under those bounds (about 26 steps unbounded, 37 steps with ``max_thrust=1``).
    """
    g = env.params.gravity
    accel_up, accel_down = gains.max_accel_z, gains.max_accel_z
    if max_thrust is not None:
        accel_up = min(accel_up, (2.0 * max_thrust - 1.0) * g)
        accel_down = min(accel_down, g)
    t = bang_bang_entry_time(accel_up, accel_down, env.params.zone_z_centre, env.params.zone_z_min)
    return math.ceil(CLIMB_SLACK * t / env.params.dt)


def return_threshold(budget: int, max_steps: int) -> float:
    """Return of an episode that spends ``budget`` steps outside the zone (reward 1), then the rest
    inside it (reward 10) with no termination."""
    return budget * dynamics.REWARD_ALIVE + (max_steps - budget) * dynamics.REWARD_IN_ZONE


def _rollout(env: DroneEnv) -> torch.Tensor:
    env.set_seed(SEED)
    with torch.no_grad():
        return env.rollout(env.max_steps, PDController(env.params), break_when_any_done=False)


@pytest.mark.parametrize("max_thrust", THRUST_SETTINGS)
def test_pd_climbs_into_zone_and_stays(max_thrust: float | None) -> None:
    env = DroneEnv(batch_size=[BATCH], max_thrust=max_thrust)
    td = _rollout(env)
    assert td.shape == (BATCH, env.max_steps)

    # No termination; the only done is the truncation on the last step.
    assert not td["next", "terminated"].any()
    done = td["next", "done"].squeeze(-1)
    assert done[:, -1].all() and not done[:, :-1].any()

    # Enters the zone within the budget and never leaves it afterwards.
    gains = PDGains()
    budget = entry_step_budget(max_thrust, gains, env)
    in_zone = dynamics.in_target_zone(td["next", "observation"], env.params)
    assert in_zone.any(-1).all()
    first = in_zone.to(torch.int64).argmax(-1)  # 0-based index of the first step ending in the zone
    assert int(first.max()) + 1 <= budget
    after_entry = torch.arange(env.max_steps) >= first.unsqueeze(-1)
    assert in_zone[after_entry].all()

    returns = td["next", "reward"].sum((-2, -1))
    assert (returns >= return_threshold(budget, env.max_steps)).all()

    if max_thrust is not None:
        assert (td["action"] >= 0).all() and (td["action"] <= max_thrust).all()


@pytest.mark.parametrize("batch_size", [[], [2, 3]])
def test_pd_controller_is_a_rollout_policy(batch_size: list[int]) -> None:
    env = DroneEnv(batch_size=batch_size, max_thrust=1.0)
    env.set_seed(SEED)
    with torch.no_grad():
        td = env.rollout(50, PDController(env.params))
    assert td.shape == (*batch_size, 50)
    assert td["action"].shape == (*batch_size, 50, dynamics.ACTION_DIM)
    assert not td["next", "done"].any()


def test_pd_action_is_batched_over_any_shape() -> None:
    params = make_params(max_thrust=1.0)
    observation = dynamics.initial_state((3, 4), "air", torch.Generator().manual_seed(SEED))
    observation[..., dynamics.X] += torch.linspace(-1.5, 1.5, 12).reshape(3, 4)
    observation[..., dynamics.Z] -= torch.linspace(0.0, 2.5, 12).reshape(3, 4)
    action = pd_action(observation, params)
    assert action.shape == (3, 4, dynamics.ACTION_DIM)
    flat = pd_action(observation.reshape(-1, dynamics.STATE_DIM), params)
    torch.testing.assert_close(action.reshape(-1, dynamics.ACTION_DIM), flat)
    single = torch.stack([pd_action(o, params) for o in observation.reshape(-1, dynamics.STATE_DIM)])
    torch.testing.assert_close(flat, single)


def test_pd_action_hovers_at_the_set_point() -> None:
    gains = PDGains()
    state = torch.zeros(dynamics.STATE_DIM)
    state[dynamics.X], state[dynamics.Z] = gains.x_target, make_params().zone_z_centre  # z_target None
    action = pd_action(state, make_params())
    torch.testing.assert_close(action, torch.tensor([0.5, 0.5]))
    # the set point follows the params' zone, unless the gains name one
    higher = make_params(zone_z_min=3.0, zone_z_max=3.6)
    state[dynamics.Z] = 3.3
    torch.testing.assert_close(pd_action(state, higher), torch.tensor([0.5, 0.5]))
    state[dynamics.Z] = 1.0
    torch.testing.assert_close(pd_action(state, higher, PDGains(z_target=1.0)), torch.tensor([0.5, 0.5]))


def test_pd_action_signs() -> None:
    """Left of the target the drone must tilt towards +x, i.e. to negative alpha: x_ddot =
    sin(-alpha) T/m, and alpha_ddot = r/I (T_r - T_l) < 0 needs T_r < T_l. Below the target it
    must push more than its weight."""
    params = make_params()
    gains = PDGains(z_target=params.zone_z_centre)
    state = torch.zeros(dynamics.STATE_DIM)
    state[dynamics.Z] = gains.z_target
    state[dynamics.X] = gains.x_target - 1.0
    a_l, a_r = pd_action(state, params).tolist()
    assert a_r < a_l
    state[dynamics.X] = gains.x_target + 1.0
    a_l, a_r = pd_action(state, params).tolist()
    assert a_r > a_l
    state[dynamics.X], state[dynamics.Z] = gains.x_target, gains.z_target - 1.0
    assert pd_action(state, params).sum() > 1.0


def test_pd_action_clipping_keeps_the_attitude_command() -> None:
    """With a thrust limit, a large climb demand plus a large attitude correction is clipped into
    [0, max_thrust] keeping the full thrust difference (attitude has priority)."""
    bounded, unbounded = make_params(max_thrust=1.0), make_params()
    state = torch.zeros(dynamics.STATE_DIM)
    state[dynamics.ALPHA] = 0.05  # tilted: a moderate corrective torque is needed
    unclipped = pd_action(state, unbounded)
    clipped = pd_action(state, bounded)
    assert unclipped.sum() > 2.0  # on the floor it wants more than both motors can give
    assert (clipped >= 0).all() and (clipped <= 1.0).all()
    torch.testing.assert_close(clipped[1] - clipped[0], unclipped[1] - unclipped[0])
    assert float(clipped.max()) == pytest.approx(1.0)


def test_evaluate_pd_summary() -> None:
    stats = evaluate_pd({"max_thrust": 1.0, "max_steps": 100}, episodes=4, seed=SEED)
    assert stats["terminated_fraction"] == 0.0
    assert stats["reached_fraction"] == 1.0
    assert stats["length_mean"] == 100.0
    assert 0.0 < stats["time_in_zone"] < 1.0
    assert stats["return_mean"] <= 100 * dynamics.REWARD_IN_ZONE
