"""The pose-graph backend: the SGD of Olson, Leonard & Teller (2006), an exact-minimum polish, graph files.

Depends on numpy, scipy and numba only. Every optimizer yields an `Iteration` per iteration so callers can
record the whole optimization.

The names below are imported on first use, so that importing a light module (`optimizer.errors`,
`optimizer.jit_cache`) does not load numba.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import optimizer.jit_cache  # noqa: F401  (first: chooses numba's cache folder before numba is loaded)

if TYPE_CHECKING:
    from optimizer.cost import chi2
    from optimizer.errors import GraphError, GraphFileError, OptimizerError
    from optimizer.graph import PoseGraph
    from optimizer.iteration import Iteration

__all__ = ["GraphError", "GraphFileError", "Iteration", "OptimizerError", "PoseGraph", "chi2"]

_EXPORTS = {"chi2": "optimizer.cost", "GraphError": "optimizer.errors", "GraphFileError": "optimizer.errors",
            "OptimizerError": "optimizer.errors", "PoseGraph": "optimizer.graph",
            "Iteration": "optimizer.iteration"}


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'optimizer' has no attribute {name!r}")
