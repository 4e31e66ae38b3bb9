"""The fast engine's C++ kernels (CPU, and CUDA where built), called through :mod:`.ops`."""

from drone_torchrl.kernels.build import library, unavailable_reason

__all__ = ["library", "unavailable_reason"]
