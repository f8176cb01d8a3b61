"""A scan sliding along a curved wall: the free direction couples a shift along the wall with a turn.

Along a straight featureless wall the scan fits anywhere along it at the same heading, and the plateau test
(`match_covariance.score_plateau`) hands that direction to the wheel odometry. Along a wall bending as an arc
the scan fits anywhere along a rotation about the arc's centre: at a fixed heading its score is sharp, so
the slide went unseen and the frontend followed the scan matcher's drift (metres along, degrees in heading).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.match_covariance import COUPLED_SHARE, heading_coupling
from frontends.slam2d.slam import LaserSlam2D
from tests.laser_world import align_to_first, between, simulate_scan, wheel_odometry

ARC_RADIUS = 15.0
WALL_OFFSET = 1.5
"""The robot drives inside the arc, this far (m) from the wall; nothing else is in range."""
STEP = 0.2
LENGTH = 60.0


def arc_drive(seed: int) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """True poses, scans (a 270° laser, 541 beams, 15 m, 1 cm noise) and wheel odometry (1 % noise,
    0.5 % scale error) of a drive along the inside of a circular wall of `ARC_RADIUS`."""
    rng = np.random.default_rng(seed)
    along_wall = np.arange(-15.0, LENGTH + 15.0 + 1e-9, 0.5)
    angles = along_wall / ARC_RADIUS
    wall = np.column_stack([ARC_RADIUS * np.sin(angles), ARC_RADIUS - ARC_RADIUS * np.cos(angles)])
    segments = np.column_stack([wall[:-1], wall[1:]])
    radius = ARC_RADIUS - WALL_OFFSET
    turned = np.arange(0.0, LENGTH + 1e-9, STEP) / radius
    truth = np.column_stack([radius * np.sin(turned), ARC_RADIUS - radius * np.cos(turned), turned])
    scans = [simulate_scan(segments, pose, beams=541, fov=math.radians(270.0), max_range=15.0,
                           range_noise=0.01, rng=rng) for pose in truth]
    odometry = wheel_odometry(truth, rng, linear_noise=0.01, angular_noise=0.002, scale_error=0.005,
                              heading_bias_per_metre=0.001)
    return truth, scans, odometry


@pytest.mark.parametrize("seed", [1, 2])
def test_a_drive_along_a_curved_wall_follows_the_wheels_along_it(seed: int) -> None:
    truth, scans, odometry = arc_drive(seed)
    slam = LaserSlam2D(Slam2DConfig().without_loop_closures())
    stamps = 1_700_000_000_000_000_000 + np.arange(len(truth), dtype=np.int64) * 200_000_000
    poses = np.array([slam.add_scan(int(stamp), scan, pose).pose
                      for stamp, scan, pose in zip(stamps, scans, odometry, strict=True)])
    end = between(truth[-1], align_to_first(poses, truth)[-1])
    # The wheels' 0.5 % scale error over 60 m is 0.3 m; the slide unseen was 1.3-1.9 m and 5-8°.
    assert abs(end[0]) < 0.5
    assert abs(math.degrees(end[2])) < 2.0


def test_the_coupled_test_runs_only_where_a_turning_shift_is_the_weak_one() -> None:
    # A scan pinned across x (1e4) and weakly along y (1e2); the heading couples to y.
    def information(cross_y: float) -> np.ndarray:
        return np.array([[1e4, 0.0, 0.0], [0.0, 1e2, cross_y], [0.0, cross_y, 1e3]])

    # Eliminating the heading leaves 1e2 - c²/1e3 along y: a turning shift weaker than a plain one by
    # more than COUPLED_SHARE only when c² > (1 - COUPLED_SHARE) · 1e5.
    strong = math.sqrt((1.0 - COUPLED_SHARE) * 1e5)
    coupled = heading_coupling(information(1.05 * strong))
    assert coupled == pytest.approx([0.0, -1.05 * strong / 1e3])
    assert np.all(heading_coupling(information(0.95 * strong)) == 0.0)
    assert np.all(heading_coupling(information(0.0)) == 0.0)  # a straight wall: no turn with the shift
