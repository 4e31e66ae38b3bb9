"""Disturbances (drone_torchrl.envs.disturbances): each one changes a step exactly as its formula says.

The hand-computed cases use g = 9.81, dt = 0.02, m0 = 1, r = 0.5 (I = 2/5 m r^2 = 0.1 m): a level
drone at rest, both motors at the hover command 0.5, is in equilibrium without disturbances.
"""

from __future__ import annotations

import math

import pytest
import torch

from drone_torchrl.envs import disturbances as dist
from drone_torchrl.envs import dynamics
from drone_torchrl.envs.dynamics import ALPHA, ALPHA_DOT, X_DOT, Z_DOT, DroneParams, X, Z

G, DT = 9.81, 0.02
PARAMS = DroneParams(max_thrust=1.0)
HOVER = torch.tensor([[0.5, 0.5]])


def _internal(d: dist.Disturbance, *, wind=0.0, ratio=1.0, gain=(1.0, 1.0), gust=0.0) -> dist.Internal:
    """A drone's internal state with chosen episode draws (the key only feeds the per-step noise)."""
    internal = dist.start(d, torch.tensor([12345]))
    draw = dist.EpisodeDraw(torch.tensor([wind]), torch.tensor([ratio]), torch.tensor([list(gain)]))
    return internal._replace(draw=draw, gust=torch.tensor([gust]))


def _step(d: dist.Disturbance, internal: dist.Internal, action=HOVER, state=None):
    state = torch.zeros(1, 6) if state is None else state
    return dist.step(d, state, action, internal, 0, PARAMS)


def test_no_disturbance_is_the_nominal_step():
    d = dist.Disturbance()
    state = torch.tensor([[0.1, -0.2, 1.0, 0.3, 0.05, -0.1]])
    action = torch.tensor([[0.7, 0.4]])
    got, reward, cause, _ = _step(d, _internal(d), action, state)
    want, want_reward, want_cause = dynamics.step(state, action, PARAMS)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    assert reward.tolist() == want_reward.tolist() and cause.tolist() == want_cause.tolist()
    assert not d.active


def test_wind_pushes_sideways_by_its_fraction_of_the_weight():
    d = dist.Disturbance(wind=0.2)
    state, *_ = _step(d, _internal(d, wind=0.2))
    # x'' = 0.2 g = 1.962 m/s^2: x_dot = 0.03924 m/s, x = 0.03924 * 0.02 m; the hover is unchanged.
    assert state[0, X_DOT].item() == pytest.approx(0.2 * G * DT, rel=1e-6)
    assert state[0, X].item() == pytest.approx(0.2 * G * DT * DT, rel=1e-6)
    assert state[0, Z].item() == 0.0 and state[0, ALPHA].item() == 0.0


def test_a_heavier_drone_sinks_at_hover_command():
    d = dist.Disturbance(mass=0.3)
    state, *_ = _step(d, _internal(d, ratio=1.25))
    # z'' = g (1 / 1.25) - g = -0.2 g: the nominal hover command no longer holds the drone.
    assert state[0, Z_DOT].item() == pytest.approx(-0.2 * G * DT, rel=1e-5)
    assert state[0, Z].item() == pytest.approx(-0.2 * G * DT * DT, rel=1e-5)
    # The inertia grows with the mass: a thrust difference of 0.1 turns it 1.25 times slower.
    turned, *_ = _step(d, _internal(d, ratio=1.25), torch.tensor([[0.45, 0.55]]))
    assert turned[0, ALPHA_DOT].item() == pytest.approx(0.1 * G * 0.5 / (0.1 * 1.25) * DT, rel=1e-5)


def test_motor_gains_scale_each_motor():
    d = dist.Disturbance(motor_gain=0.1)
    state, *_ = _step(d, _internal(d, gain=(0.9, 1.1)))
    # Total thrust 0.45 + 0.55 = 1 weight (no climb); the difference 0.1 m0 g at lever 0.5 m on
    # I = 0.1: alpha'' = 0.1 * 9.81 * 0.5 / 0.1 = 4.905 rad/s^2.
    assert state[0, Z].item() == pytest.approx(0.0, abs=1e-9)
    assert state[0, ALPHA_DOT].item() == pytest.approx(4.905 * DT, rel=1e-5)
    assert state[0, ALPHA].item() == pytest.approx(4.905 * DT * DT, rel=1e-5)


def test_a_gain_acts_after_the_clamp():
    d = dist.Disturbance(motor_gain=0.2)
    # Commands of 3 are clamped to max_thrust 1; a gain of 0.8 leaves 0.8 weight per motor.
    state, *_ = _step(d, _internal(d, gain=(0.8, 0.8)), torch.tensor([[3.0, 3.0]]))
    assert state[0, Z_DOT].item() == pytest.approx((1.6 - 1.0) * G * DT, rel=1e-5)


