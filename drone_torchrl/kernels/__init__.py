"""C++ CPU kernels of the fast engine, as ``torch.library`` custom ops (see :mod:`.ops`)."""

from drone_torchrl.kernels.build import library, unavailable_reason

__all__ = ["library", "unavailable_reason"]
