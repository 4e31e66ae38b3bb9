"""The fast engine's kernels under disturbances, equal to the PyTorch reference given the same draws.

The reference is the TorchRL design: :mod:`drone_torchrl.envs.disturbances` (``observe``, ``step``),
:class:`~drone_torchrl.modules.StackedThreeNet` with :class:`~drone_torchrl.modules.ActionSampler`,
:class:`~drone_torchrl.objectives.ReinforceLoss` with autograd, and :class:`~drone_torchrl.envs.DroneEnv`
stepped by TorchRL's ``step_and_maybe_reset`` (what its collector does). The kernels get the same
start states, action noise and episode keys. Each test runs under the presets of
``conf/disturbance/`` and under each disturbance key alone, both heads, float32 and float64.

Each equality test's docstring names a mutation of ``drone_kernels.cpp`` that it was seen to catch.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from drone_torchrl.config import config_dir
from drone_torchrl.envs import DroneEnv, disturbances, dynamics, rng
from drone_torchrl.envs.rollout import Episodes
from drone_torchrl.kernels import build, library, ops
from drone_torchrl.kernels.modules import KernelReinforce, KernelRollout, KernelSegments
from drone_torchrl.modules import ActionSampler, StackedThreeNet, ThreeNetPolicy
from drone_torchrl.modules.policy import actor_from_net, init_exploration
from drone_torchrl.objectives.reinforce import ReinforceLoss, reinforce_terms, valid_steps

pytestmark = pytest.mark.skipif(
    library() is None, reason=f"C++ kernels unavailable: {build.unavailable_reason()}"
)

MAX_THRUST = 1.0  # bounded thrust (experiment=bounded): the clamp before the gain matters
HEADS = {"normal": None, "tanh_normal": MAX_THRUST}  # head -> what the kernel squashes onto
# Each key alone, at the strong preset's magnitude (the gusts' time scale with gusts, the delay
# and the observed commands at 2).
ALONE = {
    "wind": {"wind": 0.3},
    "gust": {"gust": 0.15, "gust_time": 0.1},
    "mass": {"mass": 0.3},
    "motor_gain": {"motor_gain": 0.15},
    "motor_lag": {"motor_lag": 0.05},
    "noise_position": {"noise_position": 0.03},
    "noise_angle": {"noise_angle": 0.03},
    "action_delay": {"action_delay": 2},
    "observed_actions": {"observed_actions": 2},
}
CONDITIONS = ["none", "mild", "strong", *ALONE]
DTYPES = {"float32": torch.float32, "float64": torch.float64}
CASES = [
    pytest.param(c, h, d, id=f"{c}-{h}-{d}") for c in CONDITIONS for h in HEADS for d in DTYPES
]  # fmt: skip


@functools.cache
def _preset(name: str) -> disturbances.Disturbance:
    """conf/disturbance/<name>.yaml (over none.yaml, as its defaults list says)."""
    folder = Path(config_dir()) / "disturbance"
    merged = OmegaConf.merge(OmegaConf.load(folder / "none.yaml"), OmegaConf.load(folder / f"{name}.yaml"))
    merged.pop("defaults", None)
    return disturbances.make(OmegaConf.to_container(merged))


def _disturbance(name: str) -> disturbances.Disturbance:
    return disturbances.make(ALONE[name]) if name in ALONE else _preset(name)


def _stacked(n: int, head: str, d: disturbances.Disturbance, dtype: torch.dtype, seed: int = 0, mean=None):
    """``n`` agents that fly tens of steps (not ones that fall at once) on ``d``'s observations."""
    torch.manual_seed(seed)
    nets = [ThreeNetPolicy((32, 32), "tanh", obs_dim=d.observation_dim) for _ in range(n)]
    for net in nets:
        init_exploration(net, 0.2, (0.5 if head == "normal" else 0.0) if mean is None else mean)
    return StackedThreeNet(nets, "tanh").to(dtype)