def test_motor_lag_is_a_first_order_step():
    d = dist.Disturbance(motor_lag=0.02)
    internal = _internal(d)
    state, _, _, after = _step(d, internal, torch.tensor([[1.0, 1.0]]))
    # tau = dt: the thrust covers 1 - e^-1 = 63.2% of the way from 0.5 to 1 in one step.
    thrust = 0.5 + (1.0 - math.exp(-1.0)) * 0.5
    assert after.thrust[0].tolist() == pytest.approx([thrust, thrust], rel=1e-6)
    assert state[0, Z_DOT].item() == pytest.approx((2 * thrust - 1.0) * G * DT, rel=1e-5)
    # A second step with the same command closes the remaining gap by the same fraction.
    _, _, _, again = dist.step(d, state, torch.tensor([[1.0, 1.0]]), after, 1, PARAMS)
    assert again.thrust[0, 0].item() == pytest.approx(1.0 - 0.5 * math.exp(-2.0), rel=1e-6)


def test_action_delay_applies_each_command_k_steps_later():
    d = dist.Disturbance(action_delay=2)
    internal = _internal(d)
    state = torch.zeros(1, 6)
    commands = [torch.tensor([[1.0, 1.0]]), torch.tensor([[0.0, 0.0]]), torch.tensor([[0.5, 0.5]])]
    z_dots = []
    for t, command in enumerate(commands):
        state, _, _, internal = dist.step(d, state, command, internal, t, PARAMS)
        z_dots.append(state[0, Z_DOT].item())
    # Steps 0 and 1 fly the hover commands in flight at the start; step 2 flies the command of step 0.
    assert z_dots[0] == 0.0 and z_dots[1] == 0.0
    assert z_dots[2] == pytest.approx(G * DT, rel=1e-6)
    assert internal.pending[0].tolist() == [[0.0, 0.0], [0.5, 0.5]]


def test_observed_actions_are_the_last_commands_newest_first():
    d = dist.Disturbance(observed_actions=2)
    internal = _internal(d)
    state = torch.zeros(1, 6)
    assert dist.observe(d, state, internal, 0).shape == (1, 10) and d.observation_dim == 10
    for t, a in enumerate((0.1, 0.2, 0.3)):
        state, _, _, internal = dist.step(d, state, torch.tensor([[a, a + 0.01]]), internal, t, PARAMS)
    obs = dist.observe(d, state, internal, 3)
    assert obs[0, 6:].tolist() == pytest.approx([0.3, 0.31, 0.2, 0.21])
    torch.testing.assert_close(obs[0, :6], state[0])


def test_observation_noise_has_the_stated_spread_on_positions_and_angle_only():
    d = dist.Disturbance(noise_position=0.03, noise_angle=0.01)
    keys = torch.arange(20000)
    internal = dist.start(d, keys)
    state = torch.rand(20000, 6)
    noise = dist.observe(d, state, internal, 7) - state
    std = noise.std(0)
    assert std[X].item() == pytest.approx(0.03, rel=0.03) and std[Z].item() == pytest.approx(0.03, rel=0.03)
    assert std[ALPHA].item() == pytest.approx(0.01, rel=0.03)
    assert noise[:, [X_DOT, Z_DOT, ALPHA_DOT]].abs().max().item() == 0.0
    # A fresh draw each step, the same draw for the same (key, step).
    assert not torch.equal(dist.observe(d, state, internal, 8), state + noise)
    torch.testing.assert_close(dist.observe(d, state, internal, 7), state + noise, rtol=0, atol=0)


def test_gusts_are_a_stationary_ornstein_uhlenbeck_process():
    d = dist.Disturbance(gust=0.2, gust_time=0.1)
    n = 4000
    internal = dist.start(d, torch.arange(n))
    state = torch.zeros(n, 6)
    gusts = [internal.gust]
    for t in range(40):
        _, _, _, internal = dist.step(d, state, HOVER.expand(n, 2), internal, t, PARAMS)
        gusts.append(internal.gust)
    g = torch.stack(gusts)  # [41, n]
    # The stationary std at every step, and the lag-1 correlation e^(-dt/tau) = e^-0.2.
    assert g[0].std().item() == pytest.approx(0.2, rel=0.05)
    assert g[-1].std().item() == pytest.approx(0.2, rel=0.05)
    corr = torch.corrcoef(torch.stack((g[:-1].flatten(), g[1:].flatten())))[0, 1].item()
    assert corr == pytest.approx(math.exp(-0.2), abs=0.02)


def test_gust_force_enters_like_the_wind():
    d = dist.Disturbance(gust=0.1)
    state, *_ = _step(d, _internal(d, gust=-0.15))
    assert state[0, X_DOT].item() == pytest.approx(-0.15 * G * DT, rel=1e-6)


