"""steady_malloc: freed large arrays are reused instead of page-faulted in again each cycle."""
from __future__ import annotations

import platform
import subprocess
import sys

import pytest

LOOP = """
import resource, sys
import numpy as np
from fv_algos.allocator import steady_malloc
if sys.argv[1] == "steady":
    assert steady_malloc() and steady_malloc()
for _ in range(3):
    np.ones(8_000_000)  # 64 MB: above the 32 MiB ceiling of the dynamic threshold
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(50):
    np.ones(8_000_000)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", LOOP, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_steady_malloc_stops_refaulting_freed_arrays() -> None:
    default, steady = _faults("default"), _faults("steady")
    # default glibc: each 64 MB array is mmapped and unmapped again, faulting its pages in
    # every cycle (fewer than 16,384 a cycle where transparent huge pages serve some)
    assert default > 50 * 200
    assert steady < default / 20
