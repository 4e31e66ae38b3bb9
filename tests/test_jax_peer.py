"""The JAX benchmark peer (``benchmarks/peers/jax_reinforce.py``) against the project.

The peer shares no code with the project, so these tests are what makes its timings a fair
comparison: the same physics, the same loss and gradient, the same optimizer. Skipped without jax.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytestmark = pytest.mark.slow  # collected only with -m slow (tests/conftest.py)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

# Imported here, not in the tests, so that their one-off import time (torchrl's) is not a test's.
from drone_torchrl.envs import dynamics  # noqa: E402
from drone_torchrl.modules.policy import ThreeNetPolicy, actor_from_net  # noqa: E402
from drone_torchrl.objectives.reinforce import ReinforceLoss  # noqa: E402

PEER_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "peers" / "jax_reinforce.py"


@pytest.fixture(scope="module")
def peer():
    """The peer script as a module (it sets its one-thread XLA flags when first imported)."""
    if "jax_reinforce_peer" not in sys.modules:
        spec = importlib.util.spec_from_file_location("jax_reinforce_peer", PEER_PATH)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
    return sys.modules["jax_reinforce_peer"]


def _edge_cases() -> tuple[np.ndarray, np.ndarray]:
    """States whose next state lies exactly on (or one float from) a domain or zone bound.

    With both motors at 0.5 the thrust equals the weight: a level drone at rest stays where it is
    (x, z and alpha unchanged, bit for bit), and a tilted one keeps its angle.
    """
    f32 = np.float32

    def around(v: float) -> list[np.float32]:
        v = f32(v)
        return [np.nextafter(v, f32(-np.inf)), v, np.nextafter(v, f32(np.inf))]

    states = []
    for x in [*around(2.0), *around(-2.0), *around(0.8), *around(-0.8)]:
        states.append([x, 0, 1.0, 0, 0, 0])
    for z in [*around(4.0), *around(-0.05), *around(2.2), *around(3.2)]:
        states.append([0, 0, z, 0, 0, 0])
    for alpha in [*around(math.pi / 3), *around(-math.pi / 3)]:
        states.append([0, 0, 1.0, 0, alpha, 0])
        states.append([0.5, 0, 2.5, 0, alpha, 0])  # in the zone but for the tilt bound
    states.append([2.5, 0, -1.0, 0, 1.5, 0])  # every cause at once: out of x (1) wins
    states.append([0, 0, 4.5, 0, 1.5, 0])  # ceiling (3) and tilt (4): ceiling wins
    states.append([0, 0, -1.0, 0, 1.5, 0])  # floor (2) and tilt: floor wins
    states = np.asarray(states, np.float32)
    return states, np.full((len(states), 2), 0.5, np.float32)


def test_one_step_dynamics_equals_the_project(peer):
    rng = np.random.default_rng(0)
    n = 1000
    low = np.array([-2.4, -3, -0.4, -3, -1.4, -4], np.float32)
    high = np.array([2.4, 3, 4.4, 3, 1.4, 4], np.float32)
    states = rng.uniform(low, high, (n, 6)).astype(np.float32)
    actions = rng.uniform(-1.0, 2.0, (n, 2)).astype(np.float32)
    edge_states, edge_actions = _edge_cases()
    states = np.concatenate([states, edge_states])
    actions = np.concatenate([actions, edge_actions])

    next_jax, reward_jax, cause_jax = jax.jit(peer.step)(jnp.asarray(states), jnp.asarray(actions))
    next_torch, reward_torch, cause_torch = dynamics.step(
        torch.from_numpy(states), torch.from_numpy(actions), dynamics.DroneParams()
    )
    np.testing.assert_allclose(np.asarray(next_jax), next_torch.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(reward_jax), reward_torch.numpy())
    np.testing.assert_array_equal(np.asarray(cause_jax), cause_torch.numpy())
    # Every cause, the zone and plain flight occur (the random states alone cover them all).
    causes = cause_torch[:n].numpy()
    assert all((causes == c).sum() >= 20 for c in range(5)), np.bincount(causes)
    rewards = reward_torch[:n].numpy()
    assert {0.0, 1.0, 10.0} <= set(rewards.tolist())
    # The edge cases hit the bounds as intended: some terminate, some stay in, some in the zone.
    edge_causes = cause_torch[n:].numpy()
    assert set(edge_causes.tolist()) == {0, 1, 2, 3, 4}
    assert 10.0 in reward_torch[n:].numpy().tolist()


@pytest.fixture(scope="module")
def episode_batch(peer):
    """Three agents' episodes flown by the peer from fixed weights: a freshly initialised agent (a
    short episode), and two whose nets are a tilt controller (a PD law on alpha through the first
    unit of each layer, on top of their random weights scaled down 1000x) climbing through the
    zone with little noise: one to the ceiling, one for all 300 steps."""
    params, _, train_keys = peer.init_agents(jnp.asarray([0, 1, 2], jnp.uint32))
    params = np.array(params)
    for agent, thrust in ((1, 0.53), (2, 0.51)):
        layers = {k: np.array(v) * 1e-3 for k, v in peer.unflatten(jnp.asarray(params[agent])).items()}
        # h = 0.1 (alpha + 0.45 alpha_dot); left motor 0.5x + h, right 0.5x - h: alpha'' = -98 h.
        layers["w1"][peer.ALPHA, 0] += 0.1
        layers["w1"][peer.ALPHA_DOT, 0] += 0.045
        layers["w2"][0, 0] += 1.0
        layers["wh"][0, :2] += [1.0, -1.0]
        layers["bh"][:2] = thrust
        layers["bh"][2:] = math.log(math.expm1(0.005 - peer.MIN_STD))  # std 0.005
        params[agent] = np.asarray(peer.flatten(layers))
    params = jnp.asarray(params)
    start, noise = jax.jit(jax.vmap(lambda k: peer.draws(k, 0)))(train_keys)
    episodes = jax.jit(peer.rollout_while)(params, start, noise)
    return params, start, noise, tuple(np.array(x) for x in episodes)


def test_loss_and_gradient_equal_the_project(peer, episode_batch):
    params, start, _, (obs, action, reward, valid) = episode_batch
    lengths = valid.sum(-1)
    assert lengths[0] < 50 and 100 < lengths[1] < 300 and lengths[2] == 300, lengths  # ended, truncated
    assert (reward[1:] == 10.0).sum(-1).min() >= 10  # both climbers crossed the zone
    for agent, length in enumerate(lengths):  # valid steps come first, then only padding
        assert valid[agent, :length].all() and not valid[agent, length:].any()
    np.testing.assert_array_equal(obs[:, 0], np.asarray(start))

    # The stored transitions are the project's physics, with the same rewards and ends.
    for agent, length in enumerate(lengths):
        nxt, rew, cause = dynamics.step(
            torch.from_numpy(obs[agent, :length]),
            torch.from_numpy(action[agent, :length]),
            dynamics.DroneParams(),
        )
        np.testing.assert_allclose(nxt[:-1].numpy(), obs[agent, 1:length], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(rew.numpy(), reward[agent, :length])
        ended = (cause != 0).numpy()
        assert not ended[:-1].any() and (ended[-1] or length == 300)

    gammas = np.array([0.99, 0.9, 0.999], np.float32)
    tables = jax.vmap(peer.discount_tables)(jnp.asarray(gammas))
    batch = tuple(jnp.asarray(x) for x in (obs, action, reward, valid))
    grads = np.asarray(jax.jit(peer.loss_grads)(params, *batch, tables))
    chunked = np.asarray(jax.jit(partial(peer.loss_grads, chunk=50))(params, *batch, tables))
    np.testing.assert_allclose(chunked, grads, rtol=1e-4, atol=1e-6 * np.abs(grads).max())
    losses = np.asarray(jax.jit(jax.vmap(peer.episode_loss))(params, *batch, jnp.asarray(gammas)))

    steps = torch.arange(300)
    for agent, length in enumerate(lengths):
        net = ThreeNetPolicy()
        state = peer.torch_state_dict(params[agent])
        np.testing.assert_array_equal(peer.from_torch_state_dict(state), np.asarray(params[agent]))
        net.load_state_dict({k: torch.from_numpy(v) for k, v in state.items()})
        actor = actor_from_net(net, "normal", None)
        done = (steps >= int(length) - 1).unsqueeze(-1)  # the end, then repeats (as TorchRL pads)
        td = TensorDict(
            {
                "observation": torch.from_numpy(obs[agent]),
                "action": torch.from_numpy(action[agent]),
                "step_count": steps.unsqueeze(-1),
                "next": {"reward": torch.from_numpy(reward[agent]).unsqueeze(-1), "done": done},
            },
            batch_size=[300],
        )
        loss = ReinforceLoss(actor, gamma=float(gammas[agent]))(td)["loss_reinforce"]
        loss.backward()
        assert losses[agent] == pytest.approx(loss.item(), rel=1e-5)
        peer_grads = peer.torch_state_dict(grads[agent])
        for name, p in net.named_parameters():
            error = np.linalg.norm(peer_grads[name] - p.grad.numpy()) / np.linalg.norm(p.grad.numpy())
            assert error < 1e-5, (agent, name, error)


def test_adam_equals_torch(peer):
    rng = np.random.default_rng(1)
    start = rng.normal(scale=1e-3, size=peer.N_PARAMS).astype(np.float32)  # small: the steps show
    grads = [rng.normal(scale=s, size=peer.N_PARAMS).astype(np.float32) for s in (1.0, 1e-3, 30.0, 0.1)]
    lr = 5e-4

    weight = torch.nn.Parameter(torch.from_numpy(start.copy()))
    optimizer = torch.optim.Adam([weight], lr=lr)
    params, opt = jnp.asarray(start), peer.adam_init(jnp.asarray(start))
    adam = jax.jit(peer.adam_update)
    for g in grads:
        weight.grad = torch.from_numpy(g)
        optimizer.step()
        params, opt = adam(params, jnp.asarray(g), opt, jnp.float32(lr))
        moved = weight.detach().numpy() - start
        np.testing.assert_allclose(np.asarray(params) - start, moved, rtol=1e-5, atol=1e-10)


def test_initial_weights_like_torch_linear(peer):
    params, opt, _ = peer.init_agents(jnp.arange(4, dtype=jnp.uint32))
    assert params.shape == (4, peer.N_PARAMS) and float(jnp.abs(opt["m"]).max()) == 0.0
    assert not np.array_equal(np.asarray(params[0]), np.asarray(params[1]))
    for name, value in jax.jit(jax.vmap(peer.unflatten))(params).items():
        bound = 1 / math.sqrt(peer.FAN_IN[name])
        value = np.asarray(value)
        assert np.abs(value).max() <= bound and np.abs(value).max() > 0.5 * bound, name
    # The same seed gives the same weights.
    again, _, _ = peer.init_agents(jnp.asarray([3, 0, 1, 2], jnp.uint32))
    np.testing.assert_array_equal(np.asarray(again[1:]), np.asarray(params[:3]))


def test_rollouts_while_and_scan_fly_the_same_episodes(peer, episode_batch):
    params, start, noise, (obs, action, reward, valid) = episode_batch
    scanned = [np.asarray(x) for x in jax.jit(peer.rollout_scan)(params, start, noise)]
    np.testing.assert_array_equal(scanned[3], valid)
    np.testing.assert_array_equal(scanned[2], reward)
    np.testing.assert_allclose(scanned[0][valid], obs[valid], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(scanned[1][valid], action[valid], rtol=1e-6, atol=1e-7)


def test_short_training_run(peer):
    result = peer.train([1e-3, 1e-4], [0.99, 0.9], [0, 1], episodes=50, scan=25)
    returns, lengths = result["returns"], result["lengths"]
    assert returns.shape == lengths.shape == (50, 2)
    assert np.isfinite(returns).all() and np.isfinite(result["params"]).all()
    assert (lengths >= 1).all() and (lengths <= 300).all()
    assert (returns >= lengths - 1).all() and (returns <= 10 * lengths).all()
    final = peer.final_metric(returns, window=10)
    assert final.shape == (2,) and np.isfinite(final).all()
