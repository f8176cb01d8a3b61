"""Where the 2D frontend spends its time: wall and CPU seconds per stage, accumulated over a whole log.

Stages nest (verification runs inside the loop search, the local map is rebuilt inside the online
optimization); each second is charged to the innermost stage running, so the stages add up to the time
spent inside any of them. CPU seconds are the process's (every thread), which on a machine shared with
other work says more than the wall clock.
"""

from __future__ import annotations

import time
from types import TracebackType


class StageTimes:
    """Accumulators: `with times.stage("matching"): ...`; read `wall` and `cpu` (seconds per stage)."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._running: list[str] = []
        self._mark_wall = 0.0
        self._mark_cpu = 0.0

    def stage(self, name: str) -> _Stage:
        return _Stage(self, name)

    def _charge(self) -> None:
        """Charge the time since the last mark to the innermost running stage, and move the mark."""
        wall, cpu = time.perf_counter(), time.process_time()
        if self._running:
            name = self._running[-1]
            self.wall[name] = self.wall.get(name, 0.0) + wall - self._mark_wall
            self.cpu[name] = self.cpu.get(name, 0.0) + cpu - self._mark_cpu
        self._mark_wall, self._mark_cpu = wall, cpu

    def _enter(self, name: str) -> None:
        self._charge()
        self._running.append(name)

    def _exit(self) -> None:
        self._charge()
        self._running.pop()


class _Stage:
    __slots__ = ("_name", "_times")

    def __init__(self, times: StageTimes, name: str) -> None:
        self._times = times
        self._name = name

    def __enter__(self) -> None:
        self._times._enter(self._name)

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self._times._exit()
