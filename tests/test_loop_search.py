"""The loop-search settings both SLAM frontends inherit (`frontends.loop_search`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from frontends.slam2d.config import LoopClosureConfig as LaserLoopClosureConfig
from frontends.slam3d.config import LoopClosureConfig as LidarLoopClosureConfig


def test_the_search_radius_grows_with_the_path_and_stops_at_its_cap() -> None:
    settings = LidarLoopClosureConfig(search_radius=4.0, search_radius_per_metre=0.1, max_search_radius=9.0)
    radii = settings.search_radii(np.array([0.0, 20.0, 50.0, 500.0]))
    np.testing.assert_allclose(radii, [4.0, 6.0, 9.0, 9.0])  # 4 + 0.1 × path, at most 9


def test_each_frontend_keeps_its_own_radii_and_its_keys_in_their_order() -> None:
    # The keys' order is that of every configuration file and `replay --dump-config` written before the
    # settings were shared: inheriting them must not move them to the top of a section.
    laser, lidar = LaserLoopClosureConfig(), LidarLoopClosureConfig()
    assert (laser.search_radius, laser.max_search_radius) == (2.0, 30.0)
    assert (lidar.search_radius, lidar.max_search_radius) == (5.0, 30.0)
    assert [f.name for f in dataclasses.fields(laser)][:5] == [
        "enabled", "search_radius", "search_radius_per_metre", "max_search_radius",
        "min_separation_keyframes",
    ]
    assert [f.name for f in dataclasses.fields(lidar)][:7] == [
        "enabled", "every_keyframes", "min_travel", "search_radius", "search_radius_per_metre",
        "max_search_radius", "candidates_per_keyframe",
    ]