def _close(a: torch.Tensor, b: torch.Tensor, msg: str = "") -> None:
    torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6, msg=msg)


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_every_disturbed_step_equals_the_reference(condition, head, dtype):
    """Each flown step of ``ops.rollout`` with given start states, noise and episode keys:
    the observation is ``disturbances.observe``'s, the action the stacked net's sample at it, and
    the next state, reward and cause ``disturbances.step``'s (``dynamics.step``'s for the nominal
    drone) from the kernel's state and action (teacher forcing: chaos cannot hide a difference; the
    reference carries its own gusts, lag, delay and command memory).

    Mutations caught: the gusts without their decay (``dr.gust * d.gust_decay`` -> ``dr.gust``);
    the motor gain on the command before the clamp (``command`` clamped after the thrust)."""
    d, dtype = _disturbance(condition), DTYPES[dtype]
    n, e, steps = 2, 3, 60
    stacked = _stacked(n, head, d, dtype)
    params = dynamics.DroneParams(max_thrust=MAX_THRUST)
    flyer = KernelRollout(stacked, params, HEADS[head], steps, disturbance=d)
    generator = torch.Generator().manual_seed(1)
    start = dynamics.initial_state((n, e), "floor", generator, dtype=dtype)
    noise = torch.randn(n, e, steps, 2, generator=generator, dtype=dtype)
    keys = disturbances.episode_keys(generator, (n, e))
    episodes = flyer(start, noise, keys=keys)
    assert 10 < episodes.length.float().mean() < steps  # long enough to test, short enough to end
    valid = episodes.valid()
    seen, states, action = episodes.inputs(), episodes.states[..., :-1, :], episodes.action
    with torch.no_grad():
        loc, scale = stacked(seen)
    _close(
        action[valid], ActionSampler(head, HEADS[head])(loc, scale, noise[..., : episodes.steps, :])[valid]
    )
    if d.nominal:
        observation, (following, reward, cause) = states, dynamics.step(states, action, params)
    else:  # the reference's internal state (gusts, lag, delay, commands) goes step by step
        internal, columns = disturbances.start(d, keys, dtype), []
        for t in range(episodes.steps):
            seen_t = disturbances.observe(d, states[..., t, :], internal, t)
            *after, internal = disturbances.step(d, states[..., t, :], action[..., t, :], internal, t, params)
            columns.append((seen_t, *after))
        observation, following, reward, cause = (torch.stack(c, 2) for c in zip(*columns, strict=True))
    _close(seen[valid], observation[valid], "observation")
    _close(episodes.states[..., 1:, :][valid], following[valid], "next state")
    assert torch.equal(episodes.reward[valid], reward[valid])
    assert torch.equal(episodes.cause[valid], cause[valid])
    assert episodes.observation is None if d.nominal else episodes.observation.shape[-1] == d.observation_dim


def test_deterministic_disturbed_episodes_fly_the_mean_action():
    """Without noise (the evaluator's episodes) the action is the mean at what the policy saw."""
    d = disturbances.make({**dataclasses.asdict(_preset("strong")), "observed_actions": 2})
    stacked = _stacked(2, "tanh_normal", d, torch.float32)
    flyer = KernelRollout(
        stacked, dynamics.DroneParams(max_thrust=MAX_THRUST), MAX_THRUST, 100, disturbance=d
    )
    generator = torch.Generator().manual_seed(0)
    start = dynamics.initial_state((2, 3), "floor", generator)
    episodes = flyer(start, keys=disturbances.episode_keys(generator, (2, 3)))
    with torch.no_grad():
        loc, _ = stacked(episodes.observation)
    valid = episodes.valid()
    _close(episodes.action[valid], (0.5 * MAX_THRUST * (torch.tanh(loc) + 1.0))[valid])
    assert bool((episodes.observation[..., 6:][valid] != 0).any())  # the commands it saw


def test_episode_keys_drawn_in_the_kernel_are_training_rng_s():
    """With ``rng`` and no ``keys``, episode ``e`` of an agent flies with key ``rng.keys(seed,
    counter, EPISODE_KEYS, (E,))[e]``: the same episodes as with those keys given.

    Mutation caught: the episode keys drawn from the wrong stream (``kEpisodeKeys = 3`` -> ``4``)."""
    d = _preset("strong")
    n, e = 3, 4
    stacked = _stacked(n, "normal", d, torch.float32)
    flyer = KernelRollout(stacked, dynamics.DroneParams(max_thrust=MAX_THRUST), None, 300, disturbance=d)
    seeds, counters = torch.tensor([0, 5, 2**40]), torch.tensor([0, 7, 123])
    key_pairs = torch.stack([seeds, counters], -1).unsqueeze(1).expand(-1, e, -1)
    drawn = flyer(rng=key_pairs)
    given = flyer(rng=key_pairs, keys=rng.keys(seeds, counters, rng.EPISODE_KEYS, (e,)))
    for a, b in zip(drawn, given, strict=True):
        assert torch.equal(a, b)
    other = flyer(rng=key_pairs, keys=rng.keys(seeds, counters, rng.EPISODE_KEYS, (e,)) + 1)
    assert not torch.equal(other.observation, given.observation)  # the keys matter


