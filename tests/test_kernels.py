"""The C++ kernels (drone_torchrl.kernels) against the PyTorch code they replace.

Every step the rollout kernel flies is checked against ``dynamics.step`` and the stacked policy
(teacher forcing: the PyTorch step is applied to the kernel's own state, so chaos cannot hide a
difference), its random numbers against ``envs.rng``, and the update kernel's loss and
gradient against TorchRL's ``ReinforceLoss`` with autograd on the episodes the kernel flew.
"""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from drone_torchrl.envs import dynamics, rng
from drone_torchrl.envs.params import PARAM_NAMES
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.episodes import counted_metrics, episode_stats
from drone_torchrl.kernels import build, library, ops
from drone_torchrl.kernels.modules import KernelReinforce, KernelRollout
from drone_torchrl.modules import ActionSampler, StackedThreeNet, ThreeNetPolicy, make_actor
from drone_torchrl.modules.policy import init_exploration
from drone_torchrl.objectives.reinforce import ReinforceLoss, discounted_returns

pytestmark = pytest.mark.skipif(
    library() is None, reason=f"C++ kernels unavailable: {build.unavailable_reason()}"
)

HEADS = {"normal": None, "tanh_normal": 1.0}  # distribution -> the TanhNormal's (and thrust's) bound


def _stacked(
    n: int, head: str, hidden=(32, 32), activation="tanh", std=0.3, seed=0, eps=0.0
) -> StackedThreeNet:
    torch.manual_seed(seed)
    nets = [ThreeNetPolicy(hidden, activation, distribution_eps=eps) for _ in range(n)]
    for net in nets:  # a policy that flies tens of steps, not one that falls at once
        init_exploration(net, std, 0.5 if head == "normal" else 0.0)
    return StackedThreeNet(nets, activation)


def _rollout(stacked, head, max_steps=300, reset_mode="floor", max_thrust="head") -> KernelRollout:
    bound = HEADS[head] if max_thrust == "head" else max_thrust
    return KernelRollout(stacked, dynamics.DroneParams(max_thrust=bound), HEADS[head], max_steps, reset_mode)


@pytest.mark.parametrize(
    ("head", "activation", "eps"),
    [("normal", "tanh", 0.0), ("tanh_normal", "tanh", 0.0), ("normal", "elu", 0.0), ("normal", "tanh", 1e-2)],
)
def test_every_step_equals_the_pytorch_policy_and_dynamics(head, activation, eps):
    """Each flown step: the action is the stacked net's ``f(loc + scale * noise)`` at the kernel's
    state, and the next state, reward and cause are ``dynamics.step``'s, to float rounding
    (also with ``distribution_eps``, the kernel's own shift of the mean and the std)."""
    n, e, steps = 3, 4, 300
    stacked = _stacked(n, head, activation=activation, std=0.1, eps=eps)
    flyer = _rollout(stacked, head, steps)
    start = dynamics.initial_state((n, e), "floor", torch.Generator().manual_seed(1))
    noise = torch.randn(n, e, steps, 2, generator=torch.Generator().manual_seed(2))
    episodes = flyer(start, noise)
    assert 20 < episodes.length.float().mean() < steps  # long enough to test, short enough to end
    params = dynamics.DroneParams(max_thrust=HEADS[head])
    sampler = ActionSampler(head, HEADS[head])
    valid = episodes.valid()
    with torch.no_grad():
        loc, scale = stacked(episodes.states[..., :-1, :])
        action = sampler(loc, scale, noise[..., : episodes.steps, :])
        following, reward, cause = dynamics.step(episodes.states[..., :-1, :], action, params)
    close = lambda a, b: torch.testing.assert_close(a[valid], b[valid], rtol=1e-5, atol=2e-6)  # noqa: E731
    close(episodes.action, action)
    close(episodes.states[..., 1:, :], following)
    assert torch.equal(episodes.reward[valid], reward[valid])
    assert torch.equal(episodes.cause[valid], cause[valid])
    # An episode ends at its first termination (or at max_steps), and nothing is kept after it.
    last = episodes.last()
    assert bool((episodes.cause[last] != 0).all() or (episodes.length == steps).any())
    assert bool((episodes.cause[valid & ~last] == 0).all())
    assert not episodes.reward[~valid].any() and not episodes.action[~valid].any()


