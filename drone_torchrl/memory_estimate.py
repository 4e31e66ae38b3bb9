"""The memory a training config will allocate, estimated before any work, and its refusal.

The refusal, of a config that cannot fit, is one line (:func:`~.memory_estimate.check`).

A batch too large to allocate failed after start-up with an allocator traceback, and a huge
``model.hidden_sizes`` got the process killed with no message at all. :func:`estimate` derives the
bytes from the shapes the code allocates; :func:`~.memory_estimate.check` compares them with what this
machine has free (``MemAvailable``, or the GPU's free memory on ``device=cuda``) and refuses the config naming
what to lower in its largest part. ``agents`` is the number of runs one process trains together (a
population): every part but the video is per agent.

Notation: ``b`` bytes per float (4, or 8 with ``env.dtype=float64``: the nets run in the env's
dtype), ``D`` the observation size (6 + 2 x ``env.disturbance.observed_actions``), ``H`` the sum of
``model.hidden_sizes``, ``Hv`` of ``algo.value_hidden_sizes``, ``P`` and ``Pv`` the policy's and the
critic's parameter counts (a linear layer ``i -> o`` has ``i o + o``; the policy is the trunk
``D -> H1 -> ... -> Hn`` and two heads ``Hn -> 2``, the critic ``D -> Hv1 -> ... -> 1``), ``A`` the
agents and ``T`` = ``env.max_steps``. The parts:

- **weights**: the weights, their gradient and Adam's two moments, ``4 A P b``, and ``A P b`` more
  for the nets the population is built from (training.population); on-policy learners also hold
  the critic's, ``4 Pv b``.
- **a rollout** (every evaluation, and the reference's update), per drone-step: ``39 b + 24``
  (:func:`rollout_bytes`): the episodes' states and what the policy saw (6 each), actions (2),
  rewards and returns in floats and termination causes (int64) as they are flown, and their copies
  in TorchRL's rollout layout (the observation and the next one, ...) and masked after each
  row's end.
- **REINFORCE's update** (E = ``algo.episodes_per_update`` episodes of each agent, buffered to
  ``T`` steps): ``A E T`` drone-steps. ``backend=fast``: what the kernel keeps of each step for
  the backward pass (the observation, every hidden output, loc, the std head's input, the action and
  the return-to-go: ``(D + H + 7) b``), the backward pass's gradients of every hidden output and of
  the heads (``(H + 4) b``), and the rewards, returns-to-go and causes it writes (``2 b + 8``). ``backend=reference``: a rollout's bytes, what the policy saw (``D b``) and the
  loss's autograd graph through the trunk (:func:`graph_bytes`): the forward pass keeps each
  layer's activation for the backward pass (``H b``), and the backward pass holds, at the widest
  layer ``h``, the gradients of its output, of its pre-activation and of its input (``3 h b``);
  with the heads' and the distribution's 12 floats.
- **the on-policy batch** (PPO, A2C: F = ``algo.num_envs x algo.steps_per_batch`` frames): a frame
  of the collector's batch holds the observation and the next one, the action, the distribution's
  loc and scale, the log-probability, the reward, and after GAE the value, the next value, the
  advantage, the target and the scaled reward, ``(2 D + 13) b``, with the step counts and
  trajectory ids (int64) and six done flags (bool), 30 bytes more; there are three copies of it
  (the collector's steps before they are stacked, the batch, the replay buffer's); and GAE runs the
  critic on the observations and the next ones stacked (TorchRL's ``_call_value_nets``), a copy of
  both and the widest layer's pre-activation and activation, ``2 (D + 2 hv) b`` per frame. Each
  minibatch (M = ``algo.minibatch_size`` frames) is a fourth copy of its frames and the loss's
  graph through both nets, as REINFORCE's, per frame.
- **evaluation** (``eval.episodes`` of each agent, ``T`` steps): a rollout's bytes per drone-step
  and its tensordict's three flags (bool) and two counters (int64); with ``eval.video`` the frames
  of one episode, ``(T / logger.video_stride + 1)`` x 600 x 600 x 3 bytes, and a quarter more for
  the thinned copy TensorBoard gets (host memory, also with ``device=cuda``). ``drone-eval`` keeps
  the rollouts of the checkpoint's policy and the PD controller's, and its GIF's frames
  (:func:`evaluation_parts`).

Each part is sized for the longest case (every episode lasting ``T`` steps, every batch whole),
without what the libraries allocate for themselves (tens of MB). ``tests/test_memory_estimate.py``
measures the peak memory of an update and an evaluation of real configs whose episodes last ``T``
steps: the estimate is within :data:`STATED_FACTOR` of it, either way.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

from drone_torchrl.checks import ConfigError
from drone_torchrl.envs.dynamics import ACTION_DIM, STATE_DIM
from drone_torchrl.envs.rendering import FRAME_HEIGHT, FRAME_WIDTH
from drone_torchrl.kernels.ops import AGENTS_PER_CALL, AGENTS_PER_EVALUATION
from drone_torchrl.modules.factory import observation_dim

#: The estimate is within this factor of what an update and an evaluation allocate, either way.
STATED_FACTOR = 2.0
FLOAT_BYTES = {"float32": 4, "float64": 8}
INT64_BYTES = 8
# Adam's weights, gradient, first and second moments.
ADAM_COPIES = 4
# The per-step and per-frame counts are the module docstring's, each written once, in the function
# that sizes its part (the comments there say what each number counts).


@dataclass(frozen=True)
class Part:
    """One part of the memory: its bytes, the keys that shrink it, and whether it lives on the host.

    Bytes one thing allocates, what to change to make it smaller, and whether it lives on the host
    even when the run is on a GPU (the video frames).
    """

    bytes: int
    advice: str
    host: bool = False


@dataclass(frozen=True)
class MemoryEstimate:
    """The parts of a config's memory, by what allocates them."""

    parts: Mapping[str, Part]

    @property
    def total(self) -> int:
        """Bytes of all the parts together."""
        return sum(part.bytes for part in self.parts.values())

    def on(self, host: bool | None) -> int:
        """Bytes on the host (``True``), on the run's device (``False``) or on either (None)."""
        return sum(part.bytes for part in self.parts.values() if host is None or part.host == host)


