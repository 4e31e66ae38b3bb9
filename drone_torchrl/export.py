"""A trained policy as a standalone file: a ``torch.export`` program or an ONNX model.

The file holds its deterministic action: a ``.pt2`` runs with plain torch, an ``.onnx`` with
onnxruntime or any ONNX runtime.

Both map an observation batch ``[B, 6]`` in the env's state layout
(``x, x_dot, z, z_dot, alpha, alpha_dot``) and dtype (float32; float64 for a run with
``env.dtype=float64``, whose weights are float64) to the motor commands ``[B, 2]`` (left, right) as
fractions of the weight, exactly what the env applies: the Normal head's mean, or the TanhNormal
head's deterministic action (``ExplorationType.DETERMINISTIC``: the squashed mean), clamped to
``[0, max_thrust]`` when thrust is bounded. The batch dimension is dynamic::

    policy = torch.export.load("policy.pt2").module()
    thrust = policy(observation)                                   # torch float32 [B, 6]

    session = onnxruntime.InferenceSession("policy.onnx")
    thrust = session.run(None, {"observation": observation})[0]    # numpy float32 [B, 6]

The ONNX model is converted from the same ``torch.export`` program the ``.pt2`` holds, by torch's
own exporter in its supported mode (``torch.onnx.export(..., dynamo=True)``, torch's default since
2.9; it needs onnxscript). The TorchScript-based exporter (``dynamo=False``) is deprecated and warns
on every use. onnx, onnxruntime and onnxscript are the ``onnx`` extra, never needed for ``.pt2``.

Every file is made and checked in memory before it is written: run by its own runtime
(``torch.export.load``, onnxruntime), it must reproduce the checkpoint's TorchRL actor (its
deterministic action, clamped as the env clamps it) on :func:`check_observations` within
:data:`TOLERANCE`; otherwise :class:`ExportError` and nothing is written. Then it is written at
once, through a temporary file and a rename: a full or read-only disk is a one-line
:class:`~drone_torchrl.io.storage.StorageError`, and nothing partial is left.
"""

from __future__ import annotations

import contextlib
import functools
import io
import itertools
import logging
import os
import statistics
import timeit
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor

from drone_torchrl.config import ConfigError, check_keys, check_networks, check_values, run_config
from drone_torchrl.envs import disturbances
from drone_torchrl.envs.dynamics import ACTION_DIM, HOVER_THRUST, STATE_DIM, clamp_action
from drone_torchrl.envs.params import DroneParams
from drone_torchrl.extras import Needs
from drone_torchrl.io.checkpoint import CHECKPOINT_DIR
from drone_torchrl.io.storage import name_too_long, unwritable, write_atomically
from drone_torchrl.modules.factory import build_actor, build_policy
from drone_torchrl.modules.policy import actor_from_net
from drone_torchrl.schema import EXPORT_FORMATS
from drone_torchrl.training.population_record import open_agent

#: The largest difference (max abs, in fractions of the weight) an exported file may have from the
#: actor on check_observations(). The same float32 layers evaluated by other kernels (onnxruntime's
#: GEMM and tanh) differ by 1e-7 to 1e-6; a wrong head, a missing clamp or a stale weight by 1e-2 or
#: more. 1e-4 of the weight is far below anything the drone feels.
TOLERANCE = 1e-4
# The ONNX operator set written. The policy needs only Gemm, its activation (Tanh, Relu, Elu), Add,
# Mul and Clip, all in 18, which onnxruntime reads since 1.14 (2023): more runtimes than torch's
# default (20) reach.
ONNX_OPSET = 18
# What format=onnx imports: the onnx extra (pyproject.toml).
ONNX_MODULES = ("onnx", "onnxruntime", "onnxscript")
ONNX_EXTRA = "pip install 'drone_torchrl[onnx]'"
# The folder of a run that output=null exports into (default_output).
EXPORT_DIR = "export"
# The ONNX model's input and output names.
ONNX_INPUT, ONNX_OUTPUT = "observation", "thrust"
#: The runtime that runs each format, as the latency figures name it.
RUNTIMES = {"pt2": "torch.export", "onnx": "onnxruntime"}

