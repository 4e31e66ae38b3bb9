"""``DroneEnv`` (the natively batched TorchRL env) against the environment's specification (its docstring).

Hand numbers used below (g = 9.81, dt = 0.02, g dt = 0.1962, g dt^2 = 0.003924):

* Free fall from rest (semi-implicit): z_dot_n = -g dt n, z_n = -g dt^2 (1 + 2 + ... + n)
  = -0.003924 n (n + 1) / 2. With floor_tolerance = 0.05 the floor is hit once
  n (n + 1) / 2 > 0.05 / 0.003924 = 12.74: n = 4 gives 10 (z = -0.03924, inside),
  n = 5 gives 15 (z = -0.05886) -> FLOOR on step 5.
"""

from __future__ import annotations

import math
import re

import pytest
import torch
from torchrl.data import Bounded, Unbounded
from torchrl.envs.utils import check_env_specs, step_mdp

from drone_torchrl.envs import DroneEnv, TerminationCause
from drone_torchrl.envs.dynamics import ALPHA, ALPHA_DOT, X_DOT, Z_DOT, X, Z

G, DT = 9.81, 0.02
GDT2 = G * DT * DT  # 0.003924


def const_policy(a_l, a_r):
    """A TorchRL rollout policy that always applies ``[a_l, a_r]`` to every sub-env."""

    def policy(td):
        a = torch.tensor([a_l, a_r], dtype=torch.float32)
        return td.set("action", a.expand(*td.batch_size, 2).clone())

    return policy


def sequence_policy(actions):
    """Apply ``actions[t]`` (shape ``[*batch, 2]``) at the t-th call."""
    it = iter(actions)

    def policy(td):
        return td.set("action", next(it).clone())

    return policy


def attitude_pd(td):
    """Hold alpha at 0 with hover collective thrust (air mode, default drone).

    alpha_ddot = r/I (T_r - T_l) = 5 * 9.81 (a_r - a_l) = 49.05 (a_r - a_l); ask for
    alpha_ddot = -100 alpha - 20 alpha_dot (critically damped, omega = 10 rad/s, omega dt = 0.2).
    """
    obs = td["observation"]
    diff = (-100.0 * obs[..., ALPHA] - 20.0 * obs[..., ALPHA_DOT]) / 49.05
    return td.set("action", torch.stack((0.5 - diff / 2, 0.5 + diff / 2), -1))


def run(env, actions, seed=0):
    """Reset (after seeding) and apply ``actions`` one by one; return the stacked step outputs."""
    env.set_seed(seed)
    td = env.reset()
    out = []
    for a in actions:
        td["action"] = a
        td = env.step(td)
        out.append(td["next"].clone())
        td = step_mdp(td)
    return torch.stack(out, -1)


# ----------------------------------------------------------------------------- specs


@pytest.mark.parametrize("max_thrust", [None, 1.0])
@pytest.mark.parametrize("batch_size", [[], [1], [8]])
def test_check_env_specs(batch_size, max_thrust):
    env = DroneEnv(batch_size=batch_size, max_thrust=max_thrust)
    env.set_seed(0)
    check_env_specs(env)
    assert env.batch_size == torch.Size(batch_size)
    assert env.observation_spec["observation"].shape == (*batch_size, 6)
    assert env.action_spec.shape == (*batch_size, 2)
    assert env.observation_spec["termination_cause"].dtype == torch.int64
    assert env.observation_spec["termination_cause"].shape == (*batch_size, 1)
    assert env.full_done_spec["terminated"].dtype == torch.bool


def test_action_spec_bounded_and_unbounded():
    env = DroneEnv(batch_size=[2], max_thrust=1.0)
    spec = env.action_spec
    assert isinstance(spec, Bounded)
    assert torch.equal(spec.space.low, torch.zeros(2, 2))
    assert torch.equal(spec.space.high, torch.ones(2, 2))
    assert spec.dtype == torch.float32
    spec_07 = DroneEnv(max_thrust=0.7).action_spec
    assert torch.equal(spec_07.space.high, torch.full((2,), 0.7))
    assert isinstance(DroneEnv(batch_size=[2]).action_spec, Unbounded)


# ----------------------------------------------------------------------------- free fall, floor