def test_episode_draws_cover_their_ranges_and_follow_the_key_not_the_position():
    d = dist.Disturbance(**STRONG)
    keys = torch.arange(5000) * 7919
    draw = dist.draw_episode(d, keys)
    assert draw.wind.abs().max().item() <= 0.3 and draw.wind.abs().max().item() > 0.29
    assert 0.7 <= draw.mass_ratio.min().item() < 0.71 and 1.29 < draw.mass_ratio.max().item() <= 1.3
    assert draw.gain.min().item() >= 0.85 and draw.gain.max().item() <= 1.15
    # Left and right gains are independent draws.
    assert abs(torch.corrcoef(draw.gain.T)[0, 1].item()) < 0.05
    # The same key draws the same episode wherever it sits in the batch.
    order = torch.randperm(5000, generator=torch.Generator().manual_seed(0))
    shuffled = dist.draw_episode(d, keys[order])
    torch.testing.assert_close(shuffled.wind, draw.wind[order], rtol=0, atol=0)
    torch.testing.assert_close(shuffled.gain, draw.gain[order], rtol=0, atol=0)
    alone = dist.start(d, keys[17:18])
    torch.testing.assert_close(alone.gust, dist.start(d, keys).gust[17:18], rtol=0, atol=0)


@pytest.mark.parametrize(
    ("field", "value"),
    [("wind", -0.1), ("mass", 0.95), ("motor_gain", 1.0), ("gust_time", 0.0), ("action_delay", 1.5),
     ("observed_actions", -1), ("noise_angle", math.nan), ("action_delay", True)],
)  # fmt: skip
def test_bad_magnitudes_are_refused_in_one_line(field, value):
    with pytest.raises(ValueError, match=rf"^{field}=.* is not allowed; expected [^\n]+$"):
        dist.Disturbance(**{field: value})


def _preset(name: str) -> dict:
    """conf/disturbance/<name>.yaml as composed (the presets live in the configs only)."""
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import config_dir, env_kwargs

    with initialize_config_dir(config_dir(), version_base="1.3"):
        return env_kwargs(compose("eval", [f"disturbance={name}"]))["disturbance"]


def test_presets():
    presets = {name: dist.make(_preset(name)) for name in ("none", "mild", "strong")}
    assert not presets["none"].active and presets["none"] == dist.Disturbance()
    mild, strong = presets["mild"], presets["strong"]
    assert mild.active and strong.active and mild.action_delay == 1 and strong.action_delay == 2
    # A 30% heavier drone with a 15% weaker motor still lifts itself with max_thrust 1.
    assert 2 * (1 - strong.motor_gain) / (1 + strong.mass) > 1


STRONG = {"wind": 0.3, "gust": 0.15, "mass": 0.3, "motor_gain": 0.15, "motor_lag": 0.05,
          "noise_position": 0.03, "noise_angle": 0.03, "action_delay": 2}  # fmt: skip


def test_the_env_and_the_evaluator_fly_the_same_disturbed_episodes():
    from drone_torchrl.envs import DroneEnv
    from drone_torchrl.envs.heuristic import PDController
    from drone_torchrl.evaluation import evaluate

    env = DroneEnv(batch_size=[6], max_thrust=1.0, disturbance=STRONG)
    env.set_seed(3)
    td = env.rollout(300, PDController(env.params), break_when_any_done=False)
    stats, _ = evaluate(PDController(env.params), {"max_thrust": 1.0, "disturbance": STRONG}, 6, 3)
    lengths = stats["length"].tolist()
    env_returns = [td["next", "reward"][i, :n].sum().item() for i, n in enumerate(lengths)]
    assert env_returns == stats["return"].tolist()
    # The disturbances matter: the nominal drone flies other episodes (PD holds all 300 steps there).
    nominal, _ = evaluate(PDController(env.params), {"max_thrust": 1.0}, 6, 3)
    assert nominal["length"].tolist() == [300] * 6 and lengths != [300] * 6


def test_episode_keys_follow_the_seed_not_the_batch_layout():
    from drone_torchrl.envs import DroneEnv

    flat = DroneEnv(batch_size=[6], disturbance={"wind": 0.1})
    grid = DroneEnv(batch_size=[2, 3], disturbance={"wind": 0.1})
    flat.set_seed(5)
    grid.set_seed(5)
    flat.reset()
    grid.reset()
    assert torch.equal(grid.episode_keys.reshape(-1), flat.episode_keys)
    assert torch.equal(grid.state.reshape(-1, 6), flat.state)
    # A nominal env draws no keys, so its start states do not change with this feature.
    plain = DroneEnv(batch_size=[6])
    plain.set_seed(5)
    plain.reset()
    assert plain.episode_keys is None and torch.equal(plain.state, flat.state)