def size(n: float) -> str:
    """``n`` bytes in the largest unit that keeps a number >= 1 (``12.3 GB``)."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if n < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"


def mlp_parameters(widths: Sequence[int]) -> int:
    """Parameters of linear layers ``widths[0] -> widths[1] -> ...`` (weights and biases)."""
    return sum(i * o + o for i, o in pairwise(widths))


def policy_parameters(cfg: Mapping[str, Any]) -> int:
    """The three-net policy's parameters: the trunk and its two heads."""
    hidden = list(cfg["model"]["hidden_sizes"])
    return mlp_parameters([observation_dim(cfg), *hidden]) + 2 * mlp_parameters([hidden[-1], ACTION_DIM])


def rollout_bytes(b: int) -> int:
    """A rollout's bytes per drone-step with ``b``-byte floats."""
    # States, actions and rewards in floats (the cause is an int64), in the chunks (with the
    # observations), concatenated (states and observations both), and masked.
    return (3 * (STATE_DIM + ACTION_DIM + 1) + 2 * STATE_DIM) * b + 3 * INT64_BYTES


def graph_bytes(hidden: Sequence[int], b: int) -> int:
    """Bytes of the loss's autograd graph per sample through hidden layers of these widths.

    The graph holds every layer's activation, and the backward pass's gradients at the widest (of
    its output, its pre-activation and its input).
    """
    return (sum(hidden) + 3 * max(hidden)) * b


def flown_frame_bytes(d: int, b: int) -> int:
    """A frame of a flown batch (the on-policy learners', SAC's) with ``d`` observations, ``b``-byte floats."""
    # The observation and the next one; action, loc, scale (2 each), log-probability, reward, value,
    # next value, advantage, value target and the scaled reward; step counts (and the next ones)
    # and the collector's trajectory ids (int64); the done, terminated and truncated flags (and the
    # next ones; bools).
    return (2 * d + 3 * ACTION_DIM + 7) * b + 3 * INT64_BYTES + 6