def test_free_fall_from_floor_ends_with_floor_on_step_5():
    env = DroneEnv(batch_size=[3])
    env.set_seed(0)
    td = env.rollout(50, const_policy(0.0, 0.0))  # stops at the first done
    assert td.batch_size == (3, 5)
    nxt = td["next"]
    # z_n = -0.003924 * n(n+1)/2 for n = 1..5 in every sub-env (zero thrust: z_ddot = -g exactly)
    expected_z = [-GDT2 * n * (n + 1) / 2 for n in range(1, 6)]
    for i in range(3):
        assert nxt["observation"][i, :, Z].tolist() == pytest.approx(expected_z, rel=1e-5)
        assert nxt["observation"][i, :, Z_DOT].tolist() == pytest.approx(
            [-G * DT * n for n in range(1, 6)], rel=1e-5
        )
    # x and alpha never move at zero thrust
    start = td["observation"][:, 0]
    assert torch.equal(nxt["observation"][:, :, X], start[:, None, X].expand(3, 5))
    assert torch.equal(nxt["observation"][:, :, ALPHA], start[:, None, ALPHA].expand(3, 5))
    assert nxt["termination_cause"][..., 0].tolist() == [[0, 0, 0, 0, 2]] * 3
    assert nxt["terminated"][..., 0].tolist() == [[False] * 4 + [True]] * 3
    assert not nxt["truncated"].any()
    assert torch.equal(nxt["done"], nxt["terminated"])
    # reward 1 (alive, outside the zone) on steps 1-4, 0 on the terminating step
    assert nxt["reward"][..., 0].tolist() == [[1.0, 1.0, 1.0, 1.0, 0.0]] * 3
    assert nxt["step_count"][..., 0].tolist() == [[1, 2, 3, 4, 5]] * 3


@pytest.mark.parametrize(
    "tolerance, steps",
    [
        (0.0, 1),  # z_1 = -0.003924 < 0
        (0.05, 5),  # see module docstring
        # n(n+1)/2 > 0.1 / 0.003924 = 25.48: n = 6 -> 21 (z = -0.0824), n = 7 -> 28 (z = -0.10987)
        (0.1, 7),
    ],
)
def test_floor_tolerance_sets_the_floor_step(tolerance, steps):
    env = DroneEnv(floor_tolerance=tolerance)
    env.set_seed(1)
    td = env.rollout(50, const_policy(0.0, 0.0))
    assert td.batch_size == (steps,)
    assert td["next", "termination_cause"][:, 0].tolist() == [0] * (steps - 1) + [int(TerminationCause.FLOOR)]
    z_last = td["next", "observation"][-1, Z].item()
    assert z_last == pytest.approx(-GDT2 * steps * (steps + 1) / 2, rel=1e-5)
    assert z_last < -tolerance


# ----------------------------------------------------------------------------- other causes


def test_ceiling_in_step_9():
    # air reset z in [2.69, 2.71]; a = [5, 5]: z_ddot = 10 g cos(alpha) - g ~= 9 g = 88.29
    # z_n ~= 2.7 + 88.29 * dt^2 * n(n+1)/2 = 2.7 + 0.035316 n(n+1)/2 (+-0.01 reset, +-0.01 t from
    # z_dot_0): n = 8 -> 3.971 (< 4 even at +0.012), n = 9 -> 4.289 > 4.
    env = DroneEnv(batch_size=[4], reset_mode="air")
    env.set_seed(2)
    td = env.rollout(50, const_policy(5.0, 5.0))
    assert td.batch_size == (4, 9)
    assert td["next", "termination_cause"][:, -1, 0].tolist() == [int(TerminationCause.CEILING)] * 4
    assert (td["next", "termination_cause"][:, :-1] == 0).all()
    assert (td["next", "observation"][:, -1, Z] > 4.0).all()
    assert (td["next", "observation"][:, -2, Z] <= 4.0).all()


