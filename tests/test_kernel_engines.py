"""The fast engine's other targets: the scalar engine (CPU) and the CUDA engine, equal to the reference.

``drone_kernels.cpp`` is one source for three builds. The vector engine (the CPU default) flies
8 (float32) or 4 (float64) drones per SIMD register; the CUDA engine runs the same loops
(``fly_block``: episodes and segments; ``reinforce_agent``) with one drone per thread; the scalar engine
is that one-drone-per-block code compiled for the CPU. The scalar engine here passes the equality
tests of ``test_kernel_disturbances.py`` (the reference: ``disturbances``, ``StackedThreeNet``,
``ReinforceLoss`` with autograd, ``DroneEnv`` under TorchRL's auto-reset), so the code each CUDA
thread runs is tested on a machine without a GPU. The tests marked ``gpu`` run the CUDA engine
itself against the vector engine (and so the reference) and skip without a CUDA device.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import time
from pathlib import Path

import pytest
import test_kernel_disturbances as equality
import torch

from drone_torchrl.envs import disturbances, dynamics
from drone_torchrl.kernels import build, ops

pytestmark = pytest.mark.skipif(
    build.library(scalar=True) is None, reason=f"C++ kernels unavailable: {build.unavailable_reason()}"
)

# The presets and the keys whose per-drone state the engines carry (gusts, lag, delay, commands).
CONDITIONS = ["none", "mild", "strong", "gust", "motor_lag", "action_delay", "observed_actions"]
CASES = [
    pytest.param(c, h, d, id=f"{c}-{h}-{d}")
    for c in CONDITIONS
    for h in equality.HEADS
    for d in equality.DTYPES
    if c in ("none", "strong") or (h == "normal" and d == "float32")
]


@pytest.fixture
def scalar_engine(monkeypatch) -> list[torch.dtype]:
    """Every op call goes to the scalar engine; the list records the dtypes it was called for."""
    calls: list[torch.dtype] = []

    def scalar(dtype: torch.dtype = torch.float32, device: torch.device | None = None):
        calls.append(dtype)
        return build.library(double=dtype == torch.float64, scalar=True)

    monkeypatch.setattr(ops, "_lib", scalar)
    return calls


def test_the_scalar_engine_is_the_one_drone_per_block_build():
    """The saved steps of one 9-step episode: 9 one-drone blocks in the scalar engine, 2 (float32,
    8 lanes) or 3 (float64, 4 lanes) blocks in the vector engine, each block ``lanes`` x the width
    (the inputs, 64 hidden outputs, loc, the std head's pre-activation, the action, the return)."""
    sizes = ops._words(*ops._net(6, [32, 32], 1, 0.0, 0.0), 9, 1, 1, 9)  # rows, agents, episodes, steps
    width = 6 + 64 + 3 * dynamics.ACTION_DIM + 1
    for double, blocks, lanes in ((False, 2, 8), (True, 3, 4)):
        assert build.library(double, scalar=True).dk_saved_size(sizes) == 9 * width
        assert build.library(double).dk_saved_size(sizes) == blocks * lanes * width


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_the_scalar_engine_flies_the_reference_s_steps(scalar_engine, condition, head, dtype):
    """``test_every_disturbed_step_equals_the_reference`` on the scalar engine.

    Mutation caught: one agent's weights read from the first agent's row (``params + agent[0] *
    net.params`` -> ``params`` in ``fly_block``)."""
    equality.test_every_disturbed_step_equals_the_reference(condition, head, dtype)
    assert equality.DTYPES[dtype] in scalar_engine


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_the_scalar_engine_s_update_equals_reinforce_loss(scalar_engine, condition, head, dtype):
    """``test_disturbed_update_equals_reinforce_loss`` on the scalar engine.

    Mutation caught: the gradient's steps masked by lane instead of by step (``r % T`` ->
    ``l % T`` in ``reinforce_agent``'s ``valid``), invisible with 8 lanes of 300-step episodes."""
    equality.test_disturbed_update_equals_reinforce_loss(condition, head, dtype)
    assert equality.DTYPES[dtype] in scalar_engine


@pytest.mark.parametrize(("condition", "head", "dtype"), CASES)
def test_the_scalar_engine_s_segments_equal_drone_env(scalar_engine, monkeypatch, condition, head, dtype):
    """``test_segments_equal_drone_env_under_the_collector_s_auto_reset`` on the scalar engine.

    Mutation caught: a restarted drone keeping the previous episode's gust (the
    ``start_episode(d, dr, restart)`` of ``fly_block``'s restart left out)."""
    equality.test_segments_equal_drone_env_under_the_collector_s_auto_reset(
        monkeypatch, condition, head, dtype
    )
    assert equality.DTYPES[dtype] in scalar_engine


@pytest.mark.slow
def test_the_cuda_engine_compiles(tmp_path):
    """``nvcc`` builds the CUDA engine (no GPU needed) and the library exports its entry points."""
    if build.nvcc() is None:
        pytest.skip("no nvcc on this machine (CI has one)")
    target = tmp_path / "drone_kernels_cuda.so"
    assert build.build_cuda(target) is None
    exports = target.read_bytes()
    for name in (b"dk_rollout", b"dk_reinforce", b"dk_cuda_scratch_size", b"dk_saved_size"):
        assert name in exports, name


# --------------------------------------------------------------------------------- on a GPU only


def _constants(condition: str, device: str):
    d = equality._disturbance(condition)
    params = dynamics.DroneParams(max_thrust=equality.MAX_THRUST)
    return d, ops.env_constants(params, None, device=device), ops.disturbance_constants(d, device=device)


@pytest.mark.gpu
@pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device (pytest -m gpu on a GPU machine)"
)
@pytest.mark.parametrize("condition", CONDITIONS)
@pytest.mark.parametrize("dtype", list(equality.DTYPES))
def test_cuda_rollout_and_update_equal_the_cpu_engine(condition, dtype):
    """On a GPU: ``rollout`` (given start states, noise and keys) and ``reinforce`` (draws from the
    agents' keys) of the CUDA engine equal the CPU engine's, which equals the reference (above and
    test_kernel_disturbances.py): lengths and causes exactly, the rest to float rounding."""
    dtype = equality.DTYPES[dtype]
    d, env, dist = _constants(condition, "cpu")
    n, e, steps, hidden = 64, 2, 300, [32, 32]
    generator = torch.Generator().manual_seed(0)
    params = (
        torch.randn(n, ops.param_count(d.observation_dim, hidden), generator=generator, dtype=dtype) * 0.2
    )
    start = dynamics.initial_state((n, e), "floor", generator, dtype=dtype)
    noise = torch.randn(n, e, steps, 2, generator=generator, dtype=dtype)
    keys = disturbances.episode_keys(generator, (n, e))
    active, gamma = torch.ones(n, dtype=torch.bool), torch.full((n,), 0.99)
    rng = torch.stack([torch.arange(n), torch.full((n,), 3)], -1).unsqueeze(1).expand(-1, e, -1)

    def both(function, *args, **kwargs):
        cuda = [a.cuda() if isinstance(a, torch.Tensor) else a for a in args]
        cuda_kwargs = {k: v.cuda() if isinstance(v, torch.Tensor) else v for k, v in kwargs.items()}
        return function(*args, **kwargs), [t.cpu() for t in function(*cuda, **cuda_kwargs)]

    net = (hidden, 0, 1e-6, steps)
    cpu, gpu_out = both(ops.rollout, params, start, noise, None, active, env, gamma, *net, 0.0, dist, keys)
    for name, a, b in zip(
        ("states", "action", "reward", "cause", "length", "returns", "stats", "seen"),
        cpu,
        gpu_out,
        strict=True,
    ):
        if a.dtype in (torch.int64, torch.bool):
            assert torch.equal(a, b), name
        else:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4, msg=name)
    flags = [1, 1, 0, 0]
    cpu, gpu_out = both(ops.reinforce, params, rng, active, env, gamma, flags, *net, 0.0, dist)
    assert torch.equal(cpu[4], gpu_out[4])  # lengths
    rel = (cpu[0].double() - gpu_out[0].double()).norm(dim=1) / cpu[0].double().norm(dim=1)
    assert float(rel.max()) < 1e-3, rel