def reinforce_parts(cfg: Mapping[str, Any], agents: int) -> dict[str, Part]:
    """REINFORCE's update: ``A x algo.episodes_per_update x env.max_steps`` drone-steps.

    Sized on the backend's terms: the C++ engine's buffers, or the reference's rollout and
    autograd graph.
    """
    b = FLOAT_BYTES[cfg["env"]["dtype"]]
    steps = cfg["algo"]["episodes_per_update"] * cfg["env"]["max_steps"]
    hidden = cfg["model"]["hidden_sizes"]
    advice = "lower algo.episodes_per_update, env.max_steps or model.hidden_sizes"
    if cfg["backend"] == "fast":
        # The kernel's buffers, for the agents of one kernel call: kept for the backward pass, the
        # observation, the hidden outputs, loc, the std head's input and the action (2 each) and the
        # return-to-go; the backward pass's gradients of every hidden output and of the heads (2
        # each); the rewards and returns-to-go (floats) and causes (int64) it writes.
        steps *= min(agents, AGENTS_PER_CALL)
        saved = observation_dim(cfg) + sum(hidden) + 3 * ACTION_DIM + 1
        per_step = (saved + sum(hidden) + 2 * ACTION_DIM + 2) * b + INT64_BYTES
    else:
        # Besides the trunk, the loss's loc, scale, their pre-activations, the log-probability, its
        # reduction, the returns-to-go, the weights of each step and their gradients: 12 floats.
        steps *= agents
        per_step = rollout_bytes(b) + observation_dim(cfg) * b + graph_bytes(hidden, b) + 12 * b
    return {"REINFORCE's update": Part(steps * per_step, advice)}


def on_policy_parts(cfg: Mapping[str, Any], agents: int) -> dict[str, Part]:
    """The on-policy learners' (PPO, A2C) batch, a minibatch's graph, and the critic's weights.

    The batch is ``algo.num_envs x algo.steps_per_batch`` frames.
    """
    algo, b, d = cfg["algo"], FLOAT_BYTES[cfg["env"]["dtype"]], observation_dim(cfg)
    value_hidden = list(algo["value_hidden_sizes"])
    frame = flown_frame_bytes(d, b)
    frames = agents * algo["num_envs"] * algo["steps_per_batch"]
    # Three copies of a frame (the collector's steps before they are stacked, the batch, the replay
    # buffer's), and GAE's critic pass on the observations and the next ones stacked: their copy,
    # and the widest layer's pre-activation and activation.
    batch = frames * (3 * frame + 2 * (d + 2 * max(value_hidden)) * b)
    graph = graph_bytes([*cfg["model"]["hidden_sizes"], *value_hidden], b)
    minibatch = agents * algo["minibatch_size"] * (frame + graph)
    critic = agents * ADAM_COPIES * mlp_parameters([d, *value_hidden, 1]) * b
    advice = "lower algo.minibatch_size, model.hidden_sizes or algo.value_hidden_sizes"
    return {
        "the on-policy batch": Part(batch, "lower algo.num_envs or algo.steps_per_batch"),
        "a minibatch": Part(minibatch, advice),
        "the critic's weights": Part(critic, "lower algo.value_hidden_sizes"),
    }


def sac_parts(cfg: Mapping[str, Any], agents: int) -> dict[str, Part]:
    """SAC's replay buffer, the batch it flies, a minibatch's graph and the Q-networks' weights.

    The replay buffer holds ``algo.buffer_size`` frames.
    """
    algo, b, d = cfg["algo"], FLOAT_BYTES[cfg["env"]["dtype"]], observation_dim(cfg)
    q_hidden = list(algo["qvalue_hidden_sizes"])
    # A stored frame: the observation and the next one, the action (2) and the reward; its done and
    # terminated flags (bool); with n-step returns each window's length (int64) too.
    stored = (2 * d + ACTION_DIM + 1) * b + 2 + (INT64_BYTES if algo["n_steps"] > 1 else 0)
    frames = agents * algo["num_envs"] * algo["steps_per_batch"]
    # SACLoss's graph per sample: the actor on the observations and the next ones; the two
    # Q-networks on (observation, action), on (observation, new action) and their targets on the next ones.
    graph = 2 * graph_bytes(cfg["model"]["hidden_sizes"], b) + 6 * graph_bytes(q_hidden, b)
    # Two Q-networks, each with its gradient, Adam's two moments and its target copy.
    q_weights = 2 * (ADAM_COPIES + 1) * mlp_parameters([d + ACTION_DIM, *q_hidden, 1]) * b
    return {
        "the replay buffer": Part(agents * algo["buffer_size"] * stored, "lower algo.buffer_size"),
        "the flown batch": Part(
            frames * flown_frame_bytes(d, b), "lower algo.num_envs or algo.steps_per_batch"
        ),
        "a minibatch": Part(
            agents * algo["batch_size"] * (stored + graph),
            "lower algo.batch_size, model.hidden_sizes or algo.qvalue_hidden_sizes",
        ),
        "the Q-networks' weights": Part(agents * q_weights, "lower algo.qvalue_hidden_sizes"),
    }


