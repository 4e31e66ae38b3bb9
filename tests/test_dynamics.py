"""The pure physics functions of ``drone_torchrl.envs.dynamics`` against the paper's model, numbers by hand.

Notation: g = 9.81, dt = 0.02, so g*dt = 0.1962 and g*dt^2 = 0.003924. With the default drone
(m = 1, motor_distance = 1): r = 0.5, I_yy = 2/5 * 1 * 0.25 = 0.1, r / I_yy = 5.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import DroneParams, TerminationCause

G, DT = 9.81, 0.02
REL = 1e-5  # float32 has ~7 significant digits; a few roundings per step


def state(x=0.0, x_dot=0.0, z=0.0, z_dot=0.0, alpha=0.0, alpha_dot=0.0, dtype=torch.float32):
    return torch.tensor([x, x_dot, z, z_dot, alpha, alpha_dot], dtype=dtype)


def act(a_l, a_r):
    return torch.tensor([a_l, a_r], dtype=torch.float32)


def approx(values, rel=REL, abs=1e-7):
    return pytest.approx(values, rel=rel, abs=abs)


# ----------------------------------------------------------------------------- parameters


def test_params_lever_arm_and_inertia():
    # r = motor_distance / 2; I_yy = 2/5 m r^2 (eq. 2.4)
    p = DroneParams(mass=2.0, motor_distance=0.5)
    assert p.lever_arm == pytest.approx(0.25)
    assert p.inertia == pytest.approx(0.4 * 2.0 * 0.25**2)  # = 0.05
    assert DroneParams().inertia == pytest.approx(0.1)
    assert DroneParams(mass=3.0, gravity=5.0).weight == pytest.approx(15.0)


# ----------------------------------------------------------------------------- integration


@pytest.mark.parametrize(
    "start",
    [state(), state(x=0.3, z=2.5), state(x=-1.0, z=3.9)],
    ids=["origin", "in-zone", "near-ceiling"],
)
def test_hover_is_an_equilibrium_when_level(start):
    # a_l = a_r = 0.5: T_l + T_r = m g, alpha = 0 -> x_ddot = -sin(0) g = 0, z_ddot = g - g = 0,
    # alpha_ddot = r/I (T_r - T_l) = 0. Every term is exact in float32, so the state is unchanged.
    nxt = dynamics.integrate(start, act(0.5, 0.5), DroneParams())
    assert torch.equal(nxt, start)


def test_hover_with_velocities_moves_positions_only():
    # Accelerations are zero (level, hover thrust), so velocities stay and each position moves by v dt.
    start = state(x=0.1, x_dot=0.5, z=2.0, z_dot=-0.25, alpha=0.0, alpha_dot=0.1)
    nxt = dynamics.integrate(start, act(0.5, 0.5), DroneParams())
    expected = [0.1 + 0.5 * DT, 0.5, 2.0 - 0.25 * DT, -0.25, 0.1 * DT, 0.1]
    assert nxt.tolist() == approx(expected)


def test_free_fall_one_step_is_semi_implicit():
    # Zero thrust: z_ddot = -g. z_dot_1 = -g dt = -0.1962; z_1 = 0 + z_dot_1 dt = -g dt^2 = -0.003924
    # (explicit Euler would leave z_1 = 0). x and alpha see no acceleration.
    start = state(x=0.005, alpha=-0.007)
    nxt = dynamics.integrate(start, act(0.0, 0.0), DroneParams())
    assert nxt.tolist() == approx([0.005, 0.0, -0.003924, -0.1962, -0.007, 0.0])


def test_pure_torque_non_default_mass_and_motor_distance():
    # m = 2, motor_distance = 0.5: r = 0.25, I_yy = 0.4 * 2 * 0.0625 = 0.05, r / I_yy = 5.
    # a = [0.25, 0.75]: T_l = 0.25 * 2 * 9.81 = 4.905, T_r = 14.715, T_r - T_l = 9.81
    # alpha_ddot = 5 * 9.81 = 49.05; alpha_dot_1 = 0.981; alpha_1 = 0.981 * 0.02 = 0.01962.
    # T_l + T_r = m g, alpha_0 = 0 -> z_ddot = 0 and x_ddot = 0.
    p = DroneParams(mass=2.0, motor_distance=0.5)
    nxt = dynamics.integrate(state(z=1.0), act(0.25, 0.75), p)
    assert nxt.tolist() == approx([0.0, 0.0, 1.0, 0.0, 0.01962, 0.981], abs=1e-6)
    # The mirror image turns the other way (a_l > a_r -> clockwise, alpha_ddot < 0).
    mirrored = dynamics.integrate(state(z=1.0), act(0.75, 0.25), p)
    assert mirrored[dynamics.ALPHA_DOT].item() == pytest.approx(-0.981, rel=REL)


def test_pure_torque_default_drone():
    # r / I_yy = 5; a = [0.4, 0.6]: T_r - T_l = 0.2 * 9.81 = 1.962 -> alpha_ddot = 9.81
    # alpha_dot_1 = 0.1962, alpha_1 = 0.003924.
    nxt = dynamics.integrate(state(z=2.0), act(0.4, 0.6), DroneParams())
    assert nxt[dynamics.ALPHA_DOT].item() == pytest.approx(0.1962, rel=REL)
    assert nxt[dynamics.ALPHA].item() == pytest.approx(0.003924, rel=REL)


@pytest.mark.parametrize("alpha", [0.1, -0.1, 0.5])
def test_tilt_pushes_against_the_roll(alpha):
    # x_ddot = sin(-alpha) (T_l + T_r) / m: alpha > 0 (counter-clockwise) with positive thrust
    # accelerates towards -x. With hover thrust, x_ddot = -sin(alpha) g and
    # z_ddot = cos(alpha) g - g; alpha_ddot = 0.
    nxt = dynamics.integrate(state(z=2.0, alpha=alpha), act(0.5, 0.5), DroneParams())
    x_ddot = -math.sin(alpha) * G
    z_ddot = math.cos(alpha) * G - G
    assert math.copysign(1.0, nxt[dynamics.X_DOT].item()) == -math.copysign(1.0, alpha)
    expected = [x_ddot * DT * DT, x_ddot * DT, 2.0 + z_ddot * DT * DT, z_ddot * DT, alpha, 0.0]
    assert nxt.tolist() == approx(expected, abs=1e-6)


def test_semi_implicit_order_over_two_steps():
    # a = [1, 1] (twice the weight) from rest at z = 1: z_ddot = 2g - g = +g.
    #   step 1: z_dot = 0.1962,  z = 1 + 0.1962 * 0.02 = 1.003924
    #   step 2: z_dot = 0.3924,  z = 1.003924 + 0.3924 * 0.02 = 1.011772
    # (explicit Euler would give z = 1.0, then 1.003924.)
    p = DroneParams()
    s1 = dynamics.integrate(state(z=1.0), act(1.0, 1.0), p)
    s2 = dynamics.integrate(s1, act(1.0, 1.0), p)
    assert [s1[dynamics.Z].item(), s1[dynamics.Z_DOT].item()] == approx([1.003924, 0.1962])
    assert [s2[dynamics.Z].item(), s2[dynamics.Z_DOT].item()] == approx([1.011772, 0.3924])


def test_accelerations_use_the_state_before_the_step():
    # Torque a = [0.4, 0.6] (alpha_ddot = 9.81, total thrust = m g) twice from rest, level, z = 2:
    #   step 1: alpha_dot = 0.1962, alpha = 0.003924; x_ddot uses alpha_0 = 0 -> x stays 0.
    #   step 2: alpha_dot = 0.3924, alpha = 0.003924 + 0.007848 = 0.011772;
    #           x_ddot = -sin(0.003924) * 9.81 = -0.0384939 (uses alpha_1, not alpha_2)
    #           x_dot = -0.000769878, x = -1.539757e-05.
    p = DroneParams()
    s1 = dynamics.integrate(state(z=2.0), act(0.4, 0.6), p)
    assert s1[dynamics.X].item() == 0.0 and s1[dynamics.X_DOT].item() == 0.0
    s2 = dynamics.integrate(s1, act(0.4, 0.6), p)
    x_ddot = -math.sin(0.003924) * G
    assert s2[dynamics.ALPHA].item() == pytest.approx(0.011772, rel=REL)
    assert s2[dynamics.X_DOT].item() == pytest.approx(x_ddot * DT, rel=1e-4)
    assert s2[dynamics.X].item() == pytest.approx(x_ddot * DT * DT, rel=1e-4)


def test_gravity_dt_and_mass_arguments_are_used():
    # g = 5, dt = 0.1, m = 3, motor_distance = 2 (r = 1, I_yy = 0.4 * 3 * 1 = 1.2).
    p = DroneParams(mass=3.0, motor_distance=2.0, gravity=5.0, dt=0.1)
    # free fall: z_dot = -5 * 0.1 = -0.5, z = -0.5 * 0.1 = -0.05
    fall = dynamics.integrate(state(z=1.0), act(0.0, 0.0), p)
    assert [fall[dynamics.Z].item(), fall[dynamics.Z_DOT].item()] == approx([0.95, -0.5])
    # a = [1, 1]: T = 2 m g, z_ddot = 2 * 5 - 5 = +5 whatever m (thrust is a fraction of the weight)
    up = dynamics.integrate(state(z=1.0), act(1.0, 1.0), p)
    assert [up[dynamics.Z].item(), up[dynamics.Z_DOT].item()] == approx([1.05, 0.5])
    # a = [0, 1]: T_r - T_l = 15 N, alpha_ddot = r / I (T_r - T_l) = 1 / 1.2 * 15 = 12.5
    # alpha_dot = 1.25, alpha = 0.125; T_l + T_r = m g -> z_ddot = 0.
    spin = dynamics.integrate(state(z=1.0), act(0.0, 1.0), p)
    assert spin.tolist() == approx([0.0, 0.0, 1.0, 0.0, 0.125, 1.25], abs=1e-6)
    # hover stays an equilibrium for any mass (T = m g, a = 0.5 + 0.5)
    hover = dynamics.integrate(state(z=1.0), act(0.5, 0.5), p)
    assert hover.tolist() == approx(state(z=1.0).tolist(), abs=1e-6)


def test_zero_gravity_means_zero_thrust():
    # Thrust is a fraction of the weight m g; with g = 0 nothing accelerates.
    p = DroneParams(gravity=0.0)
    start = state(x=0.1, x_dot=1.0, z=2.0, alpha=0.2)
    nxt = dynamics.integrate(start, act(3.0, -1.0), p)
    assert nxt.tolist() == approx([0.1 + DT, 1.0, 2.0, 0.0, 0.2, 0.0])


def test_integrate_is_batched_and_elementwise():
    starts = torch.stack([state(z=1.0), state(z=2.0, alpha=0.1), state(x=0.5, alpha_dot=1.0)])
    actions = torch.stack([act(0.0, 0.0), act(0.5, 0.5), act(0.4, 0.6)])
    batched = dynamics.integrate(starts.reshape(3, 1, 6), actions.reshape(3, 1, 2), DroneParams())
    assert batched.shape == (3, 1, 6)
    for i in range(3):
        single = dynamics.integrate(starts[i], actions[i], DroneParams())
        assert batched[i, 0].tolist() == approx(single.tolist(), rel=1e-6)


# ----------------------------------------------------------------------------- action clamp


def test_clamp_action():
    a = torch.tensor([[2.0, -1.0], [0.3, 0.7]])
    assert dynamics.clamp_action(a, None) is a  # unbounded: untouched, negative thrust allowed
    assert torch.equal(dynamics.clamp_action(a, 1.0), torch.tensor([[1.0, 0.0], [0.3, 0.7]]))
    assert torch.equal(dynamics.clamp_action(a, 0.5), torch.tensor([[0.5, 0.0], [0.3, 0.5]]))


def test_step_clamps_when_bounded_and_not_when_unbounded():
    # Bounded [0, 1]: [2, -1] acts as [1, 0] (alpha_ddot = 5 * 9.81 = 49.05, z_ddot = 0).
    start = state(z=2.0)
    bounded = DroneParams(max_thrust=1.0)
    s_clamped, _, _ = dynamics.step(start, act(2.0, -1.0), bounded)
    s_ref, _, _ = dynamics.step(start, act(1.0, 0.0), bounded)
    assert torch.equal(s_clamped, s_ref)
    # Unbounded: [-0.5, -0.5] is applied: z_ddot = -g - g = -19.62 -> z_dot = -0.3924
    s_neg, _, _ = dynamics.step(start, act(-0.5, -0.5), DroneParams())
    assert s_neg[dynamics.Z_DOT].item() == pytest.approx(-0.3924, rel=REL)


# ----------------------------------------------------------------------------- termination


def cause_of(dtype=torch.float32, floor_tolerance=0.05, **kw) -> int:
    params = DroneParams(floor_tolerance=floor_tolerance)
    return int(dynamics.termination_cause(state(dtype=dtype, **kw), params))


def f32_next(value: float, direction: float) -> float:
    """The float32 neighbour of float32(value) towards ``direction``."""
    v = torch.tensor(value, dtype=torch.float32)
    return torch.nextafter(v, torch.tensor(direction, dtype=torch.float32)).item()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "kw",
    [
        # x = +-2.0, z = 0, z = 4.0 are exact in float32 and float64.
        {"x": 2.0, "z": 1.0},
        {"x": -2.0, "z": 1.0},
        {"z": 4.0},
        {"z": 0.0},
        # z = -0.05 and alpha = +-pi/3 are not representable; the comparison is done in the state's
        # dtype, so the nearest float32 (resp. float64) to the bound is on the bound.
        {"z": -0.05},
        {"z": 1.0, "alpha": math.pi / 3},
        {"z": 1.0, "alpha": -math.pi / 3},
        {"x": -2.0, "z": 4.0, "alpha": math.pi / 3},  # every bound at once, still inside
        {"z": 1.0, "x_dot": 1e6, "z_dot": -1e6, "alpha_dot": 1e6},  # velocities are unbounded
    ],
)
def test_bounds_are_inclusive(kw, dtype):
    assert cause_of(dtype=dtype, **kw) == TerminationCause.NONE


@pytest.mark.parametrize(
    "kw, cause",
    [
        ({"x": f32_next(2.0, 3.0), "z": 1.0}, TerminationCause.OUT_X),
        ({"x": f32_next(-2.0, -3.0), "z": 1.0}, TerminationCause.OUT_X),
        ({"z": f32_next(-0.05, -1.0)}, TerminationCause.FLOOR),
        ({"z": -0.0501}, TerminationCause.FLOOR),
        ({"z": f32_next(4.0, 5.0)}, TerminationCause.CEILING),
        ({"z": 1.0, "alpha": f32_next(math.pi / 3, 2.0)}, TerminationCause.TILT),
        ({"z": 1.0, "alpha": f32_next(-math.pi / 3, -2.0)}, TerminationCause.TILT),
    ],
)
def test_just_outside_each_bound(kw, cause):
    assert cause_of(**kw) == cause


def test_bounds_float64_exactly_on_and_beyond():
    assert cause_of(dtype=torch.float64, z=math.nextafter(-0.05, -1)) == TerminationCause.FLOOR
    assert cause_of(dtype=torch.float64, z=1.0, alpha=math.nextafter(math.pi / 3, 2)) == TerminationCause.TILT


def test_floor_tolerance_zero_ends_below_zero():
    assert cause_of(floor_tolerance=0.0, z=0.0) == TerminationCause.NONE
    assert cause_of(floor_tolerance=0.0, z=f32_next(0.0, -1.0)) == TerminationCause.FLOOR
    assert cause_of(floor_tolerance=0.0, z=-0.001) == TerminationCause.FLOOR
    # a larger tolerance moves the floor down
    assert cause_of(floor_tolerance=0.2, z=-0.2) == TerminationCause.NONE
    assert cause_of(floor_tolerance=0.2, z=-0.21) == TerminationCause.FLOOR


def _lowest_code_cases():
    # Every combination of (x out or not) x (z floor / ceiling / inside) x (alpha out or not).
    cases = []
    for x_out, z_case, tilt in itertools.product([False, True], ["in", "floor", "ceiling"], [False, True]):
        kw = {"x": -3.0 if x_out else 0.0, "z": {"in": 1.0, "floor": -1.0, "ceiling": 5.0}[z_case]}
        kw["alpha"] = 1.5 if tilt else 0.0
        codes = [
            c for c, on in [(1, x_out), (2, z_case == "floor"), (3, z_case == "ceiling"), (4, tilt)] if on
        ]
        cases.append((kw, min(codes, default=0)))
    return cases


def test_lowest_code_wins_batched():
    cases = _lowest_code_cases()
    states = torch.stack([state(**kw) for kw, _ in cases]).reshape(3, 4, 6)
    causes = dynamics.termination_cause(states, DroneParams())
    assert causes.shape == (3, 4) and causes.dtype == torch.int64
    assert causes.flatten().tolist() == [c for _, c in cases]
    # spot checks of the rule written out
    assert [c for _, c in cases].count(1) == 6  # OUT_X beats all
    assert cause_of(z=-1.0, alpha=1.5) == TerminationCause.FLOOR
    assert cause_of(z=5.0, alpha=-1.5) == TerminationCause.CEILING


# ----------------------------------------------------------------------------- reward and zone


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "kw, inside",
    [
        ({"z": 2.7}, True),
        ({"x": 0.8, "z": 2.7}, True),
        ({"x": -0.8, "z": 2.7}, True),
        ({"z": 2.2}, True),
        ({"z": 3.2}, True),
        ({"x": 0.8, "z": 3.2, "alpha": -math.pi / 3}, True),
        ({"x": 0.81, "z": 2.7}, False),
        ({"x": -0.81, "z": 2.7}, False),
        ({"z": 2.19}, False),
        ({"z": 3.21}, False),
        ({"z": 0.0}, False),
    ],
)
def test_target_zone_inclusive(kw, inside, dtype):
    s = state(dtype=dtype, **kw)
    paper = DroneParams()
    assert bool(dynamics.in_target_zone(s, paper)) is inside
    r = dynamics.reward(s, torch.tensor(False), paper)
    assert r.item() == (10.0 if inside else 1.0)
    assert r.dtype == dtype
    # the terminating step earns 0, inside the zone or not
    assert dynamics.reward(s, torch.tensor(True), paper).item() == 0.0


def test_target_zone_just_outside_float32():
    paper = DroneParams()
    assert not bool(dynamics.in_target_zone(state(x=f32_next(0.8, 1.0), z=2.7), paper))
    assert not bool(dynamics.in_target_zone(state(z=f32_next(2.2, 0.0)), paper))
    assert not bool(dynamics.in_target_zone(state(z=f32_next(3.2, 4.0)), paper))


def test_step_returns_state_reward_cause():
    # Two drones: hover in the zone (reward 10, no cause) and free fall from z = -0.049:
    # z_1 = -0.049 - 0.003924 = -0.052924 < -0.05 -> FLOOR, reward 0.
    starts = torch.stack([state(z=2.7), state(z=-0.049)])
    actions = torch.stack([act(0.5, 0.5), act(0.0, 0.0)])
    nxt, rew, cause = dynamics.step(starts, actions, DroneParams())
    assert nxt.shape == (2, 6) and rew.shape == (2,) and cause.shape == (2,)
    assert rew.dtype == torch.float32 and cause.dtype == torch.int64
    assert rew.tolist() == [10.0, 0.0]
    assert cause.tolist() == [0, 2]
    assert nxt[1, dynamics.Z].item() == pytest.approx(-0.052924, rel=REL)
    # outside the zone, not terminated: reward 1 (on the floor at hover)
    _, rew1, cause1 = dynamics.step(state(), act(0.5, 0.5), DroneParams())
    assert (rew1.item(), cause1.item()) == (1.0, 0)


# ----------------------------------------------------------------------------- initial states


def test_initial_state_floor_range():
    s = dynamics.initial_state((4000,), "floor", torch.Generator().manual_seed(1))
    assert s.shape == (4000, 6) and s.dtype == torch.float32
    for i in (dynamics.X_DOT, dynamics.Z, dynamics.Z_DOT, dynamics.ALPHA_DOT):
        assert torch.equal(s[:, i], torch.zeros(4000))
    for i in (dynamics.X, dynamics.ALPHA):
        assert s[:, i].abs().max().item() <= 0.01
        # uniform over the whole +-0.01, not a narrower range
        assert s[:, i].max().item() > 0.0099 and s[:, i].min().item() < -0.0099


def test_initial_state_air_range():
    s = dynamics.initial_state((4000,), "air", torch.Generator().manual_seed(2))
    centre = torch.tensor([0.0, 0.0, 2.7, 0.0, 0.0, 0.0])
    dev = s - centre
    # 2.7 +- 0.01 is rounded to float32 (ulp 2.4e-7 near 2.7)
    assert dev.abs().max().item() <= 0.01 + 1e-6
    assert (dev.max(0).values > 0.0099).all() and (dev.min(0).values < -0.0099).all()


def test_initial_state_is_seeded_and_layout_independent():
    def draw(shape, seed=5):
        return dynamics.initial_state(shape, "air", torch.Generator().manual_seed(seed))

    assert torch.equal(draw((4,)), draw((4,)))
    assert torch.equal(draw((2, 2)).reshape(4, 6), draw((4,)))
    assert torch.equal(draw(()), draw((1,))[0])
    assert torch.equal(draw(()), draw((3,))[0])
    assert not torch.equal(draw((4,)), draw((4,), seed=6))


def test_initial_state_rejects_unknown_mode():
    with pytest.raises(ValueError, match="reset_mode"):
        dynamics.initial_state((2,), "x")


def test_start_states_are_drawn_on_the_generators_device_then_moved():
    """A seed gives the same start states on every device: the numbers come from the (CPU)
    generator and only then move to the env's device (here the meta device stands in for a GPU)."""
    generator = torch.Generator().manual_seed(3)
    states = dynamics.initial_state((4,), "air", generator, device="meta")
    assert states.device.type == "meta" and states.shape == (4, dynamics.STATE_DIM)
    reference = torch.Generator().manual_seed(3)
    torch.rand((4, dynamics.STATE_DIM), generator=reference)  # the same draw on the CPU
    assert torch.equal(generator.get_state(), reference.get_state())