# check_observations(): CHECK_RANDOM states drawn uniformly within CHECK_SPAN of CHECK_CENTRE (twice
# the domain where it has bounds: x +-2, z 0..4, alpha +-pi/3; velocities past any an episode
# reaches), the box's 64 corners, the floor start, hovering in the zone, and each component (and all
# of them) at +-CHECK_EXTREME, far outside any state (a tanh trunk saturates).
CHECK_SEED = 0
CHECK_RANDOM = 1024
_PAPER = DroneParams()
CHECK_CENTRE = (0.0, 0.0, 0.5 * (_PAPER.z_min + _PAPER.z_max), 0.0, 0.0, 0.0)
CHECK_SPAN = (2 * _PAPER.x_limit, 10.0, _PAPER.z_max - _PAPER.z_min, 10.0, 2 * _PAPER.alpha_limit, 20.0)
CHECK_EXTREME = 1e3
# Hovering in the zone's centre: one of the checked observations, and the one the latency is timed on.
HOVER_OBSERVATION = (0.0, 0.0, _PAPER.zone_z_centre, 0.0, 0.0, 0.0)

# Latency: the median over LATENCY_REPEATS repeats of the mean time of LATENCY_CALLS calls, after
# LATENCY_WARMUP untimed calls; one thread (a controller's one core, and no thread pool to wake).
LATENCY_REPEATS = 21
LATENCY_CALLS = 200
LATENCY_WARMUP = 50
US_PER_S = 1e6


class ExportError(RuntimeError):
    """An exported file that does not reproduce the actor (one line); nothing was written."""


class DeterministicPolicy(nn.Module):
    """Observation ``[B, 6]`` -> the motor commands ``[B, 2]`` the env applies (deterministic).

    Args:
        net: the policy's net, observations to the Normal's ``(loc, scale)``.
        distribution: the head, ``"normal"`` or ``"tanh_normal"`` (the mean squashed into
            ``[0, max_thrust]``).
        max_thrust: the per-motor thrust limit (``"tanh_normal"`` only).
    """

    def __init__(self, net: nn.Module, distribution: str, max_thrust: float | None) -> None:
        super().__init__()
        self.net = net
        self.distribution = distribution
        self.max_thrust = max_thrust

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        """The motor commands ``[B, 2]`` for observations ``[B, 6]``."""
        loc, _ = self.net(observation)
        # TanhNormal(low=0, high=max_thrust, tanh_loc=False): the mean through tanh onto [0, A].
        if self.distribution == "tanh_normal":
            loc = (torch.tanh(loc) + 1.0) * (0.5 * self.max_thrust)
        if self.max_thrust is not None:  # what dynamics.clamp_action does in the env
            loc = loc.clamp(0.0, self.max_thrust)
        return loc


@dataclass
class Exported:
    """What :func:`export_policy` wrote and how it compared with the actor."""

    path: Path
    format: str
    max_abs_diff: float  # the written file against the actor, on ``checked`` observations
    checked: int
    policy: DeterministicPolicy = field(repr=False)  # the eager policy it was exported from


# ------------------------------------------------------------------------------ what to write
def resolve_output(format: str | None, output: Any) -> tuple[str, Path | None]:
    """The format and the file of ``format=`` and ``output=``, checked to fit each other.

    They fit when the output's suffix is the format's (``.pt2``, ``.onnx``); otherwise
    :class:`~.checks.ConfigError`. A null format is the suffix's (``pt2`` without an output); a null
    output stays None: the file goes into the checkpoint's run folder (:func:`default_output`).
    """
    if format is not None and format not in EXPORT_FORMATS:
        raise ConfigError.of(
            "format", format, f"one of {list(EXPORT_FORMATS)}, or null (from the output's suffix)"
        )
    if output is None:
        return format or EXPORT_FORMATS[0], None
    if not isinstance(output, str | os.PathLike) or not str(output).strip():
        raise ConfigError.of("output", output, "a file path such as policy.pt2 or policy.onnx")
    path = Path(output)
    named = path.suffix.lower().removeprefix(".")
    if (too_long := name_too_long(path)) is not None:
        expected = f"a file name this file system takes ({too_long})"
    elif path.is_dir():
        expected = "a file path such as policy.pt2, not a folder"
    elif format is None and named not in EXPORT_FORMATS:
        suffixes = " or ".join(f".{name}" for name in EXPORT_FORMATS)
        expected = f"a file name ending in {suffixes} (its suffix names the format)"
    elif format is not None and named != format:
        expected = f"a file name ending in .{format}, to match format={format}"
    else:
        return named, path
    raise ConfigError.of("output", str(output), expected)


