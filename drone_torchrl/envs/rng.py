"""Counter-based random numbers: an agent's noise is a function of (seed, update, stream, index).

The fast path draws each agent's start states and action noise for a whole update at once. With
one ``torch.Generator`` per agent that is one call per agent per update (Python work that grows
with the population) and a generator state to save. Here the numbers are a hash of the agent's
``seed``, the update counter (the run record's ``updates_done``), a stream id and the element's
index, computed for all agents in a few tensor operations:

- an agent's numbers do not depend on how many agents share the batch or where it sits, so an agent
  trained alone and inside any population follows the same run;
- resuming needs no RNG state: the counter is the update count the checkpoint already holds;
- the same code runs on CPU and GPU and gives the same integers on both.

The hash is SplitMix64's finaliser (Steele, Lea and Flood, 2014), applied as in SplitMix64's own
stream (``mix(key + index * golden)``), on int64 tensors with wrap-around arithmetic. Uniforms
take the top 24 bits (exact in float32, never 0 or 1); normals use the Box-Muller transform, the two
outputs of one pair going to the two motors.
"""

from __future__ import annotations

import ctypes
import math

import torch


def _signed(value: int) -> int:
    """An unsigned 64-bit constant as the int64 with the same bits."""
    return ctypes.c_int64(value).value


GOLDEN = _signed(0x9E3779B97F4A7C15)
_M1 = _signed(0xBF58476D1CE4E5B9)
_M2 = _signed(0x94D049BB133111EB)
# Distinct odd multipliers that spread the update counter and the stream id over the key.
_UPDATE = _signed(0xD1B54A32D192ED03)
_STREAM = _signed(0xAEF17502108EF2D9)
UNIFORM_BITS = 24

# Streams: independent sequences per purpose.
START_STATES = 1
ACTION_NOISE = 2
EPISODE_KEYS = 3  # the keys of the episodes' disturbances (drone_torchrl.envs.disturbances)


def _shift_right(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 bits (torch's ``>>`` is arithmetic on signed integers)."""
    return (x >> bits) & ((1 << (64 - bits)) - 1)


def mix(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64's finaliser: a bijection of 64-bit integers that scatters every input bit."""
    x = (x ^ _shift_right(x, 30)) * _M1
    x = (x ^ _shift_right(x, 27)) * _M2
    return x ^ _shift_right(x, 31)


def keys(seeds: torch.Tensor, counters: torch.Tensor, stream: int, shape: tuple[int, ...]) -> torch.Tensor:
    """64-bit keys, int64 ``[N, *shape]``: the hash of each agent's (seed, counter, stream) key and element index.

    The raw hashes, to seed counter-based draws of their own.
    """
    seeds = torch.as_tensor(seeds, dtype=torch.int64)
    counters = torch.as_tensor(counters, dtype=torch.int64, device=seeds.device)
    key = mix(mix(seeds) ^ (counters * _UPDATE + _signed(stream * _STREAM)))
    index = torch.arange(math.prod(shape), dtype=torch.int64, device=seeds.device).reshape(shape)
    return mix(key.reshape(-1, *([1] * len(shape))) + index * GOLDEN)


def uniform(seeds: torch.Tensor, counters: torch.Tensor, stream: int, shape: tuple[int, ...]) -> torch.Tensor:
    """Uniforms in (0, 1), float32 ``[N, *shape]``: agent ``i``'s depend only on its seed and counter."""
    top = _shift_right(keys(seeds, counters, stream, shape), 64 - UNIFORM_BITS)
    return (top.to(torch.float32) + 0.5) / float(1 << UNIFORM_BITS)


def normal(seeds: torch.Tensor, counters: torch.Tensor, stream: int, shape: tuple[int, ...]) -> torch.Tensor:
    """Standard normals, float32 ``[N, *shape]`` with an even last dim (Box-Muller pairs)."""
    if shape[-1] % 2:
        raise ValueError(f"normal() needs an even last dim, got shape {shape}")
    return box_muller(uniform(seeds, counters, stream, shape)).reshape(-1, *shape)


def box_muller(u: torch.Tensor) -> torch.Tensor:
    """Standard normals from uniforms ``[..., 2k]``, two from each consecutive pair, in the uniforms' dtype."""
    radius = (-2.0 * u[..., 0::2].log()).sqrt()
    angle = 2.0 * math.pi * u[..., 1::2]
    return torch.stack((radius * angle.cos(), radius * angle.sin()), -1).flatten(-2)