def estimate(
    cfg: Mapping[str, Any], agents: int = 1, learner: Callable[[Mapping, int], dict[str, Part]] | None = None
) -> MemoryEstimate:
    """The memory of a training config with ``agents`` runs in one process.

    The config is resolved, as nested mappings. ``learner`` gives the algorithm's own parts (its
    :class:`~drone_torchrl.registry.Algorithm`'s ``memory``; None: the parts every run has).
    """
    b = FLOAT_BYTES[cfg["env"]["dtype"]]
    weights = (ADAM_COPIES + 1) * agents * policy_parameters(cfg) * b
    parts = {"the policy's weights": Part(weights, "lower model.hidden_sizes")}
    if learner is not None:
        parts.update(learner(cfg, agents))
    episodes = min(agents, AGENTS_PER_EVALUATION) * cfg["eval"]["episodes"]
    video = cfg["logger"]["video_stride"] if cfg["eval"]["video"] else None
    advice = "lower eval.episodes or env.max_steps"
    video_advice = "set eval.video=false, raise logger.video_stride or lower env.max_steps"
    parts.update(evaluation_parts(b, episodes, cfg["env"]["max_steps"], video, advice, video_advice))
    return MemoryEstimate(parts)


def evaluation_parts(
    b: int, episodes: int, max_steps: int, video_stride: int | None, advice: str, video_advice: str
) -> dict[str, Part]:
    """The memory of ``episodes`` evaluation episodes and of a video of one of them.

    The episodes: every agent's, or every policy's that ``drone-eval`` keeps. ``video_stride``: the
    steps drawn (None: no video). ``advice`` and ``video_advice`` name the keys that size them.
    """
    # Per drone-step, a rollout and its tensordict's terminated, truncated and done flags (bool)
    # and step count and termination cause (int64).
    parts = {"evaluation": Part(episodes * max_steps * (rollout_bytes(b) + 3 + 2 * INT64_BYTES), advice)}
    if video_stride is not None:  # RGB frames, and a quarter more for TensorBoard's thinned copy
        frames = max_steps // video_stride + 1
        video = math.ceil(frames * (FRAME_WIDTH * FRAME_HEIGHT * 3) * (1 + 0.25))
        parts["an evaluation video"] = Part(video, video_advice, host=True)
    return parts


def available_ram() -> tuple[int, str] | None:
    """Bytes of RAM a new allocation can take and where that number comes from, or None."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "MemAvailable"
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free physical pages"
    except (OSError, ValueError, AttributeError):
        return None


def available_gpu(device: Any) -> tuple[int, str] | None:
    """Free bytes on the GPU ``device`` names, or None for another device."""
    import torch

    if torch.device(device).type != "cuda" or not torch.cuda.is_available():
        return None
    free, _ = torch.cuda.mem_get_info(torch.device(device))
    return free, f"free on {device}"


def check(memory: MemoryEstimate, device: Any) -> None:
    """Raise a one-line :class:`~.checks.ConfigError` when ``memory`` exceeds what is free.

    The GPU's for the parts on ``device=cuda``, the RAM for the rest (everything on the CPU).
    """
    gpu = available_gpu(device)
    # (the parts' side: the host, the device, or None for all; the memory free there; its name)
    checks = [(False, gpu, "of GPU memory")] if gpu is not None else []
    checks.append((None if gpu is None else True, available_ram(), "of RAM"))
    for side, free, what in checks:
        needed = memory.on(side)
        if free is None or needed <= free[0]:
            continue
        parts = [item for item in memory.parts.items() if side is None or item[1].host == side]
        name, part = max(parts, key=lambda item: item[1].bytes)
        raise ConfigError(
            f"this config needs about {size(needed)} of memory, more than the {size(free[0])} {what} "
            f"available ({free[1]}); the largest part is {name}, {size(part.bytes)}: {part.advice}"
        )
