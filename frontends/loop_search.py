"""Loop-closure search settings the 2D and 3D SLAM frontends share: whether loops are searched, and how far.

Each frontend's `LoopClosureConfig` inherits them and sets its own radii. A dataclass lists its bases'
fields before its own, the base listed last first, and a field a subclass declares again keeps its place:
that keeps each `[slam2d.loop_closure]` / `[slam3d.loop_closure]` section's keys in their order (TOML,
`replay --dump-config`). A frontend whose keys come between `enabled` and the radius names a base holding
them after `LoopSearchRadius`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class LoopClosureSwitch:
    enabled: bool = True
    """Search for loop closures at all (False: the map is odometry and matching alone)."""


@dataclass(frozen=True, kw_only=True)
class LoopSearchRadius:
    """Candidates are searched within a radius that grows with the drift between two keyframes."""

    search_radius: float
    """Candidates are keyframes within this distance of the current estimate (m) …"""
    search_radius_per_metre: float = 0.05
    """… plus this much per metre of the shortest path joining the two in the graph (the drift grows)."""
    max_search_radius: float

    def search_radii(self, path_lengths: NDArray[np.float64]) -> NDArray[np.float64]:
        """The search radius (m) around keyframes `path_lengths` (m) away along the graph's shortest paths."""
        return np.minimum(
            self.search_radius + self.search_radius_per_metre * path_lengths, self.max_search_radius
        )