def test_tilt_in_step_10():
    # air reset; a = [0, 1]: alpha_ddot = 5 * 9.81 = 49.05, alpha_n ~= 0.01962 n(n+1)/2 (+-0.012):
    # n = 9 -> 0.883, n = 10 -> 1.079 > pi/3 = 1.0472. T_l + T_r = m g keeps z near 2.7, x small.
    env = DroneEnv(batch_size=[4], reset_mode="air")
    env.set_seed(3)
    td = env.rollout(50, const_policy(0.0, 1.0))
    assert td.batch_size == (4, 10)
    assert td["next", "termination_cause"][:, -1, 0].tolist() == [int(TerminationCause.TILT)] * 4
    alpha = td["next", "observation"][..., ALPHA]
    assert (alpha[:, -1] > math.pi / 3).all() and (alpha[:, :-1] <= math.pi / 3).all()
    assert td["next", "reward"][:, -1, 0].tolist() == [0.0] * 4


def _tilt_then_thrust(k, thrust, steps, seed):
    """Roll to alpha ~= 0.01962 k^2 (k steps a = [0, 1], k steps a = [1, 0] bring alpha_dot back
    to ~0), then apply the collective ``[thrust, thrust]``. With negative thrust and alpha > 0,
    x_ddot = -sin(alpha) (2 thrust g) > 0 pushes towards +x while z_ddot = 2 thrust g cos(alpha) - g
    pulls down, so the drone leaves through x = +2, the floor, or both on the same step."""
    env = DroneEnv(batch_size=[3], reset_mode="air")
    env.set_seed(seed)
    actions = [torch.tensor([[0.0, 1.0]] * 3)] * k + [torch.tensor([[1.0, 0.0]] * 3)] * k
    actions += [torch.full((3, 2), float(thrust))] * (steps - 2 * k)
    return env.rollout(steps, sequence_policy(actions))


def test_out_x_alone():
    # k = 7: alpha ~= 0.96, thrust -5: x_ddot ~= +80, z_ddot ~= -9.81 (10 cos 0.96 + 1) ~= -65.
    # Simulated once over every corner of the reset box: OUT_X on step 26 with z in [0.45, 0.55].
    td = _tilt_then_thrust(7, -5.0, 60, seed=4)
    assert td.batch_size == (3, 26)
    assert td["next", "termination_cause"][:, -1, 0].tolist() == [int(TerminationCause.OUT_X)] * 3
    assert (td["next", "termination_cause"][:, :-1] == 0).all()
    last = td["next", "observation"][:, -1]
    assert (last[:, X] > 2.0).all()
    assert ((last[:, Z] > 0.0) & (last[:, Z] < 4.0)).all() and (last[:, ALPHA].abs() < 1.0).all()
    assert td["next", "reward"][:, -1, 0].tolist() == [0.0] * 3


def test_out_x_and_floor_on_the_same_step_reports_out_x():
    # k = 6: alpha ~= 0.71, thrust -10: x passes +2 and z passes -0.05 on the same step (21 for every
    # corner of the reset box, simulated once); the lowest code, OUT_X = 1, wins over FLOOR = 2.
    td = _tilt_then_thrust(6, -10.0, 60, seed=4)
    assert td.batch_size == (3, 21)
    last = td["next", "observation"][:, -1]
    assert (last[:, X] > 2.0).all() and (last[:, Z] < -0.05).all()
    assert td["next", "termination_cause"][:, -1, 0].tolist() == [int(TerminationCause.OUT_X)] * 3
    assert td["next", "terminated"][:, -1, 0].all()


# ----------------------------------------------------------------------------- reward, truncation


def test_hover_in_air_earns_10_per_step_and_truncates_at_300():
    env = DroneEnv(batch_size=[2], reset_mode="air")
    assert env.max_steps == 300
    env.set_seed(5)
    td = env.rollout(400, attitude_pd)
    assert td.batch_size == (2, 300)
    nxt = td["next"]
    assert nxt["step_count"][..., 0].tolist() == [list(range(1, 301))] * 2
    assert not nxt["terminated"].any()
    assert nxt["truncated"][:, :-1].sum() == 0 and nxt["truncated"][:, -1].all()
    assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
    assert (nxt["termination_cause"] == 0).all()
    # inside the zone the whole time: 10 per step, the theoretical maximum 10 * 300
    assert nxt["reward"].sum(-2)[..., 0].tolist() == [3000.0, 3000.0]