def _reference_loss(stacked, head, episodes: Episodes, gamma, d):
    """ReinforceLoss (baseline, normalised returns) + autograd per agent on the kernel's episodes,
    the policy's inputs being the observations the kernel's policy saw, in float64 whatever the
    kernel's precision. Also each agent's loss scale, ``sum_t |c_t log pi_t|`` where the loss is
    ``sum_t c_t log pi_t``: with normalised returns the terms nearly cancel, and float32 rounding
    of the returns-to-go moves the loss by about 1e-6 of that scale (ReinforceLoss's own float32
    loss as much as the kernel's)."""
    episodes = Episodes(*(x if x is None or not x.is_floating_point() else x.double() for x in episodes))
    losses, grads, scales = [], [], []
    for agent in range(len(stacked)):
        net = ThreeNetPolicy((32, 32), "tanh", obs_dim=d.observation_dim).double()
        net.load_state_dict(stacked.agent_state_dict(agent))
        batch = Episodes(*(x[agent] for x in episodes[:5])).as_rollout(300)
        batch["observation"] = episodes.inputs()[agent, :, : batch.shape[-1]]
        actor = actor_from_net(net, head, MAX_THRUST)
        options = {"gamma": float(gamma[agent]), "baseline": "mean", "normalize_returns": True}
        loss = ReinforceLoss(actor, **options)(batch)["loss_reinforce"]
        loss.backward()
        grads.append(torch.cat([p.grad.reshape(-1) for p in net.parameters()]))
        losses.append(loss.detach())
        with torch.no_grad():
            log_prob = actor.get_dist(batch).log_prob(batch["action"])
        log_prob.requires_grad_()
        done = batch["next", "done"].squeeze(-1)
        terms = reinforce_terms(
            log_prob, batch["next", "reward"].squeeze(-1), done, valid_steps(done.unsqueeze(-1)).squeeze(-1),
            batch["step_count"].squeeze(-1), **options,
        )  # fmt: skip
        terms["loss_reinforce"].backward()  # log_prob.grad: each step's c_t
        scales.append((log_prob.grad * log_prob).abs().sum().detach())
    return torch.stack(losses), torch.stack(grads), torch.stack(scales)


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_disturbed_update_equals_reinforce_loss(condition, head, dtype):
    """``ops.reinforce`` under disturbances (start states, noise and episode keys drawn
    from the agents' RNG keys): its episodes are ``KernelRollout``'s with the same keys, and its
    loss and gradient ReinforceLoss's with autograd, through the observations the policy saw: the
    gradient to 2e-5 relative; the loss to 1e-5 relative in float64, and in float32 to 1e-5 of its
    scale (see ``_reference_loss``: the float32 kernel sums the returns-to-go as it always did).

    Mutation caught: the backward through the true state instead of the observation (the saved
    inputs written from ``dr.s`` instead of ``block.x``)."""
    d, dtype = _disturbance(condition), DTYPES[dtype]
    n, e = 2, 2
    stacked = _stacked(n, head, d, dtype)
    flyer = KernelRollout(
        stacked, dynamics.DroneParams(max_thrust=MAX_THRUST), HEADS[head], 300, disturbance=d
    )
    flags = {
        "baseline_mean": True,
        "normalize_returns": True,
        "discount_weight": False,
        "mean_log_prob": False,
    }
    seed, counter, gamma = torch.tensor([3, 4]), torch.tensor([1, 2]), torch.tensor([0.99, 0.9])
    active = torch.ones(n, dtype=torch.bool)
    grad, loss, _, finite, length, _ = KernelReinforce(flyer, e, flags)(seed, counter, gamma, active)
    episodes = flyer(rng=torch.stack([seed, counter], -1).unsqueeze(1).expand(-1, e, -1))
    assert torch.equal(episodes.length, length) and bool(finite.all())
    ref_loss, ref_grad, scale = _reference_loss(stacked, head, episodes, gamma, d)
    assert bool(
        ((loss - ref_loss).abs() <= 1e-5 * (scale if dtype == torch.float32 else ref_loss.abs())).all()
    )
    rel = (grad.double() - ref_grad).norm(dim=1) / ref_grad.norm(dim=1)
    assert float(rel.max()) < 2e-5, rel


