"""The best achievable return (drone_torchrl.optimum): the bound against a hand derivation, the
replay that earns it through the env's own dynamics, and policies that cannot beat it.

The hand derivation (docs/optimum.md) for the bounded drone (each motor <= 1 x weight, so the
vertical acceleration lies in [-g, +g]), in units of g dt^2 = 3.924 mm for heights and g dt for
velocities:
- full thrust for k steps reaches z_k = k (k + 1) / 2; 2.2 m is 560.65 units: first at k = 33;
- 28 steps of full thrust, then none: in the zone from step 35 (z = 574 units = 2.2524 m), apex
  28^2 = 784 units = 3.0764 m at step 56; 29 steps would overshoot (841 units = 3.300 m);
- entering at step 34 and staying is impossible (the zone is 254.84 units high: an entry speed u
  overshoots by u(u - 1)/2 or more, so u <= 23.08; from rest, 34 steps reach at most 559.5 units
  with that end speed, less than 560.65).
So 266 steps in the zone from step 35 on: 34 * 1 + 266 * 10 = 2694.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from drone_torchrl.envs import DroneEnv, dynamics
from drone_torchrl.envs.dynamics import DroneParams
from drone_torchrl.episodes import episode_stats
from drone_torchrl.evaluation import evaluate_pd, reference_optimum
from drone_torchrl.optimum import (
    earliest_zone_step,
    env_optimum,
    fly_plan,
    max_zone_steps,
    optimum,
    zone_margin,
)

BOUNDED = DroneParams(max_thrust=1.0)
ZONE_Z_MIN, ZONE_Z_MAX = BOUNDED.zone_z_min, BOUNDED.zone_z_max  # the zone of the default arena
STEPS = 300
EPISODES, SEED = 100, 0  # drone-eval's seeded starts
UNIT = BOUNDED.gravity * BOUNDED.dt**2  # g dt^2: the height one step of g adds to one step of climb


def _floor_starts(**env_kwargs) -> torch.Tensor:
    env = DroneEnv(batch_size=[EPISODES], **env_kwargs)
    env.set_seed(SEED)
    return env.reset().get("observation")


def _fly_vertical(collective: list[float], params: DroneParams = BOUNDED) -> np.ndarray:
    """Heights after each step of a level drone (float64) given vertical thrusts, through dynamics.step."""
    state = torch.zeros(1, dynamics.STATE_DIM, dtype=torch.float64)
    heights = []
    for c in collective:
        action = torch.full((1, dynamics.ACTION_DIM), c / dynamics.ACTION_DIM, dtype=torch.float64)
        state, _, cause = dynamics.step(state, action, params)
        assert int(cause) == 0
        heights.append(float(state[0, dynamics.Z]))
    return np.array(heights)


def test_full_thrust_climb_by_hand():
    """z_k = k (k + 1) / 2 units: the zone's floor (2.2 m) is first reached at step 33."""
    z = _fly_vertical([2.0] * 40)
    k = np.arange(1, 41)
    np.testing.assert_allclose(z, UNIT * k * (k + 1) / 2, rtol=1e-12)
    assert int(np.argmax(z >= ZONE_Z_MIN)) + 1 == 33
    assert z[32] == pytest.approx(2.201364, abs=1e-6) and z[31] == pytest.approx(2.071872, abs=1e-6)