def test_truncation_with_small_max_steps_and_auto_reset():
    # Hover thrust in the air survives 7 steps easily (drift ~ 0.01 m/s * 0.14 s).
    env = DroneEnv(batch_size=[2], reset_mode="air", max_steps=7)
    env.set_seed(6)
    td = env.rollout(20, const_policy(0.5, 0.5), break_when_any_done=False)
    nxt = td["next"]
    counts = list(range(1, 8)) * 2 + list(range(1, 7))
    assert nxt["step_count"][..., 0].tolist() == [counts] * 2
    truncated = [c == 7 for c in counts]
    assert nxt["truncated"][..., 0].tolist() == [truncated] * 2
    assert torch.equal(nxt["done"], nxt["truncated"])
    assert not nxt["terminated"].any()
    assert (nxt["reward"] == 10.0).all()
    # after each truncation the next root observation is a fresh air reset (step_count 0)
    assert td["step_count"][:, 7, 0].tolist() == [0, 0]
    assert td["step_count"][:, 14, 0].tolist() == [0, 0]


def test_max_steps_one_truncates_every_step():
    env = DroneEnv(max_steps=1, reset_mode="air")
    env.set_seed(0)
    td = env.rollout(3, const_policy(0.5, 0.5), break_when_any_done=False)
    assert td["next", "truncated"][:, 0].tolist() == [True] * 3
    assert td["next", "step_count"][:, 0].tolist() == [1] * 3


def test_terminated_and_truncated_on_the_same_step_is_only_terminated():
    # max_steps = 5 and the free fall hits the floor on step 5 too.
    env = DroneEnv(batch_size=[2], max_steps=5)
    env.set_seed(7)
    td = env.rollout(10, const_policy(0.0, 0.0))
    assert td.batch_size == (2, 5)
    last = td["next"][:, -1]
    assert last["terminated"][:, 0].tolist() == [True, True]
    assert last["truncated"][:, 0].tolist() == [False, False]
    assert last["done"][:, 0].tolist() == [True, True]
    assert last["termination_cause"][:, 0].tolist() == [2, 2]
    assert last["step_count"][:, 0].tolist() == [5, 5]


def test_reset_output():
    env = DroneEnv(batch_size=[3])
    env.set_seed(0)
    td = env.reset()
    assert td["step_count"].tolist() == [[0]] * 3
    assert td["termination_cause"].tolist() == [[0]] * 3
    assert not td["done"].any() and not td["terminated"].any() and not td["truncated"].any()
    assert torch.equal(td["observation"], env.state)


# ----------------------------------------------------------------------------- partial resets


def test_step_and_maybe_reset_resets_only_done_sub_envs():
    # Sub-env 0 free-falls (FLOOR on step 5); 1 and 2 hover on the floor (z sinks by ~1e-5 m).
    env = DroneEnv(batch_size=[3])
    env.set_seed(8)
    td = env.reset()
    action = torch.tensor([[0.0, 0.0], [0.5, 0.5], [0.5, 0.5]])
    for n in range(1, 6):
        td["action"] = action
        before = env.state
        stepped, td = env.step_and_maybe_reset(td)
        nxt = stepped["next"]
        if n < 5:
            assert not nxt["done"].any()
            assert torch.equal(td["observation"], nxt["observation"])
    assert nxt["done"][:, 0].tolist() == [True, False, False]
    assert nxt["termination_cause"][:, 0].tolist() == [2, 0, 0]
    # the untouched sub-envs carry on bit for bit: observation, counter, cause and internal state
    assert torch.equal(td["observation"][1:], nxt["observation"][1:])
    assert td["step_count"][:, 0].tolist() == [0, 5, 5]
    assert td["termination_cause"][:, 0].tolist() == [0, 0, 0]
    state = env.state
    assert torch.equal(state[1:], nxt["observation"][1:])
    # sub-env 0 is a fresh floor reset
    assert torch.equal(state[0], td["observation"][0])
    assert state[0, [X_DOT, Z, Z_DOT, ALPHA_DOT]].tolist() == [0.0] * 4
    assert not torch.equal(state[0], before[0])
    # and the next step continues sub-envs 1, 2 from their state (step_count 6), sub-env 0 from 0
    td["action"] = action
    stepped, td = env.step_and_maybe_reset(td)
    assert stepped["next", "step_count"][:, 0].tolist() == [1, 6, 6]