@pytest.mark.slow
def test_the_gpu_check_runs_on_the_cpu_in_a_minute():
    """``benchmarks/gpu_check.sh --device cpu --quick`` (what a GPU machine runs, on the CPU): every
    row is printed with a figure (the engine, 32 and 256 agents for the project and the JAX peer,
    their ratios, drone-train), in at most 60 s."""
    root = Path(__file__).resolve().parents[1]
    start = time.perf_counter()
    out = subprocess.run(
        ["bash", str(root / "benchmarks" / "gpu_check.sh"), "--device", "cpu", "--quick"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    took = time.perf_counter() - start
    assert out.returncode == 0, out.stderr[-2000:]
    rows = {
        line.split(" | ")[0].lstrip("| "): line for line in out.stdout.splitlines() if line.startswith("| ")
    }
    for n in (32, 256):
        assert re.search(r"\| [0-9.]+ s/update \|", rows[f"project, {n} agents"]), rows
        if importlib.util.find_spec("jax") is not None:
            assert re.search(r"\| [0-9.]+x \|", rows[f"ratio project / JAX, {n} agents"]), rows
    assert "exit 0" in rows["drone-train device=cpu algo.episodes=100"]
    assert took <= 60, took


def test_on_a_gpu_the_fast_engine_refuses_what_it_does_not_train():
    """``device=cuda`` with PPO (its segments run on the CPU engine only) is refused in one line
    naming the keys; another device type is refused too. Neither builds anything first."""
    from drone_torchrl.kernels.coverage import fast_refusal

    nominal = disturbances.make(None)
    ppo = fast_refusal("cuda:0", [32, 32], "tanh", "float32", nominal, "ppo")
    assert ppo == "device='cuda:0' with algo.name='ppo' (on a GPU the fast engine trains REINFORCE only)"
    assert fast_refusal("mps", [32, 32], "tanh", "float32", nominal).startswith("device='mps' (")
