"""drone-export format=onnx: the ONNX model against the actor (both heads, bounded and unbounded thrust),
its interface (the .pt2's), the check that refuses a wrong file, the missing extra, the latency.

The checkpoints here hold fresh policies (no training) whose mean head is drawn wide, so the
commands reach past both clamps and the TanhNormal's squashing saturates."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from drone_torchrl import export
from drone_torchrl.config import ConfigError, config_dir, run_config
from drone_torchrl.io.checkpoint import FORMAT_VERSION, REQUIRED_KEYS, load_checkpoint, save_checkpoint
from drone_torchrl.modules.factory import build_actor, build_policy

# (overrides, distribution, max_thrust): both heads, bounded and unbounded thrust, the three activations.
HEADS = [
    ([], "normal", None),  # the paper
    (["env.max_thrust=1.0", "model.activation=relu"], "normal", 1.0),
    (["experiment=bounded"], "tanh_normal", 1.0),
    (["experiment=bounded", "env.max_thrust=1.5", "model.activation=elu"], "tanh_normal", 1.5),
]


def _checkpoint(path: Path, *overrides: str, seed: int = 0) -> Path:
    """A checkpoint of a fresh policy with a wide mean head (commands well outside [0, max_thrust])."""
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    net = build_policy(cfg, seed=seed)
    with torch.no_grad():
        net.mean.weight.normal_(0.0, 1.0)
        net.mean.bias.normal_(0.5, 0.5)
    state = dict.fromkeys(REQUIRED_KEYS)
    state.update(
        format_version=FORMAT_VERSION,
        backend="fast",
        actor=build_actor(cfg, net).state_dict(),
        optimizer={},
        episodes_done=0,
        updates_done=0,
        rng={"torch": None, "env": None, "agent": None},
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    save_checkpoint(state, path)
    return path


def _actor_commands(checkpoint: Path, observations: torch.Tensor) -> torch.Tensor:
    """The reference, built here as drone-eval flies it: the actor's deterministic action, clamped."""
    state = load_checkpoint(checkpoint)
    cfg = run_config(state["config"])
    actor = build_actor(cfg)
    actor.load_state_dict(state["actor"])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = actor(TensorDict({"observation": observations}, batch_size=observations.shape[:1]))["action"]
    return action if cfg.env.max_thrust is None else action.clamp(0.0, cfg.env.max_thrust)


@pytest.fixture
def onnxruntime():
    pytest.importorskip("onnx")
    pytest.importorskip("onnxscript")
    return pytest.importorskip("onnxruntime")


@pytest.mark.parametrize(
    ("overrides", "distribution", "max_thrust"), HEADS, ids=[h[1] + str(h[2]) for h in HEADS]
)
def test_onnx_matches_the_actor_and_the_pt2(tmp_path, onnxruntime, overrides, distribution, max_thrust):
    checkpoint = _checkpoint(tmp_path / "last.pt", *overrides)
    exported = export.export_policy(checkpoint, tmp_path / "policy.onnx")
    assert exported.format == "onnx" and exported.path == tmp_path / "policy.onnx"
    assert exported.max_abs_diff <= export.TOLERANCE and exported.checked == len(export.check_observations())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt", "policy.onnx"]  # one file, no .tmp
    pt2 = export.export_policy(checkpoint, tmp_path / "policy.pt2").path

    generator = torch.Generator().manual_seed(1)
    random = torch.randn(257, 6, generator=generator) * torch.tensor([1.0, 2.0, 1.0, 2.0, 0.3, 1.0])
    random[:, 2] += 2.0
    edges = torch.tensor(
        [
            [0.0] * 6,
            [2.0, 0.0, 4.0, 0.0, 1.05, 0.0],  # the domain's corner, tilted to the limit
            [-2.0, -5.0, 0.0, -5.0, -1.05, -10.0],
            [1e4] * 6,  # every tanh saturated
            [-1e4] * 6,
            [0.0, 0.0, 1e6, 0.0, 0.0, 0.0],
            [1e30, -1e30, 0.0, 0.0, 0.0, 0.0],
        ]
    )
    session = onnxruntime.InferenceSession(str(exported.path), providers=["CPUExecutionProvider"])
    program = torch.export.load(pt2).module()
    for observations in (random, edges, random[:1]):
        expected = _actor_commands(checkpoint, observations)
        thrust = session.run(None, {"observation": observations.numpy()})[0]
        assert thrust.shape == (len(observations), 2) and thrust.dtype == np.float32
        np.testing.assert_allclose(thrust, expected.numpy(), rtol=0, atol=export.TOLERANCE)
        np.testing.assert_allclose(
            thrust, program(observations).detach().numpy(), rtol=0, atol=export.TOLERANCE
        )
        if max_thrust is not None:
            assert thrust.min() >= 0.0 and thrust.max() <= max_thrust
    # The wide head reaches past the clamps (or saturates the squashing) on the random states.
    reference = _actor_commands(checkpoint, random)
    if max_thrust is None:
        assert reference.min() < 0.0 and reference.max() > 1.0
    elif distribution == "normal":
        assert (reference == 0.0).any() and (reference == max_thrust).any()
    else:
        assert reference.min() < 0.01 * max_thrust and reference.max() > 0.99 * max_thrust

    # The .pt2's interface: one float32 input [batch, 6], one float32 output [batch, 2].
    (given,), (returned,) = session.get_inputs(), session.get_outputs()
    assert (given.name, given.type, given.shape[1]) == ("observation", "tensor(float)", 6)
    assert (returned.name, returned.type, returned.shape[1]) == ("thrust", "tensor(float)", 2)
    assert isinstance(given.shape[0], str) and given.shape[0] == returned.shape[0]  # the dynamic batch
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["distribution"] == distribution and meta["max_thrust"] == (
        "none" if max_thrust is None else repr(max_thrust)
    )