def test_bang_bang_plan_by_hand_earns_the_bound():
    """28 steps at full thrust, then none until the apex (step 56), then hover: the zone from step 35."""
    plan = [2.0] * 28 + [0.0] * 28 + [1.0] * (STEPS - 56)
    z = _fly_vertical(plan)
    in_zone = (z >= ZONE_Z_MIN) & (z <= ZONE_Z_MAX)
    assert int(np.argmax(in_zone)) + 1 == 35 and in_zone[34:].all()
    assert z[34] == pytest.approx(574 * UNIT) and z.max() == pytest.approx(784 * UNIT)  # 2.2524, 3.0764 m
    assert 29**2 * UNIT > ZONE_Z_MAX  # one more step of full thrust overshoots
    # Entering at 34 and staying: the entry speed u (units of g dt) overshoots by at least u (u - 1) / 2.
    height = (ZONE_Z_MAX - ZONE_Z_MIN) / UNIT
    u = (height + 0.5 * 23 * 24) / 23  # the largest u with 23 u - 23 * 24 / 2 <= height (23 <= u < 24)
    assert 23 * u - 23 * 24 / 2 == pytest.approx(height) and 23 <= u < 24
    reach = sum(min(i, u + 34 - i) for i in range(1, 35))  # speed <= i, and <= u + (34 - i)
    assert reach == pytest.approx(559.48, abs=0.01)
    zone_floor = ZONE_Z_MIN / UNIT
    assert zone_floor == pytest.approx(560.652, abs=1e-3)
    assert reach < zone_floor  # the zone's floor is out of reach at step 34


def test_the_bound_for_the_bounded_floor_starts():
    """The LPs and the MILP agree with the hand derivation: 266 zone steps from step 35, 2694."""
    best = optimum(BOUNDED, STEPS)
    assert (best.first_zone_step, best.zone_steps, best.best_return, best.exact) == (35, 266, 2694.0, True)
    assert best.plan.margin == pytest.approx(0.0666, abs=1e-4)  # the plan stays 6.7 cm inside the zone
    # Holding the zone from step 34 misses it by 3 mm (the LP's largest margin is negative).
    assert zone_margin(BOUNDED, STEPS, 34).margin == pytest.approx(-0.00302, abs=1e-5)
    assert zone_margin(BOUNDED, STEPS, 33).margin < zone_margin(BOUNDED, STEPS, 34).margin
    # Mass does not enter (thrust is a fraction of the weight); the floor tolerance does not matter here.
    for other in (DroneParams(max_thrust=1.0, mass=3.0), DroneParams(max_thrust=1.0, floor_tolerance=0.0)):
        assert optimum(other, STEPS).best_return == 2694.0
    # A short episode that cannot reach the zone: survive every step, nothing more.
    assert max_zone_steps(BOUNDED, 32) == 0 and earliest_zone_step(BOUNDED, 32) is None
    # More thrust, earlier entry: the bound grows with max_thrust.
    returns = [optimum(DroneParams(max_thrust=a), STEPS).best_return for a in (0.75, 1.0, 1.5)]
    assert returns == sorted(returns) and len(set(returns)) == 3


def test_replay_earns_the_bound_on_every_start():
    """drone-eval's 100 floor starts (x, alpha in +-0.01): the plan through dynamics.step, then PD."""
    starts = _floor_starts(max_thrust=1.0)
    assert float(starts[:, dynamics.ALPHA].abs().max()) > 0.009  # really tilted starts
    episodes, plan = fly_plan(starts, BOUNDED, STEPS)
    stats = episode_stats(episodes)
    assert plan.first_zone_step == 35 and plan.margin > 0.06
    assert torch.all(stats["return"] == 2694.0)
    assert torch.all(stats["first_zone_step"] == 35)
    assert torch.all(stats["termination_cause"] == int(dynamics.TerminationCause.NONE))
    states = episodes.states[:, 1:]
    climb = states[:, : plan.apex_step]
    # Up to the apex: the tilt never changes (equal thrusts), the heights are the plan's (float32).
    assert torch.all(climb[..., dynamics.ALPHA] == starts[:, None, dynamics.ALPHA])
    np.testing.assert_allclose(
        climb[..., dynamics.Z].double(), np.broadcast_to(plan.z[: plan.apex_step], climb.shape[:2]), atol=1e-5
    )
    assert float(states[..., dynamics.X].abs().max()) < 0.2
    assert float(states[..., dynamics.ALPHA].abs().max()) < 0.1
    assert float(episodes.action.max()) <= BOUNDED.max_thrust and float(episodes.action.min()) >= 0.0


