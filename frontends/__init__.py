"""Frontends: read laser and LiDAR logs (MCAP, ROS 1 bags, ROS 2 bags) into typed, time-ordered streams.

`open_log(path)` picks the container from the path and its contents and returns a `LogReader`; its
`info()` reads the summary / index, and its iterators (`scans`, `clouds`, `odometry`, `transforms`,
`messages`) stream `Scan2D`, `Cloud3D`, `OdometryPose` and `Transform` in sensor-time order.

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
    "LogReader": "frontends.log",
    "open_log": "frontends.log",
    "TransformTree": "frontends.transforms",
    "Cloud3D": "frontends.types",
    "LogInfo": "frontends.types",
    "OdometryPose": "frontends.types",
    "Scan2D": "frontends.types",
    "TopicInfo": "frontends.types",
    "Transform": "frontends.types",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'frontends' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