def default_output(checkpoint: Path, format: str, agent: int | None = None) -> Path:
    """Where ``output=null`` writes: ``<run>/export/<checkpoint's name>[_agent<K>].<format>``.

    ``<run>`` is the run folder of ``checkpoint`` (``<run>/checkpoints/<name>.pt``; a checkpoint file
    elsewhere: its own folder), so ``checkpoints/last.pt`` becomes ``export/last.pt2`` and
    ``best.pt`` ``best.pt2``: exports of other checkpoints, formats and agents do not overwrite each
    other, and nothing lands in the folder the command was started from.
    """
    checkpoint = Path(checkpoint)
    run = checkpoint.parent.parent if checkpoint.parent.name == CHECKPOINT_DIR else checkpoint.parent
    name = checkpoint.stem if agent is None else f"{checkpoint.stem}_agent{agent}"
    return run / EXPORT_DIR / f"{name}.{format}"


def check_onnx_extra() -> None:
    """format=onnx without the onnx extra: one line naming it (:class:`~.checks.ConfigError`)."""
    if missing := [name for name in ONNX_MODULES if not Needs(name, "onnx").installed]:
        raise ConfigError(f"format=onnx needs {', '.join(missing)}, not installed here: {ONNX_EXTRA}")


# ------------------------------------------------------------------------------- the policy
def policy_and_actor(
    net: nn.Module, distribution: str, max_thrust: float | None
) -> tuple[DeterministicPolicy, ProbabilisticActor]:
    """The exported policy over ``net`` and the TorchRL actor it must reproduce (both eval mode)."""
    policy = DeterministicPolicy(net, distribution, max_thrust).eval()
    return policy, actor_from_net(net, distribution, max_thrust).eval()


def load_policy(
    checkpoint: str | os.PathLike, agent: int | None = None
) -> tuple[DeterministicPolicy, ProbabilisticActor, Path]:
    """The deterministic policy and the actor of a checkpoint file or run folder, on the CPU.

    Of a population run, its agent ``agent``'s; :class:`~.checks.ConfigError` if unusable.
    """
    path, state = open_agent("checkpoint", checkpoint, agent)
    cfg = run_config(state["config"])
    cfg.device = "cpu"
    check_networks("checkpoint", path, state, cfg)
    net = build_policy(cfg)
    build_actor(cfg, net).load_state_dict(state["actor"])  # the actor's keys; the net holds the weights
    return (*policy_and_actor(net, cfg.model.distribution, cfg.env.max_thrust), path)


def actor_commands(
    actor: ProbabilisticActor, observation: torch.Tensor, max_thrust: float | None
) -> torch.Tensor:
    """The motor commands the env applies when ``actor`` acts deterministically: the reference."""
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = actor(TensorDict({"observation": observation}, batch_size=observation.shape[:1]))
    return clamp_action(td["action"], max_thrust)


def check_observations(observation_dim: int = STATE_DIM) -> torch.Tensor:
    """The float32 observations ``[N, observation_dim]`` every export is checked on.

    Fixed: seeded draws, corners, extremes; see ``CHECK_SPAN``. Past the 6 state entries (a run with
    ``env.disturbance.observed_actions``) come past commands, seeded uniforms in [0, 1].
    """
    centre, span = torch.tensor(CHECK_CENTRE), torch.tensor(CHECK_SPAN)
    generator = torch.Generator().manual_seed(CHECK_SEED)
    uniform = 2.0 * torch.rand(CHECK_RANDOM, STATE_DIM, generator=generator) - 1.0
    corners = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=STATE_DIM)))
    axes = torch.cat([torch.eye(STATE_DIM), torch.ones(1, STATE_DIM)])
    edges = [
        torch.zeros(1, STATE_DIM),  # the floor start
        torch.tensor([HOVER_OBSERVATION]),
        centre + span * corners,
        CHECK_EXTREME * axes,
        -CHECK_EXTREME * axes,
    ]
    states = torch.cat([centre + span * uniform, *edges]).to(torch.float32)
    commands = torch.rand(len(states), observation_dim - STATE_DIM, generator=generator)
    return torch.cat([states, commands], -1)


def observation_dim(policy: DeterministicPolicy) -> int:
    """Entries of the policy's observations: its first layer's inputs (6, plus 2 per observed command)."""
    return next(m for m in policy.modules() if isinstance(m, nn.Linear)).in_features