class _InjectedEnv(DroneEnv):
    """DroneEnv whose episodes start from given states and keys: a drone reset for step ``j`` (its
    new episode's first step) starts from ``fresh[d, j]`` with key ``fresh_keys[d, j]``."""

    def _reset(self, tensordict=None, **kwargs):
        mask = None if tensordict is None else tensordict.get("_reset", None)
        every = torch.ones(self.batch_size, dtype=torch.bool)
        self.rows = (every if mask is None else mask.reshape(self.batch_size)).nonzero().squeeze(-1)
        # DroneEnv's bug, not the kernel's: a disturbed env that adds nothing to the state hands out
        # the state itself as the observation (disturbances.observe), and a partial reset writes the
        # state in place: the last step's "next" observation would read the new episode's start.
        self._state = self._state.clone()
        return super()._reset(tensordict, **kwargs)

    def _start(self, state, keys, index=None):
        return super()._start(state, self.fresh_keys[self.rows, self.j], index)


def _env_segments(monkeypatch, d, head, dtype, stacked, noise, fresh, fresh_keys, max_steps) -> dict:
    """Every step of ``DroneEnv`` under TorchRL's ``step_and_maybe_reset`` (the collector's auto-reset),
    the actions sampled from the stacked net with ``noise``."""
    n, steps = noise.shape[:2]
    env = _InjectedEnv(batch_size=[n], max_steps=max_steps, max_thrust=MAX_THRUST, dtype=dtype, disturbance=d)
    env.fresh, env.fresh_keys, env.j = fresh, fresh_keys, 0
    monkeypatch.setattr(dynamics, "initial_state", lambda *args, **kwargs: env.fresh[env.rows, env.j])
    sampler = ActionSampler(head, HEADS[head])
    td, frames = env.reset(), []
    with torch.no_grad():
        for j in range(steps):
            loc, scale = stacked(td["observation"].unsqueeze(0))
            td["action"] = sampler(loc, scale, noise[:, j].unsqueeze(0))[0]
            env.j = j + 1  # drones done at step j start their next episode at step j + 1
            td, following = env.step_and_maybe_reset(td)
            frames.append(td.clone())
            td = following
    whole = torch.stack(frames, 1)
    following = whole["next"]
    return {
        "observation": whole["observation"],
        "action": whole["action"],
        "reward": following["reward"].squeeze(-1),
        "next_observation": following["observation"],
        "cause": following["termination_cause"].squeeze(-1),
        "terminated": following["terminated"].squeeze(-1),
        "truncated": following["truncated"].squeeze(-1),
        "step_count": whole["step_count"].squeeze(-1),
    }


SEGMENT_STEPS, SEGMENT_MAX_STEPS = 24, 9