def test_reset_with_mask_leaves_other_sub_envs_untouched():
    env = DroneEnv(batch_size=[4], reset_mode="air")
    env.set_seed(9)
    td = env.reset()
    for _ in range(3):
        td["action"] = torch.full((4, 2), 0.5)
        td = step_mdp(env.step(td))
    before = env.state
    # As in step_and_maybe_reset, the input carries the current root data plus the "_reset" mask
    # (TorchRL fills the entries that are not reset from it, and pads missing keys with 0).
    mask = torch.tensor([[True], [False], [True], [False]])
    out = env.reset(td.clone().set("_reset", mask))
    after = env.state
    keep = torch.tensor([1, 3])
    assert torch.equal(after[keep], before[keep])
    assert torch.equal(out["observation"][keep], before[keep])
    assert out["step_count"][:, 0].tolist() == [0, 3, 0, 3]
    # reset sub-envs are new air starts
    fresh = after[[0, 2]]
    assert not torch.equal(fresh, before[[0, 2]])
    centre = torch.tensor([0.0, 0.0, 2.7, 0.0, 0.0, 0.0])
    assert (fresh - centre).abs().max().item() <= 0.01 + 1e-6
    # 2-D batch too
    env2 = DroneEnv(batch_size=[2, 2])
    env2.set_seed(0)
    td2 = env2.reset()
    td2["action"] = torch.full((2, 2, 2), 0.7)
    td2 = step_mdp(env2.step(td2))
    before2 = env2.state
    out2 = env2.reset(td2.set("_reset", torch.tensor([[[False], [True]], [[False], [False]]])))
    assert out2["step_count"][..., 0].tolist() == [[1, 0], [1, 1]]
    after2 = env2.state
    assert torch.equal(after2[0, 0], before2[0, 0]) and torch.equal(after2[1], before2[1])
    assert after2[0, 1, Z].item() == 0.0
    assert torch.equal(out2["observation"], after2)
    # the env itself does not need the caller's copy: the next step continues from its own state
    td_next = out2.clone().set("action", torch.full((2, 2, 2), 0.7))
    td_next["observation"].zero_()
    nxt = env2.step(td_next)["next"]
    assert nxt["step_count"][..., 0].tolist() == [[2, 1], [2, 2]]
    assert nxt["observation"][1, 1, Z].item() > before2[1, 1, Z].item()  # still climbing (a = 0.7)


# ----------------------------------------------------------------------------- seeding, resets


def _random_actions(batch, steps, seed=0, high=0.6):
    gen = torch.Generator().manual_seed(seed)
    # mean thrust 0.3 of the weight per motor: drones sink, so episodes end and auto-reset
    return [torch.rand((*batch, 2), generator=gen) * high for _ in range(steps)]


def test_same_seed_same_trajectory_bit_for_bit():
    actions = _random_actions([4], 40)
    rollouts = []
    for _ in range(2):
        env = DroneEnv(batch_size=[4])
        env.set_seed(123)
        rollouts.append(env.rollout(40, sequence_policy(actions), break_when_any_done=False))
    a, b = rollouts
    assert a["next", "done"].any(), "the test should cross at least one auto-reset"
    assert (a == b).all()
    # a different seed gives other starts
    env = DroneEnv(batch_size=[4])
    env.set_seed(124)
    c = env.rollout(40, sequence_policy(actions), break_when_any_done=False)
    assert not torch.equal(a["observation"][:, 0], c["observation"][:, 0])


def test_set_seed_makes_resets_reproducible():
    env = DroneEnv(batch_size=[5], reset_mode="air")
    env.set_seed(42)
    r1, r2 = env.reset()["observation"], env.reset()["observation"]
    env.set_seed(42)
    assert torch.equal(env.reset()["observation"], r1)
    assert torch.equal(env.reset()["observation"], r2)
    assert not torch.equal(r1, r2)
    other = DroneEnv(batch_size=[5], reset_mode="air")
    other.set_seed(42)
    assert torch.equal(other.reset()["observation"], r1)
    other.set_seed(43)
    assert not torch.equal(other.reset()["observation"], r1)


