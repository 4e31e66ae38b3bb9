"""What the fast engine (``backend=fast``) flies, and the one-line reason where it cannot.

An option the C++ engine does not take is refused before any work (``backend=reference`` takes
every option), rather than silently run by other code. Each reason names the key that asks for it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from drone_torchrl.envs import disturbances
from drone_torchrl.envs.dynamics import DTYPES
from drone_torchrl.kernels.build import cuda_library, library, unavailable_reason
from drone_torchrl.kernels.ops import ACTIVATION_CODES, MAX_LAYERS, MAX_WIDTH
from drone_torchrl.kernels.ops import DTYPES as KERNEL_DTYPES


def fast_refusal(
    device: str,
    hidden_sizes: Sequence[int],
    activation: str,
    dtype: str,
    disturbance: disturbances.Disturbance,
    algo: str = "reinforce",
) -> str | None:
    """Why ``backend=fast`` cannot train this run, or None where it can.

    The reason reads ``"<key>=<value> (<why>)"``. Builds the kernels on first use (a few seconds
    once per machine, then cached; the CUDA engine for a ``cuda`` device). ``algo``: ``algo.name``;
    on a GPU the engine flies REINFORCE's updates, not PPO/A2C/SAC's segments.
    """
    cuda = torch.device(device).type == "cuda"
    if torch.device(device).type not in ("cpu", "cuda"):
        return f"device={device!r} (the fast engine runs on the CPU or a CUDA GPU)"
    if cuda and algo != "reinforce":
        return f"device={device!r} with algo.name={algo!r} (on a GPU the fast engine trains REINFORCE only)"
    hidden = list(hidden_sizes)
    if len(hidden) > MAX_LAYERS or any(not 0 < h <= MAX_WIDTH for h in hidden):
        return f"model.hidden_sizes={hidden} (at most {MAX_LAYERS} layers of at most {MAX_WIDTH})"
    if activation not in ACTIVATION_CODES:
        return f"model.activation={activation!r} (one of {list(ACTIVATION_CODES)})"
    if DTYPES[dtype] not in KERNEL_DTYPES:
        return f"env.dtype={dtype!r}"
    if disturbance.observed_actions > disturbances.MAX_STEPS_BACK:
        return f"env.disturbance.observed_actions={disturbance.observed_actions}"
    if (cuda_library if cuda else library)(double=DTYPES[dtype] == torch.float64) is None:
        engine = "CUDA engine" if cuda else "C++ kernels"
        return f"this machine: its {engine} could not be built ({unavailable_reason()})"
    return None