def test_deterministic_episodes_fly_the_mean_action():
    stacked = _stacked(2, "tanh_normal")
    start = dynamics.initial_state((2, 3), "air", torch.Generator().manual_seed(0))
    episodes = _rollout(stacked, "tanh_normal")(start)
    with torch.no_grad():
        loc, _ = stacked(episodes.states[..., :-1, :])
    expected = 0.5 * (torch.tanh(loc) + 1.0)  # the TanhNormal's deterministic action on [0, 1]
    valid = episodes.valid()
    torch.testing.assert_close(episodes.action[valid], expected[valid], rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("reset_mode", ["floor", "air"])
def test_random_numbers_are_those_of_training_rng(reset_mode):
    """Start states drawn in the kernel are rng.uniform's bit for bit; the noise is rng.normal's to
    float rounding (the Box-Muller log, cos and sin are the kernel's own)."""
    n, e, steps = 4, 3, 300
    stacked = _stacked(n, "normal")
    flyer = _rollout(stacked, "normal", steps, reset_mode)
    seeds = torch.tensor([0, 1, 7, 2**62 + 12345])
    counters = torch.tensor([0, 3, 1000, 5])
    drawn = flyer(rng=torch.stack([seeds, counters], -1).unsqueeze(1).expand(-1, e, -1))
    start = dynamics.states_from_uniform(rng.uniform(seeds, counters, rng.START_STATES, (e, 6)), reset_mode)
    noise = rng.normal(seeds, counters, rng.ACTION_NOISE, (steps, e, 2)).transpose(1, 2)
    given = flyer(start, noise)
    assert torch.equal(drawn.states[..., 0, :], start)
    assert torch.equal(drawn.length, given.length)
    valid = given.valid()
    torch.testing.assert_close(drawn.action[valid], given.action[valid], rtol=0, atol=1e-6)


def test_returns_and_counts_equal_the_python_definitions():
    n, e, steps = 3, 5, 300
    stacked = _stacked(n, "normal")
    flyer = _rollout(stacked, "normal", steps)
    start = dynamics.initial_state((n, e), "floor", torch.Generator().manual_seed(3))
    noise = torch.randn(n, e, steps, 2, generator=torch.Generator().manual_seed(4))
    gamma = torch.tensor([0.99, 0.9, 0.5], dtype=torch.float64)
    states, action, reward, cause, length, returns, counts, _ = ops.rollout(
        stacked.flat.detach(), start, noise, None, torch.ones(n, dtype=torch.bool), flyer.env, gamma,
        flyer.hidden, flyer.activation, stacked.min_std, steps,
    )  # fmt: skip
    episodes = Episodes(states, action, reward, cause, length)
    expected = discounted_returns(
        reward.unsqueeze(-1), episodes.last().unsqueeze(-1), gamma.float().reshape(n, 1, 1)
    ).squeeze(-1)
    torch.testing.assert_close(returns, expected, rtol=1e-5, atol=1e-4)
    stats = episode_stats(episodes)
    for key, value in counted_metrics(length, counts).items():
        torch.testing.assert_close(value.to(stats[key].dtype), stats[key], msg=key)
    assert (stats["time_in_zone"] > 0).any() or (stats["return"] > 0).all()


def _torchrl_gradient(stacked, head, episodes, gamma, options, active):
    """ReinforceLoss over a plain make_actor() per agent (the TorchRL reference), with autograd."""
    losses, grads = [], []
    for agent in range(len(stacked)):
        actor = make_actor(
            head, stacked.hidden_sizes, stacked.activation_name, stacked.min_std, HEADS[head],
            distribution_eps=stacked.distribution_eps,
        )  # fmt: skip
        actor.module[0].module.load_state_dict(stacked.agent_state_dict(agent))
        batch = Episodes(*(x[agent] for x in episodes[:5])).as_rollout(300)  # states .. length
        loss_module = ReinforceLoss(actor, gamma=float(gamma[agent]), **options)
        out = loss_module(batch)
        out["loss_reinforce"].backward()
        net = actor.module[0].module
        grads.append(torch.cat([p.grad.reshape(-1) for p in net.parameters()]))
        losses.append(out["loss_reinforce"].detach())
    return torch.stack(losses) * active, torch.stack(grads) * active.unsqueeze(1)


OPTIONS = [
    {},
    {"baseline": "mean"},
    {"normalize_returns": True},
    {"discount_weight": True},
    {"log_prob_reduction": "mean"},
    {"baseline": "mean", "normalize_returns": True, "discount_weight": True, "log_prob_reduction": "mean"},
]


@pytest.mark.parametrize(
    ("head", "options", "eps"),
    [(head, options, 0.0) for head, options in itertools.product(HEADS, OPTIONS)]
    + [("normal", {"log_prob_reduction": "mean"}, 1e-2)],
)
def test_update_kernel_loss_and_gradient_equal_torchrl_reinforce_loss(head, options, eps):
    """On the episodes the update kernel flies (the same as KernelRollout with the same RNG keys),
    its loss and gradient equal ReinforceLoss + autograd agent by agent; an inactive agent gets zeros.
    With ``distribution_eps`` too (the paper's code's ``Normal(mu + eps, sigma + eps)``).

    Mutation caught (in drone_kernels.cpp): ``d_loc``'s sign flipped in ``log_prob_backward``."""
    n, e = 4, 3
    stacked = _stacked(n, head, eps=eps)
    flyer = _rollout(stacked, head)
    flags = {
        "baseline_mean": options.get("baseline") == "mean",
        "normalize_returns": options.get("normalize_returns", False),
        "discount_weight": options.get("discount_weight", False),
        "mean_log_prob": options.get("log_prob_reduction") == "mean",
    }
    seed, counter = torch.arange(n), torch.tensor([0, 3, 5, 9])
    gamma = torch.tensor([0.99, 0.9, 0.5, 0.999])
    active = torch.tensor([True, True, False, True])
    grad, loss, std, finite, length, counts = KernelReinforce(flyer, e, flags)(seed, counter, gamma, active)
    episodes = flyer(active=active, rng=torch.stack([seed, counter], -1).unsqueeze(1).expand(-1, e, -1))
    assert torch.equal(episodes.length, length)
    assert bool(finite.all()) and (length[~active] == 0).all()
    ref_loss, ref_grad = _torchrl_gradient(stacked, head, episodes, gamma, options, active)
    torch.testing.assert_close(loss.float(), ref_loss, rtol=2e-5, atol=2e-5)
    rel = (grad - ref_grad).norm(dim=1) / ref_grad.norm(dim=1).clamp_min(1e-12)
    assert float(rel[active].max()) < 2e-5, rel
    assert not grad[~active].any() and float(loss[~active].abs().sum()) == 0
    # The policy's mean std over the valid steps, as the PyTorch net gives it.
    with torch.no_grad():
        _, scale = stacked(episodes.states[..., :-1, :])
    valid = episodes.valid().unsqueeze(-1)
    expected_std = (scale * valid).sum((1, 2, 3)) / (valid.sum((1, 2, 3)) * 2).clamp_min(1)
    torch.testing.assert_close(std[active].float(), expected_std[active], rtol=1e-5, atol=1e-7)


def test_an_agent_does_not_depend_on_its_population():
    """Alone, first of 3 or last of 11 agents: the same episodes and gradient, bit for bit."""
    flags = dict.fromkeys(ops.LOSS_OPTIONS, False)
    mine = _stacked(1, "normal", seed=5)
    others = _stacked(10, "normal", seed=6)

    def run(stacked, where):
        n = len(stacked)
        seed, counter = torch.arange(100, 100 + n), torch.arange(n) * 7
        seed[where], counter[where] = 42, 3
        gamma = torch.linspace(0.5, 0.999, n)
        gamma[where] = 0.99
        out = KernelReinforce(_rollout(stacked, "normal"), 2, flags)(
            seed, counter, gamma, torch.ones(n, dtype=torch.bool)
        )
        return [x[where] for x in out]

    def population(before, after):
        flat = torch.cat([others.flat[:before], mine.flat, others.flat[before : before + after]])
        stacked = _stacked(before + 1 + after, "normal")
        with torch.no_grad():
            stacked.flat.copy_(flat)
        return stacked

    alone = run(mine, 0)
    for before, after in [(0, 2), (10, 0)]:
        for a, b in zip(alone, run(population(before, after), before), strict=True):
            assert torch.equal(a, b)


def test_the_update_kernel_called_on_chunks_of_agents_gives_the_whole_populations_outputs(monkeypatch):
    """ops.AGENTS_PER_CALL bounds the kernel's scratch memory: 7 agents run as chunks of 3, 3 and 1
    give the gradient, loss, std, lengths and counts of one call on all 7, bit for bit (a chunk
    written at the wrong rows, or reading another chunk's parameters, differs)."""
    flags = dict.fromkeys(ops.LOSS_OPTIONS, False)
    n = 7
    flyer = _rollout(_stacked(n, "normal", seed=3), "normal")
    args = (
        torch.arange(n),
        torch.arange(n) * 5,
        torch.linspace(0.5, 0.999, n),
        torch.ones(n, dtype=torch.bool),
    )
    args[3][4] = False
    whole = KernelReinforce(flyer, 2, flags)(*args)
    monkeypatch.setattr(ops, "AGENTS_PER_CALL", 3)
    chunked = KernelReinforce(flyer, 2, flags)(*args)
    assert whole[0][4].abs().sum() == 0 and whole[0][5].abs().sum() > 0
    for a, b in zip(whole, chunked, strict=True):
        assert torch.equal(a, b)


def test_float64_kernels_match_float32_to_rounding():
    stacked = _stacked(2, "normal")
    doubled = _stacked(2, "normal")
    with torch.no_grad():
        doubled.flat.data = stacked.flat.detach().double()
    start = dynamics.initial_state((2, 2), "air", torch.Generator().manual_seed(0))
    noise = torch.randn(2, 2, 40, 2, generator=torch.Generator().manual_seed(1))
    single = _rollout(stacked, "normal", 40)(start, noise)
    double = _rollout(doubled, "normal", 40)(start.double(), noise.double())
    assert double.states.dtype == torch.float64
    torch.testing.assert_close(double.states.float(), single.states, rtol=1e-4, atol=1e-4)


def test_non_finite_weights_give_non_finite_actions_and_no_crash():
    stacked = _stacked(3, "normal")
    with torch.no_grad():
        stacked.flat[1, 5] = math.nan
    flags = dict.fromkeys(ops.LOSS_OPTIONS, False)
    _, loss, _, finite, _, _ = KernelReinforce(_rollout(stacked, "normal"), 1, flags)(
        torch.arange(3),
        torch.zeros(3, dtype=torch.int64),
        torch.full((3,), 0.99),
        torch.ones(3, dtype=torch.bool),
    )
    assert finite.tolist() == [True, False, True]
    assert math.isfinite(loss[0]) and math.isfinite(loss[2])


def test_a_missing_compiler_falls_back_with_one_reason(tmp_path):
    """With no working compiler the kernels are unavailable, with the reason; nothing is cached."""
    code = (
        "from drone_torchrl.kernels import build\n"
        "assert build.library() is None\n"
        "print(build.unavailable_reason())\n"
    )
    env = {
        "CXX": str(tmp_path / "no-such-compiler"),
        "DRONE_TORCHRL_CACHE": str(tmp_path / "cache"),
        "PATH": "",
    }
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert "no C++ compiler found" in out.stdout
    assert not any((tmp_path / "cache").glob("*.so"))


@pytest.mark.slow  # two fresh processes, one of them compiling the kernels: about 20 s
def test_the_build_is_cached_per_source_and_machine(tmp_path):
    code = "from drone_torchrl.kernels import build\nassert build.library() is not None\n"
    env = {"DRONE_TORCHRL_CACHE": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    subprocess.run([sys.executable, "-c", code], env=env, check=True)
    built = list(tmp_path.glob("drone_kernels-float32-*.so"))
    assert len(built) == 1 and not list(tmp_path.glob("*.tmp"))
    stamp = built[0].stat().st_mtime_ns
    subprocess.run([sys.executable, "-c", code], env=env, check=True)
    assert built[0].stat().st_mtime_ns == stamp  # loaded, not built again


def test_the_kernels_read_every_constant_python_packs():
    # The kernels' own list (its order: their offsets) is Python's: DroneParams' fields first.
    read = tuple(library().dk_env_constants().decode().split(",")[:-1])
    assert read == ops.ENV_CONSTANTS and read[: len(PARAM_NAMES)] == PARAM_NAMES
    params = dynamics.DroneParams(max_thrust=2.0, floor_tolerance=0.1, bounds="strict")
    env = dict(zip(ops.ENV_CONSTANTS, ops.env_constants(params, 2.0, "air").tolist(), strict=True))
    assert env["floor"] == pytest.approx(-0.1) and env["max_thrust"] == env["squash_high"] == 2.0
    assert env["reset_air"] == 1.0 and env["arm_over_inertia"] == pytest.approx(0.5 / (0.4 * 0.25))
    assert env["bounds"] == 1.0 and env["zone_x_limit"] == 0.8 and env["zone_z_centre"] == pytest.approx(2.7)
    paper = dict(
        zip(ops.ENV_CONSTANTS, ops.env_constants(dynamics.DroneParams(), None).tolist(), strict=True)
    )
    assert (
        paper["max_thrust"] == paper["squash_high"] == -1.0 and paper["bounds"] == paper["reset_air"] == 0.0
    )


def test_a_library_reading_other_constants_or_observations_is_refused_at_load(monkeypatch):
    """The names and offsets are checked when a library loads, not only their count.

    Two constants swapped (the count unchanged), or an observation of another width, as after a
    DroneParams field or an observation entry added on one side only: the loader refuses the library.
    """
    path = Path(library()._name)
    assert build._load(path, double=False) is not None  # as built: it loads
    names = list(build.ENV_CONSTANTS)
    names[1], names[2] = names[2], names[1]
    monkeypatch.setattr(build, "ENV_CONSTANTS", tuple(names))
    with pytest.raises(OSError, match=r"reads the constants \('mass', 'motor_distance', 'gravity'"):
        build._load(path, double=False)
    monkeypatch.undo()
    monkeypatch.setattr(dynamics, "STATE_NAMES", (*dynamics.STATE_NAMES, "extra"))
    with pytest.raises(OSError, match="sees 6 observation entries with 0 observed commands; drone_torchrl 7"):
        build._load(path, double=False)
    monkeypatch.undo()
    # A library built from another version of the source (DRONE_TORCHRL_CUDA_LIBRARY names any file):
    # its entry points take other arguments, which no constant shows.
    monkeypatch.setattr(build, "ABI_VERSION", build.ABI_VERSION + 1)
    with pytest.raises(
        OSError, match=f"arguments of version {build.ABI_VERSION - 1}, not {build.ABI_VERSION}"
    ):
        build._load(path, double=False)