def test_reset_mode_ranges():
    floor = DroneEnv(batch_size=[2000])
    floor.set_seed(0)
    s = floor.reset()["observation"]
    assert torch.equal(s[:, [X_DOT, Z, Z_DOT, ALPHA_DOT]], torch.zeros(2000, 4))
    assert s[:, [X, ALPHA]].abs().max().item() <= 0.01
    assert s[:, [X, ALPHA]].abs().max().item() > 0.0099

    air = DroneEnv(batch_size=[2000], reset_mode="air")
    air.set_seed(0)
    s = air.reset()["observation"]
    dev = s - torch.tensor([0.0, 0.0, 2.7, 0.0, 0.0, 0.0])
    assert dev.abs().max().item() <= 0.01 + 1e-6  # float32 rounding of 2.7 +- 0.01
    assert (dev.abs().max(0).values > 0.0099).all()


# ----------------------------------------------------------------------------- thrust bounds


def test_bounded_thrust_clamps_out_of_range_actions():
    env = DroneEnv(batch_size=[2], max_thrust=1.0, reset_mode="air")
    clamped = run(env, [torch.tensor([[2.0, -1.0], [5.0, 0.5]])] * 4, seed=11)
    ref = run(env, [torch.tensor([[1.0, 0.0], [1.0, 0.5]])] * 4, seed=11)
    assert (clamped == ref).all()
    # and it is not a no-op: [1, 0] spins the drone clockwise (alpha_dot_1 = alpha_dot_0 - 49.05 * 0.02)
    assert ref["observation"][0, 0, ALPHA_DOT] < -0.9


def test_bounded_thrust_clamps_negative_to_zero():
    env = DroneEnv(max_thrust=1.0)
    neg = run(env, [torch.tensor([-0.5, -0.5])] * 5, seed=3)
    zero = run(env, [torch.tensor([0.0, 0.0])] * 5, seed=3)
    assert (neg == zero).all()
    assert neg["termination_cause"][-1, 0].item() == TerminationCause.FLOOR


def test_unbounded_negative_thrust_is_applied():
    # a = [-0.5, -0.5]: z_ddot = -cos(alpha) g - g ~= -2g; free fall has z_ddot = -g.
    env = DroneEnv(reset_mode="air")
    env.set_seed(12)
    start = env.reset()["observation"]
    neg = run(env, [torch.tensor([-0.5, -0.5])], seed=12)["observation"][0]
    fall = run(env, [torch.tensor([0.0, 0.0])], seed=12)["observation"][0]
    z_dot0, alpha0 = start[Z_DOT].item(), start[ALPHA].item()
    assert neg[Z_DOT].item() == pytest.approx(z_dot0 + (-math.cos(alpha0) * G - G) * DT, abs=1e-6)
    assert fall[Z_DOT].item() == pytest.approx(z_dot0 - G * DT, abs=1e-6)
    assert neg[Z].item() < fall[Z].item()


# ----------------------------------------------------------------------------- non-finite actions


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_action_raises_and_leaves_state(bad):
    env = DroneEnv(batch_size=[4], reset_mode="air")
    env.set_seed(0)
    td = env.reset()
    td["action"] = torch.full((4, 2), 0.5)
    td = step_mdp(env.step(td))
    before = env.state
    action = torch.full((4, 2), 0.5)
    action[1, 0] = bad
    action[3, 1] = bad
    td["action"] = action
    with pytest.raises(ValueError) as err:
        env.step(td)
    msg = str(err.value)
    indices = msg[msg.index("indices") :]
    assert re.findall(r"\d+", indices) == ["1", "3"]
    assert torch.equal(env.state, before)
    # the failed step did not count: the next good step is step 2, from the old state
    td["action"] = torch.full((4, 2), 0.5)
    nxt = env.step(td)["next"]
    assert nxt["step_count"][:, 0].tolist() == [2, 2, 2, 2]


def test_non_finite_action_2d_batch_names_index_pairs():
    env = DroneEnv(batch_size=[2, 3])
    env.set_seed(0)
    td = env.reset()
    action = torch.zeros(2, 3, 2)
    action[1, 2, 1] = float("nan")
    td["action"] = action
    before = env.state
    with pytest.raises(ValueError, match=r"1,\s*2"):
        env.step(td)
    assert torch.equal(env.state, before)