def test_a_partial_reset_draws_new_episodes_for_the_reset_rows_only():
    from tensordict import TensorDict

    from drone_torchrl.envs import DroneEnv

    env = DroneEnv(batch_size=[4], disturbance={"wind": 0.2, "mass": 0.2})
    env.set_seed(0)
    env.reset()
    before = env.episode_keys
    mask = torch.tensor([[True], [False], [True], [False]])
    env.reset(TensorDict({"_reset": mask}, batch_size=[4]))
    after = env.episode_keys
    assert torch.equal(after[1::2], before[1::2]) and (after[0::2] != before[0::2]).all()


def test_a_done_step_s_next_observation_survives_the_auto_reset():
    """With a disturbance that adds nothing to what the drone sees (wind alone), the observation was
    the env's state tensor itself: the auto-reset of a crashed drone then overwrote the next
    observation of its last step with the new episode's start (z 0.0 where it fell below -0.05),
    what PPO's GAE bootstraps from."""
    from tensordict import TensorDict

    from drone_torchrl.envs import DroneEnv

    env = DroneEnv(batch_size=[2], disturbance={"wind": 0.1})
    env.set_seed(0)
    td = env.reset()
    action = torch.tensor([[0.0, 0.0], [0.5, 0.5]])  # drone 0 falls, drone 1 holds
    for _ in range(20):
        out, td = env.step_and_maybe_reset(td.set("action", action))
        if bool(out["next", "done"][0]):
            break
    assert int(out["next", "termination_cause"][0]) == int(dynamics.TerminationCause.FLOOR)
    terminal = out["next", "observation"][0]
    assert float(terminal[Z]) < -0.05
    torch.testing.assert_close(terminal, out["next", "state"][0])
    assert float(td["observation"][0, Z]) == 0.0  # the new episode starts on the floor
    assert isinstance(td, TensorDict)


def test_observed_actions_reach_the_specs_and_the_networks():
    from torchrl.envs.utils import check_env_specs

    from drone_torchrl.envs import DroneEnv

    env = DroneEnv(batch_size=[3], disturbance={"observed_actions": 2, "action_delay": 1})
    check_env_specs(env)
    assert env.observation_spec["observation"].shape == (3, 10)
    td = env.rand_step(env.reset())
    assert torch.equal(td["next", "observation"][:, 6:8], td["action"])


def test_the_gymnasium_twin_flies_the_env_s_disturbed_episodes():
    from drone_torchrl.envs import DroneEnv, DroneGymEnv

    env = DroneEnv(batch_size=[], max_thrust=1.0, disturbance={**STRONG, "observed_actions": 1})
    twin = DroneGymEnv(max_thrust=1.0, disturbance={**STRONG, "observed_actions": 1})
    env.set_seed(11)
    td = env.reset()
    obs, _ = twin.reset(seed=11)
    assert twin.observation_space.shape == (8,)
    actions = torch.rand(40, 2, generator=torch.Generator().manual_seed(0)) * 0.4 + 0.4
    for action in actions:
        assert torch.equal(td["observation"], torch.from_numpy(obs))
        td = env.step(td.set("action", action))["next"]
        obs, reward, terminated, _, _ = twin.step(action.numpy())
        assert reward == td["reward"].item() and terminated == td["terminated"].item()
        if terminated:
            break


def test_one_observation_layout_names_every_entry_and_gives_every_width():
    from torch import nn

    from drone_torchrl import export
    from drone_torchrl.envs import DroneEnv, DroneGymEnv
    from drone_torchrl.modules.factory import observation_dim

    d = {"observed_actions": 2}
    names = dist.observation_names(d)
    assert names == (*dynamics.STATE_NAMES, "a_l[t-1]", "a_r[t-1]", "a_l[t-2]", "a_r[t-2]")
    assert dist.observation_names() == dynamics.STATE_NAMES
    env = DroneEnv(batch_size=[3], disturbance=d)
    assert env.observation_spec["observation"].shape == (3, 10)
    assert DroneGymEnv(disturbance=d).observation_space.shape == (10,)
    assert observation_dim({"env": {"disturbance": d}}) == observation_dim({"env": {}}) + 4 == 10
    assert export._observation_names(nn.Sequential(nn.Linear(10, 4))) == names
    # Each entry is what its name says: after commands (0.3, 0.7) then (0.4, 0.6), the newest first.
    env.set_seed(0)
    td = env.reset()
    for command in ((0.3, 0.7), (0.4, 0.6)):
        td["action"] = torch.tensor([command] * 3)
        td = env.step(td)["next"]
    seen = dict(zip(names, td["observation"][0].tolist(), strict=True))
    assert [seen[n] for n in names[6:]] == pytest.approx([0.4, 0.6, 0.3, 0.7])
    assert [seen[n] for n in dynamics.STATE_NAMES] == td["state"][0].tolist()
