"""Frontends: read robot logs and turn their scans into pose-graph constraints.

Three packages, each exporting its public names:
- `frontends.logs`: MCAP, ROS 1 and ROS 2 bags into typed, time-ordered streams (`open_log`).
- `frontends.slam2d`: 2D laser SLAM (scan matching, keyframes, loop closures) into a pose graph.
- `frontends.slam3d`: 3D LiDAR SLAM (KISS-ICP odometry, keyframes, loop closures) into a pose graph.
`frontends.errors` holds the exceptions all three raise.

The names below are imported on first use: `import frontends.errors` (what the CLI needs to report
errors) must not pay for the container readers and their decoders.
"""

from __future__ import annotations

import importlib
from typing import Any

import optimizer.jit_cache  # noqa: F401  (chooses numba's cache folder before any kernel is compiled)

_EXPORTS = {
    "FrontendError": "frontends.errors",
    "LogFileError": "frontends.errors",
    "LogWarning": "frontends.errors",
    "TopicSelectionError": "frontends.errors",
    "TransformLookupError": "frontends.errors",
    "UnusableLogError": "frontends.errors",
    "MapExtentError": "frontends.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'frontends' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