def test_non_finite_action_unbatched():
    env = DroneEnv(max_thrust=1.0)  # clamping must not hide a NaN either
    env.set_seed(0)
    td = env.reset()
    before = env.state
    td["action"] = torch.tensor([float("nan"), 0.5])
    with pytest.raises(ValueError):
        env.step(td)
    assert torch.equal(env.state, before)


# ----------------------------------------------------------------------------- arguments


BAD_ARGS = [
    ("mass", 0.0),
    ("mass", -1.0),
    ("mass", True),
    ("mass", float("nan")),
    ("motor_distance", 0.0),
    ("motor_distance", -0.5),
    ("motor_distance", True),
    ("dt", 0.0),
    ("dt", -0.02),
    ("dt", float("inf")),
    ("dt", True),
    ("gravity", -9.81),
    ("gravity", 0.0),  # thrust is a fraction of the weight: nothing could move the drone
    ("gravity", 100.01),
    ("gravity", True),
    ("dt", 0.11),
    ("max_steps", 0),
    ("max_steps", -1),
    ("max_steps", 1.5),
    ("max_steps", True),
    ("reset_mode", "x"),
    ("reset_mode", None),
    ("max_thrust", 0.0),
    ("max_thrust", -1.0),
    ("max_thrust", True),
    ("floor_tolerance", -0.01),
    ("floor_tolerance", 1.01),
    ("floor_tolerance", False),
    ("render_mode", "x"),
    ("x_limit", 0.0),
    ("x_limit", float("inf")),
    ("z_max", 0.0),  # not above z_min
    ("z_min", float("nan")),
    ("alpha_limit", 0.0),
    ("alpha_limit", 3.2),
    ("zone_x_limit", 2.5),  # outside the domain
    ("zone_x_limit", 0.0),
    ("zone_z_min", -0.1),  # below the floor
    ("zone_z_min", 4.0),
    ("zone_z_max", 2.2),  # not above zone_z_min
    ("zone_z_max", 4.1),  # above the ceiling
    ("zone_z_max", True),
    ("bounds", "exclusive"),
    ("bounds", None),
    ("dtype", "float16"),
    ("dtype", torch.float16),
    ("dtype", "double"),
]


@pytest.mark.parametrize("name, value", BAD_ARGS)
def test_bad_argument_raises_value_error_naming_it(name, value):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        DroneEnv(**{name: value})


@pytest.mark.parametrize("value", [[0], [-1], [2, 0], [True], True, [1.5], "4"])
def test_bad_batch_size(value):
    with pytest.raises(ValueError, match=r"\bbatch_size\b"):
        DroneEnv(batch_size=value)


def test_edge_arguments_are_accepted():
    env = DroneEnv(gravity=100.0, floor_tolerance=0.0, max_steps=1, batch_size=[1], max_thrust=0.25, dt=0.1)
    assert (env.gravity, env.floor_tolerance, env.max_steps, env.max_thrust, env.dt) == (
        100.0,
        0.0,
        1,
        0.25,
        0.1,
    )
    assert DroneEnv(floor_tolerance=1.0).floor_tolerance == 1.0
    assert DroneEnv(batch_size=3).batch_size == (3,)
    assert DroneEnv().batch_size == ()


def test_params_and_keyword_overrides_build_one_checked_drone():
    from drone_torchrl.envs.params import DroneParams

    env = DroneEnv(batch_size=[2], params=DroneParams(max_thrust=2.0, zone_x_limit=0.6), gravity=5)
    assert env.params == DroneParams(max_thrust=2.0, zone_x_limit=0.6, gravity=5.0)
    assert (env.max_thrust, env.zone_x_limit, env.gravity, env.bounds) == (2.0, 0.6, 5.0, "inclusive")
    assert env.action_spec.space.high.max() == 2.0
    # A DroneParams built by hand is checked too, and an unknown keyword names itself.
    with pytest.raises(
        ValueError,
        match=r"^zone_x_limit=3.0 is not allowed; expected a finite number > 0 and <= x_limit \(2.0\)$",
    ):
        DroneEnv(params=DroneParams(zone_x_limit=3.0))
    with pytest.raises(TypeError, match="unexpected keyword argument 'mas'"):
        DroneEnv(mas=1.0)
