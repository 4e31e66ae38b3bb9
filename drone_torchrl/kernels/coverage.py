"""What the fast engine (``backend=fast``) flies, and the one-line reason where it cannot.

An option the C++ engine does not take is refused before any work (``backend=reference`` takes
every option), rather than silently run by other code.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from drone_torchrl.envs import disturbances
from drone_torchrl.envs.dynamics import DTYPES
from drone_torchrl.kernels.build import library, unavailable_reason
from drone_torchrl.kernels.ops import check_supported


def fast_refusal(
    device: str,
    hidden_sizes: Sequence[int],
    activation: str,
    dtype: str,
    disturbance: disturbances.Disturbance,
) -> str | None:
    """Why ``backend=fast`` cannot train this run (None where it can). Builds the kernels on first
    use (a few seconds once per machine, then cached)."""
    if torch.device(device).type != "cpu":
        return f"device={device!r} (its kernels run on the CPU; the CUDA build is not there yet)"
    reason = check_supported(disturbance.observation_dim, list(hidden_sizes), activation, DTYPES[dtype])
    if reason is not None:
        return reason
    if library(double=DTYPES[dtype] == torch.float64) is None:
        return f"this machine: its C++ kernels could not be built ({unavailable_reason()})"
    return None
