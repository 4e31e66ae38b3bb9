"""The env's arena, ``bounds`` and ``dtype`` arguments on both backends: DroneEnv, the Gymnasium twin,
the C++ kernels of the fast engine, and the learners built from a config.

The boundary cases are hand-made states exactly on a bound, stepped once with the hover command
(both motors at half the weight): with ``alpha = 0`` and no velocity that step leaves the state
exactly where it was (every term of the Euler step is exact), and with a tilt it moves ``x`` and
``z`` but leaves ``alpha`` on its bound. The arena's numbers are exact binary fractions, so "on the
bound" means the same thing in float32 and float64.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

import drone_torchrl  # noqa: F401  (registers Drone2D-v0)
from drone_torchrl.config import config_dir, physics_params
from drone_torchrl.envs import DroneEnv, dynamics, rng
from drone_torchrl.envs.dynamics import TerminationCause as C
from drone_torchrl.kernels import build, library, ops
from drone_torchrl.kernels.modules import KernelRollout
from drone_torchrl.modules import StackedThreeNet, ThreeNetPolicy

NONE, OUT_X, FLOOR, CEILING, TILT = C.NONE, C.OUT_X, C.FLOOR, C.CEILING, C.TILT
needs_kernels = pytest.mark.skipif(library() is None, reason=f"no C++ kernels: {build.unavailable_reason()}")

# Not the paper's arena (every number changed), in exact binary fractions. The floor is hit at
# z_min - floor_tolerance = 0.25.
ARENA = {
    "x_limit": 1.5,
    "z_min": 0.5,
    "z_max": 3.5,
    "alpha_limit": 0.75,
    "zone_x_limit": 0.5,
    "zone_z_min": 2.0,
    "zone_z_max": 3.0,
    "floor_tolerance": 0.25,
}
HOVER = 0.5

# (x, z, alpha) on one bound or edge each, and what the step gives: (cause, reward) with inclusive
# bounds, then with strict ones.
EDGES = [
    ((0.0, 2.5, 0.0), (NONE, 10.0), (NONE, 10.0)),  # inside the zone: no edge
    ((0.5, 2.5, 0.0), (NONE, 10.0), (NONE, 1.0)),  # zone's x edge
    ((-0.5, 2.5, 0.0), (NONE, 10.0), (NONE, 1.0)),
    ((0.0, 2.0, 0.0), (NONE, 10.0), (NONE, 1.0)),  # zone's bottom
    ((0.0, 3.0, 0.0), (NONE, 10.0), (NONE, 1.0)),  # zone's top
    ((0.0, 2.5, 0.75), (NONE, 10.0), (TILT, 0.0)),  # the tilt bound, in the zone
    ((0.0, 2.5, -0.75), (NONE, 10.0), (TILT, 0.0)),
    ((1.5, 1.0, 0.0), (NONE, 1.0), (OUT_X, 0.0)),  # the domain's x bound
    ((-1.5, 1.0, 0.0), (NONE, 1.0), (OUT_X, 0.0)),
    ((0.0, 3.5, 0.0), (NONE, 1.0), (CEILING, 0.0)),  # the ceiling
    ((0.0, 0.25, 0.0), (NONE, 1.0), (FLOOR, 0.0)),  # the floor (z_min - floor_tolerance)
    ((1.5, 3.5, 0.0), (NONE, 1.0), (OUT_X, 0.0)),  # two bounds at once: the lowest code wins
]
DTYPES = [torch.float32, torch.float64]


def _states(dtype: torch.dtype) -> torch.Tensor:
    rows = [[x, 0.0, z, 0.0, alpha, 0.0] for (x, z, alpha), _, _ in EDGES]
    return torch.tensor(rows, dtype=dtype)


def _expected(bounds: str) -> tuple[list[int], list[float]]:
    column = 1 if bounds == "inclusive" else 2
    return [int(e[column][0]) for e in EDGES], [e[column][1] for e in EDGES]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bounds", ["inclusive", "strict"])
def test_states_on_a_bound_in_droneenv(bounds, dtype):
    env = DroneEnv(batch_size=[len(EDGES)], bounds=bounds, dtype=dtype, **ARENA)
    td = env.reset()
    env._state = _states(dtype)
    td["action"] = torch.full((len(EDGES), 2), HOVER, dtype=dtype)
    nxt = env.step(td)["next"]
    causes, rewards = _expected(bounds)
    assert nxt["termination_cause"].squeeze(-1).tolist() == causes
    assert nxt["reward"].squeeze(-1).tolist() == rewards
    assert nxt["terminated"].squeeze(-1).tolist() == [c != 0 for c in causes]
    level = _states(dtype)[:, dynamics.ALPHA] == 0
    assert torch.equal(nxt["observation"][level], _states(dtype)[level])  # the hover step kept them on it
    assert torch.equal(nxt["observation"][:, dynamics.ALPHA], _states(dtype)[:, dynamics.ALPHA])
    assert nxt["observation"].dtype == nxt["reward"].dtype == dtype


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bounds", ["inclusive", "strict"])
def test_states_on_a_bound_in_the_gym_twin(bounds, dtype):
    env = gym.make("Drone2D-v0", bounds=bounds, dtype=str(dtype).removeprefix("torch."), **ARENA).unwrapped
    causes, rewards = _expected(bounds)
    for state, cause, reward in zip(_states(dtype), causes, rewards, strict=True):
        env.reset(seed=0)
        env.env._state = state.clone()  # the one drone of the DroneEnv it adapts
        obs, r, terminated, _, info = env.step([HOVER, HOVER])
        assert (info["termination_cause"], r, terminated) == (C(cause).name, reward, cause != 0)
        assert obs.dtype == env.observation_space.dtype == str(dtype).removeprefix("torch.")
    env.close()


def _hover_policy(n: int, dtype: torch.dtype) -> StackedThreeNet:
    """Agents whose deterministic action is exactly the hover command in every state."""
    torch.manual_seed(0)
    stacked = StackedThreeNet([ThreeNetPolicy((8,)) for _ in range(n)], "tanh")
    with torch.no_grad():
        stacked.flat.data = stacked.flat.to(dtype)
        params = stacked.params
        params.get(("mean", "weight")).zero_()
        params.get(("mean", "bias")).fill_(HOVER)
    return stacked


@needs_kernels
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("bounds", ["inclusive", "strict"])
def test_states_on_a_bound_in_the_kernels(bounds, dtype):
    params = physics_params({**ARENA, "bounds": bounds})
    flyer = KernelRollout(_hover_policy(1, dtype), params, None, max_steps=1)
    episodes = flyer(_states(dtype).unsqueeze(0))  # [1 agent, one row per edge, 6]
    causes, rewards = _expected(bounds)
    assert episodes.cause[0, :, 0].tolist() == causes
    assert episodes.reward[0, :, 0].tolist() == rewards
    assert episodes.reward.dtype == episodes.states.dtype == dtype


def test_the_zone_and_bounds_arguments_move_the_edges():
    """The same state is in or out of the zone, or terminated or not, by the arguments alone; the
    paper's code's zone ``|x| < 0.6`` puts x = 0.6 (the float32 nearest, compared in float32) out."""
    state = torch.tensor([0.6, 0.0, 2.7, 0.0, 0.0, 0.0])
    in_zone = lambda **kw: bool(dynamics.in_target_zone(state, physics_params(kw)))  # noqa: E731
    assert in_zone() and in_zone(zone_x_limit=0.6)
    assert not in_zone(zone_x_limit=0.6, bounds="strict") and not in_zone(zone_x_limit=0.5)
    high = torch.tensor([0.0, 0.0, 4.5, 0.0, 0.0, 0.0])
    assert int(dynamics.termination_cause(high, physics_params({}))) == CEILING
    assert int(dynamics.termination_cause(high, physics_params({"z_max": 5.0}))) == NONE
    tilted = torch.tensor([0.0, 0.0, 2.7, 0.0, 0.5, 0.0])
    assert int(dynamics.termination_cause(tilted, physics_params({"alpha_limit": 0.4}))) == TILT
    assert dynamics.reward(tilted, torch.tensor(False), physics_params({"alpha_limit": 0.6})).item() == 10.0


# ------------------------------------------------------------------------------ the start states


@pytest.mark.parametrize("reset_mode", ["floor", "air"])
def test_a_seed_gives_the_same_starts_in_both_envs_and_both_precisions(reset_mode):
    starts = {}
    for dtype in ("float32", "float64"):
        env = DroneEnv(batch_size=[3], reset_mode=reset_mode, dtype=dtype, **ARENA)
        env.set_seed(11)
        starts["env", dtype] = env.reset()["observation"]
        twin = gym.make("Drone2D-v0", reset_mode=reset_mode, dtype=dtype, **ARENA)
        observations = [twin.reset(seed=11)[0]]
        for _ in range(2):  # a step between resets: a reset right after reset(seed) repeats the start
            twin.step([HOVER, HOVER])
            observations.append(twin.reset()[0])
        starts["gym", dtype] = torch.from_numpy(np.stack(observations))
    for dtype in ("float32", "float64"):
        assert torch.equal(starts["env", dtype], starts["gym", dtype])
        assert starts["env", dtype].dtype == dynamics.DTYPES[dtype]
    single, double = starts["env", "float32"], starts["env", "float64"]
    # The noise is drawn and scaled in float32 in both; only the start point is added in float64.
    torch.testing.assert_close(double.float(), single, rtol=0, atol=0 if reset_mode == "floor" else 2.4e-7)
    centre = 0.5 * (ARENA["zone_z_min"] + ARENA["zone_z_max"]) if reset_mode == "air" else ARENA["z_min"]
    assert (double[:, dynamics.Z] - centre).abs().max() <= (0.01 if reset_mode == "air" else 0.0)


@needs_kernels
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("reset_mode", ["floor", "air"])
def test_the_kernels_draw_the_fast_engines_starts_bit_for_bit(reset_mode, dtype):
    """The fast engine draws its start states in the kernel, as rng.uniform and
    dynamics.states_from_uniform define them: the same states with the arena's floor and zone, in
    either precision."""
    params = physics_params(ARENA)
    seeds, counters, e = torch.tensor([0, 5]), torch.tensor([3, 0]), 4
    flyer = KernelRollout(_hover_policy(2, dtype), params, None, max_steps=1, reset_mode=reset_mode)
    drawn = flyer(rng=torch.stack([seeds, counters], -1).unsqueeze(1).expand(-1, e, -1))
    uniform = rng.uniform(seeds, counters, rng.START_STATES, (e, dynamics.STATE_DIM))
    expected = dynamics.states_from_uniform(uniform, reset_mode, params, dtype)
    assert torch.equal(drawn.states[..., 0, :], expected)


# ------------------------------------------------------------------------------ float64


def _fly(dtype: str, actions: torch.Tensor, **kwargs) -> dict[str, torch.Tensor]:
    """50 open-loop steps of 8 drones from seed 3 (no termination: the actions climb gently)."""
    env = DroneEnv(batch_size=[actions.shape[1]], dtype=dtype, **kwargs)
    env.set_seed(3)
    steps = actions.shape[0]
    td = env.rollout(steps, lambda td: td.set("action", actions[int(td["step_count"][0])].to(env.dtype)))
    following = td["next"]
    return {
        key: following[name]
        for key, name in [("obs", "observation"), ("reward", "reward"), ("cause", "termination_cause")]
    }


def _climbing_actions(steps: int = 50, drones: int = 8) -> torch.Tensor:
    noise = torch.randn(steps, drones, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return 0.55 + 0.05 * noise


@pytest.mark.parametrize("kwargs", [{}, {**ARENA, "bounds": "strict"}], ids=["paper", "arena-strict"])
def test_float64_matches_float32_to_rounding_and_is_float64_throughout(kwargs):
    """Tolerance: a step rounds each state component about ten times to float32 (relative 6e-8
    each); added up over 50 steps on states below 1.4 (these flights) that is at most
    50 x 10 x 6e-8 x 1.4 = 4e-5. Measured: 1e-6 (roundings partly cancel). A physics difference
    (a term of one step, ``g dt^2 = 4e-3``) is a hundred times larger."""
    actions = _climbing_actions()
    single, double = _fly("float32", actions, **kwargs), _fly("float64", actions, **kwargs)
    assert double["obs"].dtype == double["reward"].dtype == torch.float64
    assert single["obs"].dtype == single["reward"].dtype == torch.float32
    assert not double["cause"].any() and not single["cause"].any()
    assert double["obs"].abs().max() < 1.4
    torch.testing.assert_close(double["obs"], single["obs"].double(), rtol=0, atol=4e-5)
    assert torch.equal(double["reward"].float(), single["reward"])
    assert not torch.equal(double["obs"], single["obs"].double())  # really computed in float64


def test_the_gym_twin_in_float64_is_droneenv_in_float64_bit_for_bit():
    actions = _climbing_actions(drones=1)
    native = _fly("float64", actions, reset_mode="air", **ARENA)
    twin = gym.make("Drone2D-v0", reset_mode="air", dtype="float64", **ARENA)
    twin.reset(seed=3)
    obs = np.stack([twin.step(a.numpy())[0] for a in actions[:, 0]])
    assert obs.dtype == np.float64
    assert torch.equal(torch.from_numpy(obs), native["obs"][0])


@needs_kernels
def test_the_float64_kernel_is_the_float64_dynamics_with_the_arena():
    """Teacher forcing over 50 steps: each step the kernel flew, from its own state and action, is
    dynamics.step's in float64 (the C library's sin and cos per lane: to 1e-12)."""
    params = physics_params({**ARENA, "bounds": "strict"})
    torch.manual_seed(1)
    nets = [ThreeNetPolicy((16,)) for _ in range(2)]
    for net in nets:
        with torch.no_grad():
            net.mean.bias.fill_(0.55)
    stacked = StackedThreeNet(nets, "tanh")
    stacked.flat.data = stacked.flat.detach().double()
    generator = torch.Generator().manual_seed(2)
    start = dynamics.initial_state((2, 3), "floor", generator, dtype=torch.float64, params=params)
    noise = 0.05 * torch.randn(2, 3, 50, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    episodes = KernelRollout(stacked, params, None, 50)(start, noise)
    assert episodes.states.dtype == torch.float64 and episodes.length.min() > 10
    valid = episodes.valid()
    following, reward, cause = dynamics.step(episodes.states[..., :-1, :], episodes.action, params)
    torch.testing.assert_close(episodes.states[..., 1:, :][valid], following[valid], rtol=1e-12, atol=1e-12)
    assert torch.equal(episodes.reward[valid], reward[valid])
    assert torch.equal(episodes.cause[valid], cause[valid])


def _config(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=["env.max_steps=30", "algo.episodes_per_update=2", *overrides])


@needs_kernels
def test_the_fast_engine_trains_in_float64_end_to_end():
    """env.dtype=float64: the weights, the flown episodes (states, rewards) and the update's loss
    and gradient are float64 on the C++ engine, with the arena's zone and bounds."""
    from drone_torchrl.algorithms.reinforce import Reinforce
    from drone_torchrl.training.agents import AgentTable

    cfg = _config("env.dtype=float64", "env.zone_x_limit=0.6", "env.bounds=strict", "backend=fast")
    update = Reinforce(AgentTable.of([cfg]))
    population, collector = update.population, update.collector
    assert population.state["params"].dtype == torch.float64
    active = torch.ones(1, dtype=torch.bool)
    gradient = update.gradient(population.state, population.state["counter"].clone(), active)
    assert gradient.grad.dtype == gradient.loss.dtype == torch.float64
    start = dynamics.initial_state((1, 2), "floor", torch.Generator().manual_seed(0), dtype=torch.float64)
    episodes = collector.kernel(start)
    assert episodes.states.dtype == episodes.reward.dtype == episodes.action.dtype == torch.float64


