"""Keep freed heap memory in the process (Linux, glibc), so large tensors are not page-faulted anew every update.

The loss of a large population works on tensors of tens of MB (``[agents, steps, hidden]``:
40 MB at 1024 agents). glibc serves an allocation above its mmap threshold (adaptive, at most
32 MB) with fresh pages from the OS and unmaps them when the tensor is freed, so each update
faults every page of those tensors in again, which makes an elementwise op on such a tensor
several times slower than on reused memory. PyTorch's CPU allocator does not cache (its tuning guides swap in
jemalloc or tcmalloc for this); raising glibc's mmap and trim thresholds has the same effect
without a preloaded library. The process keeps freed memory until it exits (and the heap grows by
a block now and then, when a small allocation splits a freed one). Elsewhere (macOS, musl,
Windows) this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Allocations below this come from the reusable heap; larger than any tensor of a population's
#: update here (a 4096-agent loss tensor is 160 MB), small enough to leave mmap for true outliers.
KEEP_BELOW_BYTES = 1 << 30
#: The largest mmap threshold glibc documents (4 MiB x sizeof(long)); older versions refuse more.
DOCUMENTED_MAX_BYTES = 32 << 20


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds; True if both took effect.

    The mmap threshold goes to :data:`KEEP_BELOW_BYTES` (or, where refused, to
    :data:`DOCUMENTED_MAX_BYTES`), and the trim threshold alike.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mmap = any(mallopt(_M_MMAP_THRESHOLD, size) for size in (KEEP_BELOW_BYTES, DOCUMENTED_MAX_BYTES))
    trim = bool(mallopt(_M_TRIM_THRESHOLD, KEEP_BELOW_BYTES))
    return mmap and trim
