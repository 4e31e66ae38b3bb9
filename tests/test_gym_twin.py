"""The Gymnasium twin ``Drone2D-v0`` (``DroneGymEnv``) and TorchRL's ``GymEnv`` wrapper of it.

Free fall at zero thrust from the floor: z_n = -g dt^2 n(n+1)/2 = -0.003924 n(n+1)/2 first drops
below -0.05 at n = 5 (15 * 0.003924 = 0.05886; n = 4 gives 0.03924), so FLOOR ends step 5.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

import drone_torchrl
from drone_torchrl.envs import DroneEnv, DroneGymEnv, TerminationCause

G, DT = 9.81, 0.02

# check_env's advice about infinite Box bounds: the specification makes the observation (and, with
# max_thrust=None, the action) unbounded on purpose. Any other warning fails the test.
EXPECTED_WARNINGS = ("infinity", "symmetric and normalized")


def _check_env_strict(env, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, **kwargs)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_WARNINGS)]
    assert unexpected == []


def test_import_registers_drone2d():
    assert drone_torchrl.GYM_ID == "Drone2D-v0"
    assert "Drone2D-v0" in gym.registry
    env = gym.make("Drone2D-v0", max_steps=50)
    assert isinstance(env.unwrapped, DroneGymEnv)
    assert env.unwrapped.max_steps == 50
    env.close()


@pytest.mark.parametrize("max_thrust", [None, 1.0])
def test_gymnasium_check_env_without_render(max_thrust):
    env = gym.make("Drone2D-v0", max_thrust=max_thrust)
    _check_env_strict(env.unwrapped, skip_render_check=True)
    env.close()


def test_gymnasium_check_env_with_render(monkeypatch):
    pytest.importorskip("drone_torchrl.envs.rendering")
    # check_env also builds a "human" env through the spec: no display on a test machine.
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = gym.make("Drone2D-v0", render_mode="rgb_array")
    _check_env_strict(env.unwrapped)
    env.close()


def test_spaces_and_observation_dtype():
    env = DroneGymEnv()
    assert env.observation_space.shape == (6,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (2,) and env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -np.inf) and np.all(env.action_space.high == np.inf)
    bounded = DroneGymEnv(max_thrust=1.0)
    assert np.array_equal(bounded.action_space.low, np.zeros(2, np.float32))
    assert np.array_equal(bounded.action_space.high, np.ones(2, np.float32))
    assert np.array_equal(DroneGymEnv(max_thrust=0.7).action_space.high, np.full(2, 0.7, np.float32))
    obs, info = env.reset(seed=0)
    assert isinstance(obs, np.ndarray) and obs.dtype == np.float32 and obs.shape == (6,)
    assert info["termination_cause"] == "NONE"
    obs, reward, terminated, truncated, info = env.step(np.array([0.5, 0.5], np.float32))
    assert obs.dtype == np.float32 and obs.shape == (6,)
    assert isinstance(reward, float) and terminated is False and truncated is False


def test_free_fall_ends_with_floor_name():
    env = DroneGymEnv()
    env.reset(seed=1)
    causes, rewards, terms = [], [], []
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step([0.0, 0.0])
        causes.append(info["termination_cause"])
        rewards.append(reward)
        terms.append(terminated)
        assert truncated is False
    assert causes == ["NONE"] * 4 + ["FLOOR"]
    assert terms == [False] * 4 + [True]
    assert rewards == [1.0, 1.0, 1.0, 1.0, 0.0]
    assert obs[2] == pytest.approx(-0.003924 * 15, rel=1e-5)
    assert info["step_count"] == 5


@pytest.mark.parametrize(
    "action, steps, name",
    [
        # a = [5, 5] from the air: z ~= 2.7 + 88.29 dt^2 n(n+1)/2 passes 4 on step 9 (see test_env)
        ([5.0, 5.0], 9, "CEILING"),
        # a = [0, 1]: alpha ~= 0.01962 n(n+1)/2 passes pi/3 on step 10
        ([0.0, 1.0], 10, "TILT"),
    ],
)
def test_other_cause_names(action, steps, name):
    env = DroneGymEnv(reset_mode="air")
    env.reset(seed=2)
    for n in range(1, steps + 1):
        _, reward, terminated, _, info = env.step(action)
        assert terminated is (n == steps)
    assert info["termination_cause"] == name and reward == 0.0


def test_truncation_and_hover_reward():
    env = DroneGymEnv(reset_mode="air", max_steps=4)
    env.reset(seed=3)
    out = [env.step([0.5, 0.5]) for _ in range(4)]
    assert [o[3] for o in out] == [False, False, False, True]  # truncated
    assert [o[2] for o in out] == [False] * 4  # terminated
    assert [o[1] for o in out] == [10.0] * 4  # inside the zone
    assert out[-1][4]["termination_cause"] == "NONE"


def test_bounded_action_is_clamped():
    a, b = DroneGymEnv(max_thrust=1.0, reset_mode="air"), DroneGymEnv(max_thrust=1.0, reset_mode="air")
    a.reset(seed=4)
    b.reset(seed=4)
    for _ in range(3):
        oa = a.step([2.0, -1.0])[0]
        ob = b.step([1.0, 0.0])[0]
        assert np.array_equal(oa, ob)


def test_non_finite_action_raises_and_leaves_state():
    env, ref = DroneGymEnv(), DroneGymEnv()
    env.reset(seed=5)
    ref.reset(seed=5)
    with pytest.raises(ValueError):
        env.step([float("nan"), 0.5])
    with pytest.raises(ValueError):
        env.step([0.5, float("inf")])
    o1, *_, i1 = env.step([0.6, 0.6])
    o2, *_, i2 = ref.step([0.6, 0.6])
    assert np.array_equal(o1, o2) and i1["step_count"] == i2["step_count"] == 1


@pytest.mark.parametrize(
    "name, value",
    [
        ("mass", 0.0),
        ("motor_distance", -1.0),
        ("dt", 0.0),
        ("gravity", -1.0),
        ("max_steps", 0),
        ("max_steps", 1.5),
        ("reset_mode", "x"),
        ("max_thrust", 0.0),
        ("floor_tolerance", -0.1),
        ("render_mode", "x"),
        ("mass", True),
    ],
)
def test_bad_arguments(name, value):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        DroneGymEnv(**{name: value})


def test_same_seed_same_reset():
    a, b = DroneGymEnv(reset_mode="air"), DroneGymEnv(reset_mode="air")
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    assert np.array_equal(oa, ob)
    # A reset() right after reset(seed=...) keeps the seeded start (so GymEnv.set_seed, which
    # resets, does not skip it); once steps were taken the generator moves on.
    assert np.array_equal(a.reset()[0], oa)
    assert not np.array_equal(a.reset()[0], oa)
    b.step(np.zeros(2, dtype=np.float32))
    assert not np.array_equal(b.reset()[0], oa)
    assert not np.array_equal(b.reset(seed=8)[0], oa)


# ----------------------------------------------------------------------------- three-way equality

SEED = 31
T = 30


def _actions():
    # 5 steps of zero thrust end the first episode with FLOOR on step 5 (see module docstring);
    # then 25 random thrusts around hover in a fresh episode.
    gen = torch.Generator().manual_seed(0)
    rand = [0.3 + 0.6 * torch.rand(2, generator=gen) for _ in range(T - 5)]
    return [torch.zeros(2)] * 5 + rand


def _sequence_policy(actions):
    it = iter(actions)
    return lambda td: td.set("action", next(it).clone())


def _gym_twin_trajectory(actions):
    env = DroneGymEnv()
    obs, _ = env.reset(seed=SEED)  # draw 1: the first episode's start
    rows = []
    for a in actions:
        nxt, reward, terminated, truncated, info = env.step(a.numpy())
        rows.append((obs, nxt, reward, terminated, truncated, info["termination_cause"]))
        obs = env.reset()[0] if terminated or truncated else nxt  # draw 2 after the FLOOR
    return rows


def test_native_gym_twin_and_torchrl_gymenv_agree_bit_for_bit():
    """Same seed, same actions, across an episode end and the following reset.

    Each is seeded the way its users seed it: ``DroneEnv.set_seed(s)`` then a rollout;
    ``GymEnv.set_seed(s)`` (which calls the twin's ``reset(seed=s)``) then a rollout (whose first
    ``reset()`` keeps the seeded start); the bare twin ``reset(seed=s)`` then steps and ``reset()``.
    All three start from draw 1 and, after the FLOOR on step 5, from draw 2.
    """
    actions = _actions()

    native = DroneEnv()
    native.set_seed(SEED)
    td_native = native.rollout(T, _sequence_policy(actions), break_when_any_done=False)

    wrapped = GymEnv("Drone2D-v0")
    wrapped.set_seed(SEED)
    td_gym = wrapped.rollout(T, _sequence_policy(actions), break_when_any_done=False)
    wrapped.close()

    twin = _gym_twin_trajectory(actions)

    assert td_native.batch_size == td_gym.batch_size == (T,)
    # the episode boundary really is crossed: FLOOR on step 5, reset, second episode starts
    assert td_native["next", "done"][:, 0].nonzero().flatten().tolist()[:1] == [4]
    assert td_native["step_count"][5, 0].item() == 0
    assert not torch.equal(td_native["observation"][5], td_native["observation"][0])

    for key in ["observation", ("next", "observation")]:
        assert td_native[key].dtype == td_gym[key].dtype == torch.float32
        assert torch.equal(td_native[key], td_gym[key]), key
    for key in ["reward", "terminated", "truncated", "done"]:
        assert torch.equal(td_native["next", key].to(td_gym["next", key].dtype), td_gym["next", key]), key

    twin_obs = torch.stack([torch.from_numpy(r[0]) for r in twin])
    twin_next = torch.stack([torch.from_numpy(r[1]) for r in twin])
    assert torch.equal(twin_obs, td_native["observation"])
    assert torch.equal(twin_next, td_native["next", "observation"])
    assert [r[2] for r in twin] == td_native["next", "reward"][:, 0].tolist()
    assert [r[3] for r in twin] == td_native["next", "terminated"][:, 0].tolist()
    assert [r[4] for r in twin] == td_native["next", "truncated"][:, 0].tolist()
    causes = [TerminationCause(c).name for c in td_native["next", "termination_cause"][:, 0].tolist()]
    assert [r[5] for r in twin] == causes
    assert causes[4] == "FLOOR"


def test_batch_one_and_unbatched_native_agree():
    gen = torch.Generator().manual_seed(1)
    actions = [torch.rand(2, generator=gen) for _ in range(300)]
    tds = []
    for bs in ([], [1]):
        env = DroneEnv(batch_size=bs)
        env.set_seed(SEED)
        shaped = [a.reshape(*bs, 2) for a in actions]
        tds.append(env.rollout(300, _sequence_policy(shaped)))  # stops at the first episode's end
    flat, one = tds
    one = one.squeeze(0)
    assert flat["next", "done"][-1].item() and flat.batch_size[0] < 300
    assert flat.batch_size == one.batch_size
    assert (flat == one).all()


def test_torchrl_gymenv_specs():
    env = GymEnv("Drone2D-v0", max_thrust=1.0)
    check_env_specs(env)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    assert torch.equal(low, torch.zeros(2)) and torch.equal(high, torch.ones(2))
    env.close()