def _observation_names(policy: DeterministicPolicy) -> tuple[str, ...]:
    """Each entry of the policy's observations (:func:`~drone_torchrl.envs.disturbances.observation_names`)."""
    observed = (observation_dim(policy) - STATE_DIM) // ACTION_DIM
    return disturbances.observation_names({"observed_actions": observed})


# ------------------------------------------------------------------------------- writing
def _dtype(policy: DeterministicPolicy) -> torch.dtype:
    """The policy's dtype: float32, or float64 for a run with ``env.dtype=float64``."""
    return next(policy.parameters()).dtype


def program_bytes(policy: DeterministicPolicy, format: str) -> bytes:
    """``policy`` as the bytes of a ``format`` file (``pt2`` or ``onnx``), unchecked.

    See :func:`export_policy`. Made in memory: nothing reaches the disk before the file is checked, and then
    it is written at once (:func:`~drone_torchrl.io.storage.write_atomically`; torch's and onnx's own writers
    abort the process, in C++, on a full disk).
    """
    policy.requires_grad_(False)  # an inference program: no autograd graph in its outputs
    example = torch.zeros(2, observation_dim(policy), dtype=_dtype(policy))
    batch = torch.export.Dim("batch")
    with torch.no_grad():
        program = torch.export.export(policy, (example,), dynamic_shapes=({0: batch},))
    if format == "pt2":
        buffer = io.BytesIO()
        torch.export.save(program, buffer)
        return buffer.getvalue()
    # Silence the exporters' noise on drone-export's terminal: torch.onnx logs a warning for each
    # torchvision operator it cannot register, and torch.export's pytree warns about its deprecations.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            onnx_program = torch.onnx.export(
                program,
                (example,),
                dynamo=True,
                opset_version=ONNX_OPSET,
                input_names=[ONNX_INPUT],
                output_names=[ONNX_OUTPUT],
                external_data=False,
                verbose=False,
            )
    finally:
        logger.setLevel(level)
    model = onnx_program.model
    model.doc_string = "drone_torchrl policy: observations [B, 6] -> the motor commands [B, 2] the env applies (deterministic)"
    dtype = str(_dtype(policy)).removeprefix("torch.")
    model.metadata_props.update(  # what the model says about itself
        {
            ONNX_INPUT: f"{dtype} [B, {observation_dim(policy)}]: {', '.join(_observation_names(policy))}",
            ONNX_OUTPUT: f"{dtype} [B, 2]: left, right motor commands, fractions of the weight",
            "distribution": policy.distribution,
            "max_thrust": "none" if policy.max_thrust is None else repr(float(policy.max_thrust)),
            "written_by": "drone_torchrl drone-export",
        }
    )
    data = onnx_program.model_proto.SerializeToString()  # one file: the weights inside
    import onnx

    onnx.checker.check_model(data, full_check=True)
    return data


