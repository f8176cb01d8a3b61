"""KISS-ICP in a worker process, one cloud ahead of the SLAM.

KISS-ICP holds the GIL while it registers a cloud (and small_gicp while it verifies a loop closure), so a
thread cannot run the SLAM's own work (reading and decoding clouds, keyframes, loop search and verification,
recording: a quarter of a town-loop replay's CPU, on one core) beside it. A process can: `OdometryWorker`
deskews each cloud here (`odometry.SweepFrames`, with KISS-ICP's motion from the last cloud), sends it to a
`kiss_registration.KissRegistration` in a child process and makes its step from the answer, and the SLAM
submits the next cloud before it processes the last one (`LidarSlam3D.add_cloud`'s `upcoming`). The odometry
never depends on loop closures, so the steps are those of `KissOdometry` in this process, bit for bit: the
same code registers the same clouds with the same motion guesses in the same order.

The child is a fresh interpreter (`python -m frontends.slam3d.kiss_registration`), never a fork: forking a
process whose threads (numba's, rerun's, KISS-ICP's TBB pool) hold locks is unsafe, and multiprocessing's
spawn would import the parent's `__main__` (a benchmark script, a notebook) again in the child. It starts when
the frontend is made, so that its imports (numpy and KISS-ICP, no numba: about half a CPU second) overlap the
parent's start-up. Messages are pickles on the child's stdin and stdout; one request is in flight at a time
(`submit`, then `receive`), so neither side ever waits on the other's full pipe and at most one cloud is on
its way. The child runs in a session of its own, so that a Ctrl-C in the terminal reaches only the parent,
which stops it: `close` (also when the worker is garbage-collected or the interpreter exits) closes its pipes,
and a child whose parent died sees its stdin end and exits after its current cloud.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
import tempfile
import weakref
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from frontends.errors import FrontendError
from frontends.slam3d import kiss_registration
from frontends.slam3d.config import OdometryConfig
from frontends.slam3d.odometry import (
    InlineOdometry,
    KissOdometry,
    OdometryQueue,
    OdometryStep,
    SweepFrame,
    SweepFrames,
)

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
"""The folder holding `frontends`: the child's working directory, so that it imports this very copy."""
STOP_GRACE_S = 2.0
"""How long a closed worker has to finish its cloud and exit before it is killed."""
STDERR_TAIL = 2000
"""How much of a dead worker's stderr its error message quotes (characters)."""


class OdometryWorkerError(FrontendError):
    """The odometry's worker process failed or stopped."""


def start_odometry(config: OdometryConfig) -> OdometryQueue:
    """The odometry a replay uses: KISS-ICP in a worker process, or in this process on a single core,
    where the worker could only take turns with it."""
    if len(os.sched_getaffinity(0)) < 2:
        return InlineOdometry(KissOdometry(config))
    return OdometryWorker(config)


class OdometryWorker:
    """`KissOdometry(config)` in a child process, as an `OdometryQueue`. Raises `OdometryWorkerError`
    when the child fails (its error) or dies (its exit code and the end of its stderr)."""

    def __init__(self, config: OdometryConfig) -> None:
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 (closed with the child, by `_stop_worker`)
        self._process = subprocess.Popen(
            [sys.executable, "-m", kiss_registration.__name__], cwd=PACKAGE_ROOT, stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self._stderr, start_new_session=True)
        self._stop = weakref.finalize(self, _stop_worker, self._process, self._stderr)
        self._frames = SweepFrames(config)
        self._submitted = False
        self._in_flight: SweepFrame | None = None
        """The frame the child registers (None: none, or the cloud submitted had too few points)."""
        self._send(config)

    @property
    def pid(self) -> int:
        return self._process.pid

    def submit(
        self,
        points: NDArray[np.floating],
        point_times: NDArray[np.float64] | None,
        motion_guess: NDArray[np.float64] | None,
    ) -> None:
        if self._submitted:
            raise FrontendError("a cloud was submitted to the odometry before the last one was received")
        frame = self._frames.prepare(points, point_times, motion_guess)
        if frame is not None:
            self._send((frame.frame, frame.motion_guess))
        self._submitted, self._in_flight = True, frame

    def receive(self) -> OdometryStep | None:
        if not self._submitted:
            raise FrontendError("no cloud was submitted to the odometry")
        frame, self._submitted, self._in_flight = self._in_flight, False, None
        if frame is None:
            return None
        stdout = self._process.stdout
        try:
            if stdout is None or stdout.closed:
                raise ValueError("closed")
            kind, value = pickle.load(stdout)
        except (EOFError, OSError, ValueError, pickle.UnpicklingError) as error:
            raise OdometryWorkerError(self._stopped()) from error
        if kind == "error":
            self.close()
            raise OdometryWorkerError(f"the odometry failed: {value}")
        return self._frames.registered(frame, *value)

    def close(self) -> None:
        """Stop the child (at once when idle; after its current cloud, or killed, otherwise)."""
        self._stop()

    def __enter__(self) -> OdometryWorker:
        return self

    def __exit__(self, *_exception: object) -> None:
        self.close()

    def _send(self, message: object) -> None:
        stdin = self._process.stdin
        try:
            if stdin is None or stdin.closed:
                raise ValueError("closed")
            pickle.dump(message, stdin, protocol=pickle.HIGHEST_PROTOCOL)
            stdin.flush()
        except (OSError, ValueError) as error:
            raise OdometryWorkerError(self._stopped()) from error

    def _stopped(self) -> str:
        """Why the child cannot answer: its exit code and the end of its stderr (it is stopped first)."""
        if not self._stop.alive:
            return "the odometry worker was closed"
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._process.wait(STOP_GRACE_S)  # a dying child: let it finish writing why
        self._stderr.seek(0)
        said = self._stderr.read().decode(errors="replace").strip()[-STDERR_TAIL:]
        self.close()
        return f"the odometry worker process stopped (exit code {self._process.returncode})" + (
            f": {said}" if said else "")


def _stop_worker(process: subprocess.Popen[bytes], stderr: IO[bytes]) -> None:
    for pipe in (process.stdin, process.stdout):
        if pipe is not None:
            with contextlib.suppress(OSError):  # a child that died left a broken pipe: nothing to flush
                pipe.close()
    try:
        process.wait(STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    stderr.close()