def test_no_policy_beats_the_bound():
    """PD (2685, in the zone from step 36) stays below 2694 on every start, as does a crude climb."""
    best = reference_optimum({"max_thrust": 1.0})
    pd = evaluate_pd({"max_thrust": 1.0}, episodes=EPISODES, seed=SEED)
    assert pd["return_mean"] == 2685.0 and pd["return_min"] <= best.best_return
    assert pd["first_zone_step_max"] >= best.first_zone_step
    # One step more of full thrust than the hand plan: faster in, but it overshoots the zone.
    z = _fly_vertical([2.0] * 29 + [0.0] * 29 + [1.0] * (STEPS - 58))
    in_zone = (z >= ZONE_Z_MIN) & (z <= ZONE_Z_MAX)
    assert in_zone.sum() < best.zone_steps


def test_unbounded_thrust_reaches_the_ceiling():
    """Negative and unbounded thrust: a pulse on step 1 puts the drone in the zone; the bound is 3000."""
    params = DroneParams()
    best = optimum(params, STEPS)
    assert (best.first_zone_step, best.best_return) == (1, 10.0 * STEPS)
    # The smallest pulse that lifts the drone to the zone's floor in one step: c_1 >= 1 + 2.2 / (g dt^2).
    assert best.plan.collective[0] / 2 >= (1 + ZONE_Z_MIN / UNIT) / 2 == pytest.approx(280.8, abs=0.1)
    episodes, _ = fly_plan(_floor_starts(), params, STEPS)
    stats = episode_stats(episodes)
    assert torch.all(stats["return"] == 10.0 * STEPS) and torch.all(stats["first_zone_step"] == 1)
    assert reference_optimum({}) is None  # drone-eval shows no optimum fraction: PD is the reference


def test_air_starts_and_thrust_below_hover():
    """Air starts (in the zone at reset) can hold it from step 1: the bound is the ceiling. Below the
    hover thrust the bound is not derived."""
    assert env_optimum(BOUNDED, STEPS, "air").best_return == 10.0 * STEPS
    assert env_optimum(DroneParams(max_thrust=0.4), STEPS, "floor") is None
    hover = env_optimum(DroneParams(max_thrust=0.5), STEPS, "floor")  # hovers, never climbs
    assert (hover.zone_steps, hover.best_return, hover.exact) == (0, 1.0 * STEPS, True)


def test_flipped_gravity_would_fail(monkeypatch):
    """A sign error in the recursion is caught: gravity pushing up puts the zone within reach sooner."""
    from drone_torchrl import optimum as module

    real = module._recursion

    def flipped(params, steps, start, extra):
        a, b = real(params, steps, start, extra)
        b[:steps] = -b[:steps] + 2 * start[1] * (np.arange(steps) == 0)  # +g dt instead of -g dt
        return a, b

    monkeypatch.setattr(module, "_recursion", flipped)
    assert optimum(BOUNDED, STEPS).best_return != 2694.0


def test_drone_eval_says_what_the_optimum_is():
    """drone-eval's line about the optimum: the bound with bounded thrust, the ceiling without."""
    from drone_torchrl.comparison import optimum_line
    from drone_torchrl.evaluation import summarize

    bounded = {"max_thrust": 1.0}
    line = optimum_line(bounded, reference_optimum(bounded), 3000.0)
    assert "is 2694 (in the zone from step 35, 266 of 300 steps" in line
    assert "ceiling 3000" in optimum_line({}, reference_optimum({}), 3000.0)
    stats = {
        "return": torch.tensor([2694.0, 2685.0]),
        "length": torch.tensor([300, 300]),
        "time_in_zone": torch.tensor([0.9, 0.9]),
        "negative_thrust_fraction": torch.zeros(2),
        "termination_cause": torch.zeros(2, dtype=torch.int64),
        "first_zone_step": torch.tensor([35, 36]),
        "thrust_mean": torch.full((2,), 0.5),
        "thrust_max": torch.ones(2),
    }
    assert summarize(stats, 3000.0, 2694.0)["pct_of_optimum"] == pytest.approx(100 * 2689.5 / 2694)
    assert math.isnan(summarize(stats, 3000.0)["pct_of_optimum"])
