"""Freed heap memory is handed back to the system where the C library can do it (glibc)."""

from __future__ import annotations

import os
import sys

import pytest

from optimizer.freed_memory import _malloc_trim, return_freed_memory


def resident_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not sys.platform.startswith("linux") or _malloc_trim() is None,
                    reason="needs Linux with glibc's malloc_trim")
def test_holes_freed_below_live_memory_leave_the_resident_set() -> None:
    # 100 kB blocks come from glibc's heap (below its initial mmap threshold); every tenth stays alive, so
    # the freed ones are holes under live memory, which the heap cannot give back from its top.
    blocks = [bytes(100_000) for _ in range(1000)]
    kept = blocks[::10]
    del blocks
    before = resident_bytes()
    return_freed_memory()
    assert before - resident_bytes() > 50_000_000
    assert len(kept) == 100
