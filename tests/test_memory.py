"""keep_freed_memory: a large tensor freed and allocated again reuses its pages instead of faulting new ones."""

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

# Allocates and frees a 40 MB tensor (a 1024-agent loss tensor) 20 times, as updates do, and prints
# how many minor page faults filling them took after the first.
# The probe loads what a training process has loaded when Trainer calls keep_freed_memory: with
# only the small memory module imported (the package loads its modules lazily), the heap is young
# and small allocations split the freed block several times more often than in a real run.
PROBE = """
import resource, sys, torch
import drone_torchrl.training.trainer
from drone_torchrl.training.memory import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "keep" else None
x = torch.ones(1024 * 300 * 32); del x
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(19):
    y = torch.ones(1024 * 300 * 32); del y
print(took, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
    took, faults = out.stdout.split()
    return took, int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_large_tensor_is_reused_without_page_faults():
    pages = 19 * 1024 * 300 * 32 * 4 // 4096  # 19 tensors of 9600 pages of 4 KiB
    with ThreadPoolExecutor(2) as pool:  # two processes (mallopt is per process), side by side
        (took, kept), (_, default) = pool.map(_faults, ("keep", "default"))
    if took != "True":
        pytest.skip("this C library refused the thresholds (not glibc, or an old one)")
    assert default > pages // 2  # glibc maps fresh pages for each: every page faults when filled
    # The freed pages are reused (a small allocation may split a freed block now and then, and the
    # heap then grows once more).
    assert kept < pages // 4