def test_the_onnx_file_runs_with_onnxruntime_alone(tmp_path, onnxruntime):
    """The ONNX snippet of docs/training.md (Export) in a fresh interpreter: neither torch nor drone_torchrl is imported."""
    checkpoint = _checkpoint(tmp_path / "last.pt", "experiment=bounded")
    out = export.export_policy(checkpoint, tmp_path / "policy.onnx").path
    observations = export.check_observations()
    np.save(tmp_path / "obs.npy", observations.numpy())
    script = (
        "import sys, numpy as np, onnxruntime\n"
        f"session = onnxruntime.InferenceSession({str(out)!r})\n"
        f"observation = np.load({str(tmp_path / 'obs.npy')!r})\n"
        "thrust = session.run(None, {'observation': observation})[0]\n"
        f"np.save({str(tmp_path / 'act.npy')!r}, thrust)\n"
        "assert 'torch' not in sys.modules and 'drone_torchrl' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    expected = _actor_commands(checkpoint, observations).numpy()
    np.testing.assert_allclose(np.load(tmp_path / "act.npy"), expected, rtol=0, atol=export.TOLERANCE)


@pytest.mark.parametrize("format", ["pt2", "onnx"])
def test_a_file_that_differs_from_the_actor_is_refused_and_not_written(tmp_path, monkeypatch, format):
    if format == "onnx":
        for module in export.ONNX_MODULES:
            pytest.importorskip(module)
    checkpoint = _checkpoint(tmp_path / "last.pt", "experiment=bounded")
    forward = export.DeterministicPolicy.forward
    monkeypatch.setattr(export.DeterministicPolicy, "forward", lambda self, obs: forward(self, obs) * 0.99)
    with pytest.raises(export.ExportError) as info:
        export.export_policy(checkpoint, tmp_path / f"policy.{format}")
    message = str(info.value)
    assert "\n" not in message and f"the {format} program differs from the actor" in message, message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt"]


def test_format_onnx_without_the_extra_says_which_in_one_line_before_any_work(tmp_path, monkeypatch):
    # onnxruntime missing, onnx and onnxscript there (whether or not this machine has the extra).
    found = importlib.util.find_spec
    present = {"onnx", "onnxscript"}
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == "onnxruntime" else object() if name in present else found(name, *a),
    )
    monkeypatch.chdir(tmp_path)
    for overrides in (["format=onnx"], ["output=policy.onnx"]):
        # The checkpoint is not even there: the extra is refused before it is opened.
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose("export", overrides=[f"checkpoint={tmp_path / 'nothing'}", *overrides])
        with pytest.raises(ConfigError) as info:
            export.run_export(cfg)
        message = str(info.value)
        assert "\n" not in message and message.endswith("pip install 'drone_torchrl[onnx]'"), message
        assert "onnxruntime" in message and "onnxscript" not in message
    assert list(tmp_path.iterdir()) == []
    export.resolve_output("pt2", None)  # .pt2 needs nothing of it


@pytest.mark.parametrize(
    ("format", "output", "expected"),
    [
        (None, None, ("pt2", None)),  # no output: the run folder's (default_output)
        ("onnx", None, ("onnx", None)),
        ("pt2", None, ("pt2", None)),
        (None, "out/best.onnx", ("onnx", "out/best.onnx")),
        (None, "best.ONNX", ("onnx", "best.ONNX")),
        ("onnx", "best.onnx", ("onnx", "best.onnx")),
        (None, "best.pt2", ("pt2", "best.pt2")),
    ],
)
def test_the_format_is_the_output_s_suffix(format, output, expected):
    fmt, path = export.resolve_output(format, output)
    assert (fmt, path) == (expected[0], None if expected[1] is None else Path(expected[1]))


def test_latency_is_measured_for_each_runtime(tmp_path, onnxruntime):
    checkpoint = _checkpoint(tmp_path / "last.pt")
    policy = export.export_policy(checkpoint, tmp_path / "p.onnx").policy
    export.export_policy(checkpoint, tmp_path / "p.pt2")
    threads = torch.get_num_threads()
    passes = export.forward_passes(policy, {"onnx": tmp_path / "p.onnx", "pt2": tmp_path / "p.pt2"})
    times = export.latencies(passes, repeats=3, calls=5, warmup=1)
    assert list(times) == ["onnxruntime", "torch.export", "eager torch"]
    assert all(0 < us < 1e6 for us in times.values()), times
    assert torch.get_num_threads() == threads  # one thread while timing, restored after


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_drone_export_onnx_prints_the_check_and_the_latency(tmp_path, onnxruntime):
    checkpoint = _checkpoint(tmp_path / "last.pt", "experiment=bounded")
    proc = subprocess.run(
        [sys.executable, "-m", "drone_torchrl.apps.export", f"checkpoint={checkpoint}", "format=onnx"],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=tmp_path,
        env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
    )
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lines = proc.stdout.splitlines()
    # No output=: beside the checkpoint (a file outside a run's checkpoints/ folder), in export/.
    assert (
        lines[0] == f"wrote {tmp_path / 'export' / 'last.onnx'}"
        and (tmp_path / "export" / "last.onnx").is_file()
    )
    assert lines[1].startswith("checked: largest difference from the actor ")
    assert "onnxruntime" in lines[2] and " us" in lines[2] and "eager torch" in lines[2]
