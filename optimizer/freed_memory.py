"""Handing memory the process has freed back to the operating system, where the C library keeps it.

glibc serves allocations below its mmap threshold from its heap, and that threshold rises to the size of
the largest block freed so far (up to 32 MB): once a 10⁶-pose polish has freed one vector of 3·10⁶
numbers, every later array up to 32 MB comes from the heap. The heap returns memory only at its top, so
the scratch of the multigrid build, freed below the levels it leaves behind, stays resident: at 10⁶ poses
the heap held 150–290 MB of freed memory between the polish's steps, all of it in the peak RSS.
`malloc_trim(0)` releases the free pages anywhere in the heap. Elsewhere (another C library, another
system) there is nothing to call and nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Callable
from functools import cache


def return_freed_memory() -> None:
    """Releases the C library's free heap pages to the system (glibc's `malloc_trim`; elsewhere nothing)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim
