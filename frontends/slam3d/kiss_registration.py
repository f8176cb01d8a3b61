"""KISS-ICP's registration of deskewed clouds, in this process or as a worker process's loop.

`KissRegistration` is the part of the odometry that holds KISS-ICP's state (its local map, adaptive
threshold, last pose and motion); everything around it (per-point times, deskewing, the pose at the
cloud's stamp: `odometry.SweepFrames`) stays with the SLAM. This module imports only numpy, KISS-ICP and
our settings, so that a worker process running it (`python -m frontends.slam3d.kiss_registration`, see
`odometry_worker`) starts in well under a second: no numba, no frontend.
"""

from __future__ import annotations

import pickle
import sys
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from frontends.slam3d.config import OdometryConfig

if TYPE_CHECKING:
    from kiss_icp.config import KISSConfig

FloatArray = NDArray[np.float64]

NO_TIMES = np.empty(0, dtype=np.float64)


def kiss_config(config: OdometryConfig) -> KISSConfig:
    """Our odometry settings as KISS-ICP's configuration, every field set explicitly."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )

    return KISSConfig(
        data=DataConfig(max_range=config.max_range, min_range=config.min_range, deskew=config.deskew),
        mapping=MappingConfig(
            voxel_size=config.map_voxel_size, max_points_per_voxel=config.max_points_per_voxel
        ),
        registration=RegistrationConfig(
            max_num_iterations=config.max_iterations,
            convergence_criterion=config.convergence_criterion,
            max_num_threads=config.max_threads,
        ),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=config.fixed_threshold,
            initial_threshold=config.initial_threshold,
            min_motion_th=config.min_motion_threshold,
        ),
    )


class KissRegistration:
    """KISS-ICP on clouds already deskewed (it only drops the points out of range)."""

    def __init__(self, config: OdometryConfig) -> None:
        # imported here: a process whose odometry runs in a worker never loads KISS-ICP's pydantic settings
        from kiss_icp.kiss_icp import KissICP

        self._kiss = KissICP(kiss_config(config))

    def register(self, frame: FloatArray, motion_guess: FloatArray | None
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Register (N, 3) float64 points, starting from `motion_guess` (4×4) instead of the constant
        velocity model when given: the points kept, the pose at the sweep's end and the motion from the
        previous registered cloud (4×4, what deskews the next)."""
        if motion_guess is not None:
            self._kiss.last_delta = np.array(motion_guess, dtype=np.float64)
        points, _ = self._kiss.register_frame(frame, NO_TIMES)
        return (np.asarray(points), np.array(self._kiss.last_pose, dtype=np.float64),
                np.array(self._kiss.last_delta, dtype=np.float64))


def serve(requests: IO[bytes], replies: IO[bytes]) -> None:
    """A worker's loop: an `OdometryConfig`, then (frame, motion guess) pickles until `requests` ends,
    each answered with ("registered", `KissRegistration.register`'s result) or, once, ("error", what)."""
    try:
        config = pickle.load(requests)
    except EOFError:
        return
    registration = KissRegistration(config)
    while True:
        try:
            frame, motion_guess = pickle.load(requests)
        except EOFError:
            return
        reply: tuple[str, Any]
        try:
            reply = ("registered", registration.register(frame, motion_guess))
        except Exception as error:  # reported to the parent, which raises it as an OdometryWorkerError
            reply = ("error", f"{type(error).__name__}: {error}")
        try:
            pickle.dump(reply, replies, protocol=pickle.HIGHEST_PROTOCOL)
            replies.flush()
        except BrokenPipeError:  # the parent is gone, or closed us
            return
        if reply[0] == "error":
            return


if __name__ == "__main__":
    _requests, _replies = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing else may write into the replies
    serve(_requests, _replies)