def test_the_reference_flies_float64():
    from drone_torchrl.training.collectors import TorchRLCollector
    from drone_torchrl.training.population import Population

    cfg = _config("env.dtype=float64", "backend=reference")
    population = Population([cfg])
    batch = TorchRLCollector(cfg, population).collect(torch.ones(1, dtype=torch.bool))
    for key in ("observation", "action", ("next", "reward"), ("next", "observation")):
        assert batch[key].dtype == torch.float64, key


@needs_kernels
def test_the_kernels_returns_to_go_are_float64():
    params = physics_params(ARENA)
    stacked = _hover_policy(1, torch.float64)
    generator = torch.Generator().manual_seed(0)
    start = dynamics.initial_state((1, 2), "air", generator, dtype=torch.float64, params=params)
    env = ops.env_constants(params, None, "air")
    out = ops.rollout(stacked.flat.detach(), start, None, None, torch.ones(1, dtype=torch.bool), env,
                      torch.tensor([0.99], dtype=torch.float64), stacked.hidden_sizes, 0, stacked.min_std, 20)  # fmt: skip
    reward, returns = out[2], out[5]
    assert reward.dtype == returns.dtype == torch.float64
    assert (reward == 10.0).all()  # hovering in the zone's centre
    expected = sum(0.99**k * 10.0 for k in range(20))
    assert returns[0, 0, 0].item() == pytest.approx(expected, rel=1e-14)
