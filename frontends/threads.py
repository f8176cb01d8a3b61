"""The frontends' threads: how many cores this process may use, and a worker that runs calls in order.

`replay --map` runs two trackers on every scan: the localizer in the saved map, and the run's own SLAM
resumed on the saved graph, which takes the localizer's result of the same scan and gives nothing back
before `finish`. The SLAM of scan i can then run beside the localizer of scan i + 1 (`InOrderWorker`); their
kernels let go of the GIL (numba's `nogil`), so a second core shares the work."""

from __future__ import annotations

import functools
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from numba import config as numba_config

MAX_PENDING = 16
"""Calls queued at most before `submit` waits for the oldest: the queue holds their arguments (scans)."""


@functools.cache
def usable_cores() -> int:
    """The cores this process may run on (a process pinned to some, by taskset or a container, uses those)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


class InOrderWorker:
    """One worker thread. A call that fails stops the ones after it (the state they would work on is
    broken); its exception is raised by the next `submit` or `drain` after it.

    `threaded` False runs each call at once in `submit`: by default where this process may use one thread
    of numba's count (`NUMBA_NUM_THREADS`: the cores it may run on, or a batch worker's share of them, as
    `pipeline.batch` sets it), where handing the GIL back and forth would only cost."""

    def __init__(self, name: str, max_pending: int = MAX_PENDING, threaded: bool | None = None) -> None:
        self._threaded = numba_config.NUMBA_NUM_THREADS > 1 if threaded is None else threaded  # type: ignore[attr-defined]
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._pending: deque[Future[None]] = deque()
        self._max_pending = max_pending
        self._failed = False
        """Set by a failing call, on the worker thread: the calls after it, on the same thread, see it."""

    def submit(self, call: Callable[[], object]) -> None:
        if not self._threaded:
            call()
            return
        while self._pending and (self._pending[0].done() or len(self._pending) >= self._max_pending):
            self._pending.popleft().result()
        self._pending.append(self._executor.submit(self._run, call))

    def drain(self) -> None:
        """Waits for every call submitted; the worker thread ends."""
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            self._executor.shutdown(wait=True)

    def _run(self, call: Callable[[], object]) -> None:
        if self._failed:
            return
        try:
            call()
        except BaseException:
            self._failed = True
            raise