# ------------------------------------------------------------------------------- running
def onnx_session(source: str | os.PathLike | bytes, threads: int = 1) -> Any:
    """An onnxruntime CPU session of ``source`` (a file, or its bytes) on ``threads`` threads."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = threads
    options.log_severity_level = 3  # errors only
    model = source if isinstance(source, bytes) else os.fspath(source)
    return onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])


def load_program(source: str | os.PathLike | bytes, format: str) -> Callable[[torch.Tensor], torch.Tensor]:
    """The file ``source`` (a path, or its bytes) run by its own runtime, as a function.

    The function takes an observation batch in the policy's dtype.
    """
    if format == "pt2":
        return torch.no_grad()(
            torch.export.load(io.BytesIO(source) if isinstance(source, bytes) else source).module()
        )
    session = onnx_session(source)
    return lambda observation: torch.from_numpy(session.run(None, {ONNX_INPUT: observation.numpy()})[0])


def check_output_folder(output: Path, given: bool = True) -> None:
    """Refuse, before the work, an output whose folder cannot be written (:class:`~.checks.ConfigError`).

    ``given``: the user named it (``output=``); otherwise it is :func:`default_output`'s.
    """
    if (refused := unwritable(output.parent)) is None:
        return
    if given:
        raise ConfigError.of("output", str(output), f"a file in a folder this user can write ({refused})")
    raise ConfigError(
        f"output=null writes {output}, whose folder cannot be written ({refused}): give output=<file>"
    )


def export_policy(
    checkpoint: str | os.PathLike | None,
    output: str | os.PathLike | None = None,
    format: str | None = None,
    agent: int | None = None,
) -> Exported:
    """Write the deterministic policy of ``checkpoint`` to ``output`` as ``format``, checked.

    ``format`` and ``output`` are resolved by :func:`resolve_output` (no output: into the run
    folder, :func:`default_output`); the file is checked against
    the checkpoint's actor. Raises :class:`~.checks.ConfigError` for bad arguments (before any
    work), :class:`ExportError` for a file that does not reproduce the actor (nothing is written).
    """
    format, output = resolve_output(format, output)
    if format == "onnx":
        check_onnx_extra()
    if checkpoint is None:
        raise ConfigError.of("checkpoint", None, "a checkpoint file or a run folder")
    if output is not None:
        check_output_folder(output)
    policy, actor, path = load_policy(checkpoint, agent)
    if output is None:
        output = default_output(path, format, agent)
        check_output_folder(output, given=False)
    observations = check_observations(observation_dim(policy)).to(_dtype(policy))
    expected = actor_commands(actor, observations, policy.max_thrust)
    if not torch.isfinite(expected).all():
        raise ExportError(f"checkpoint={str(path)!r} gives commands that are not numbers (diverged weights?)")
    data = program_bytes(policy, format)
    got = load_program(data, format)(observations)
    if got.shape != expected.shape or got.dtype != expected.dtype:
        raise ExportError(
            f"the {format} program returns {got.dtype} {list(got.shape)}, "
            f"not {expected.dtype} {list(expected.shape)}"
        )
    difference = (got - expected).abs().max().item()
    if not difference <= TOLERANCE:  # NaN too
        raise ExportError(
            f"the {format} program differs from the actor by up to {difference:.3g} on "
            f"{len(observations)} observations (tolerance {TOLERANCE:g}); {output} not written"
        )
    write_atomically(output, data)  # never a half-written or unchecked file under the final name
    return Exported(output, format, difference, len(observations), policy)


def run_export(cfg: Mapping[str, Any]) -> Exported:
    """drone-export's work on its composed config (``conf/export.yaml``): the keys and values first."""
    resolved = check_keys(cfg, "export")
    check_values(resolved, "export")
    return export_policy(resolved["checkpoint"], resolved["output"], resolved["format"], resolved["agent"])


# ------------------------------------------------------------------------------- latency
@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """Torch on one intra-op thread (restored after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def median_us(
    call: Callable[[], Any],
    repeats: int = LATENCY_REPEATS,
    calls: int = LATENCY_CALLS,
    warmup: int = LATENCY_WARMUP,
) -> float:
    """The median over ``repeats`` of the mean time of one ``call()`` in ``calls``, in microseconds."""
    timer = timeit.Timer(call, "import gc; gc.enable()")  # timeit pauses the garbage collector otherwise
    timer.timeit(warmup)
    return statistics.median(timer.repeat(repeats, calls)) / calls * US_PER_S


def forward_passes(
    policy: DeterministicPolicy, files: Mapping[str, str | os.PathLike], batch: int = 1
) -> dict[str, Callable[[], Any]]:
    """Callables that each run one forward pass: of the eager policy and of each exported file.

    Each pass is of ``batch`` observations (hovering in the zone). The eager policy is
    ``eager torch``; each file in ``files`` (format -> path) runs in its runtime (:data:`RUNTIMES`).
    """
    hover = [*HOVER_OBSERVATION, *[HOVER_THRUST] * (observation_dim(policy) - STATE_DIM)]
    observation = torch.tensor([hover], dtype=_dtype(policy)).expand(batch, len(hover)).contiguous()
    passes: dict[str, Callable[[], Any]] = {}
    for format, path in files.items():
        if format == "onnx":  # the session fed numpy directly: no conversion timed
            passes[RUNTIMES[format]] = functools.partial(
                onnx_session(path).run, None, {ONNX_INPUT: observation.numpy()}
            )
        else:
            passes[RUNTIMES[format]] = functools.partial(load_program(path, format), observation)
    passes["eager torch"] = lambda: policy(observation)
    return passes


def latencies(passes: Mapping[str, Callable[[], Any]], **timing: int) -> dict[str, float]:
    """:func:`median_us` of each pass, on one thread and in inference mode (torch's)."""
    with one_thread(), torch.inference_mode():
        return {name: median_us(call, **timing) for name, call in passes.items()}