def _calls(terminated: torch.Tensor, truncated: torch.Tensor) -> list[int]:
    """Call lengths whose last steps include a termination and a truncation (the first of each)."""
    ends = {int(flags.any(0).nonzero()[0]) + 1 for flags in (terminated, truncated)} | {terminated.shape[1]}
    cuts = sorted(ends)
    return [b - a for a, b in zip([0, *cuts], cuts, strict=False)]


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_segments_equal_drone_env_under_the_collector_s_auto_reset(monkeypatch, condition, head, dtype):
    """``KernelSegments`` over a few calls equals ``DroneEnv`` stepped by TorchRL's
    ``step_and_maybe_reset`` with the same start states, episode keys and action noise: every
    step's observation, action, reward, next observation, cause, terminated, truncated and step
    count, with auto-reset, and episodes ending by termination and by truncation inside a call
    and at a call's last step (the drone's state carried to the next call).

    Mutations caught: the next observation at the step's count instead of the next one (its noise
    drawn at ``t``, not ``t + 1``); a new episode keeping the last one's motor lag (the carried
    thrust not reset)."""
    d, dtype = _disturbance(condition), DTYPES[dtype]
    n, steps = 11, SEGMENT_STEPS  # not a multiple of the 8 (4) lanes
    stacked = _stacked(1, head, d, dtype, mean=0.25 if head == "normal" else -0.55)
    generator = torch.Generator().manual_seed(3)
    noise = torch.randn(n, steps, 2, generator=generator, dtype=dtype)
    noise[: n // 2] += 2.0  # these drones climb (and are truncated),
    noise[n // 2 :] -= 1.0  # these sink through the floor
    fresh = dynamics.initial_state((n, steps + 1), "floor", generator, dtype=dtype)
    fresh_keys = disturbances.episode_keys(generator, (n, steps + 1))
    expected = _env_segments(
        monkeypatch, d, head, dtype, stacked, noise, fresh, fresh_keys, SEGMENT_MAX_STEPS
    )
    rollout = KernelRollout(
        stacked, dynamics.DroneParams(max_thrust=MAX_THRUST), HEADS[head], SEGMENT_MAX_STEPS, disturbance=d
    )
    calls = _calls(expected["terminated"], expected["truncated"])
    segments, pieces, j = KernelSegments(rollout, n), [], 0
    for k in calls:
        pieces.append(segments(noise[:, j : j + k], fresh[:, j : j + k], fresh_keys[:, j : j + k]))
        j += k
    got = {name: torch.cat([getattr(p, name) for p in pieces], 1) for name in expected}
    for name in ("observation", "action", "reward", "next_observation"):
        _close(got[name], expected[name], name)
    for name in ("cause", "terminated", "truncated", "step_count"):
        assert torch.equal(got[name], expected[name]), name
    # The cases this test is for: both endings, inside calls and at a call's last step.
    last = torch.tensor(calls).cumsum(0) - 1
    inside = torch.ones(steps, dtype=torch.bool)
    inside[last] = False
    for ending in ("terminated", "truncated"):
        flags = got[ending]
        assert flags[:, inside].any() and flags[:, last].any(), ending
    assert bool((segments.carried.t[got["terminated"][:, -1] | got["truncated"][:, -1]] == -1).all())


def test_the_single_source_functions_compile_for_scalar_lanes():
    """The DK_HD functions compile with V = float and V = double and no vector type in sight (what a
    CUDA kernel, one thread per drone, calls).

    Mutation caught: a lane read in a single-source function (``dr.s[k][0]`` in ``observe``)."""
    assert build.scalar_check() is None


BAD = {"wind": 0.1}  # a disturbed drone (its keys are needed)


@pytest.mark.parametrize(
    ("obs_dim", "disturbance", "keys", "message"),
    [
        (
            8,
            BAD,
            True,
            r"^params of 484 values do not fit the policy of 6 inputs and hidden sizes \[16, 16\]",
        ),
        (6, BAD, False, r"^ops.rollout under disturbances needs episode keys or rng keys$"),
        (6, "short", True, r"^disturbance of shape \[9\]; expected \[10\] \(ops.disturbance_constants\)$"),
        (6, "long delay", True, r"^action_delay and observed_actions \(26, 0\) are not allowed; expected"),
    ],
)
def test_the_ops_refuse_what_they_cannot_fly_in_one_line(obs_dim, disturbance, keys, message):
    constants = ops.disturbance_constants(BAD)
    if disturbance == "short":
        constants = constants[:-1]
    elif disturbance == "long delay":
        constants[ops.DISTURBANCE_CONSTANTS.index("action_delay")] = disturbances.MAX_STEPS_BACK + 1
    stacked = StackedThreeNet([ThreeNetPolicy((16, 16), "tanh", obs_dim=obs_dim)], "tanh")
    with pytest.raises(ValueError, match=message):
        ops.rollout(
            stacked.flat.detach(), torch.zeros(1, 1, 6), None, None, torch.ones(1, dtype=torch.bool),
            ops.env_constants(dynamics.DroneParams(), None), torch.ones(1), [16, 16], 0, 1e-6, 10,
            disturbance=constants, keys=torch.zeros(1, 1, dtype=torch.int64) if keys else None,
        )  # fmt: skip


def test_the_kernels_read_every_disturbance_constant_python_packs():
    read = tuple(library().dk_disturbance_constants().decode().split(",")[:-1])
    assert read == ops.DISTURBANCE_CONSTANTS == disturbances.FIELDS
    packed = ops.disturbance_constants({"wind": 0.2, "action_delay": 3, "observed_actions": 2})
    assert dict(zip(ops.DISTURBANCE_CONSTANTS, packed.tolist(), strict=True))["action_delay"] == 3.0
    assert ops.steps_back(packed) == (3, 2)
