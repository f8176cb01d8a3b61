"""LaserSlam2D run end to end on a simulated drive (tests/laser_world.py), and what the tests ask of the
outcome: every scan's final pose, its error against the ground truth, the loop closures that disagree
with it."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from frontends.slam2d.config import Slam2DConfig
from frontends.slam2d.slam import LaserSlam2D, ScanEstimate, Slam2DGraph
from optimizer.solve import optimize
from tests.laser_world import Run, align_to_first, between


@dataclass(frozen=True, eq=False)
class Outcome:
    run: Run
    estimates: list[ScanEstimate]
    result: Slam2DGraph
    final_scan_poses: np.ndarray
    """Every scan's pose from the optimized keyframe graph."""


def run_slam(run: Run, *, with_odometry: bool, config: Slam2DConfig | None = None) -> Outcome:
    slam = LaserSlam2D(config)
    estimates = [slam.add_scan(int(stamp), scan, odometry if with_odometry else None)
                 for stamp, scan, odometry in zip(run.stamps_ns, run.scans, run.odometry, strict=True)]
    result = slam.finish()
    *_, final = optimize(result.graph)
    return Outcome(run, estimates, result, result.scan_poses(final.poses))


def position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    aligned = align_to_first(poses, truth)
    return np.hypot(aligned[:, 0] - truth[:, 0], aligned[:, 1] - truth[:, 1])


def heading_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    aligned = align_to_first(poses, truth)
    return np.abs((aligned[:, 2] - truth[:, 2] + np.pi) % (2.0 * np.pi) - np.pi)


def wrong_loop_closures(outcome: Outcome, linear: float = 0.2,
                        angular: float = math.radians(2.0)) -> list[str]:
    """Loop-closure constraints of the final graph that disagree with the ground truth."""
    result, truth = outcome.result, outcome.run.truth
    # A keyframe is the scan that created it: the first scan hanging off it.
    keyframe_truth = truth[np.searchsorted(result.scan_keyframes, np.arange(len(result.graph.poses)))]
    graph = result.graph
    wrong = []
    for a, b, z in zip(graph.edge_from, graph.edge_to, graph.measurements, strict=True):
        if b - a == 1:  # consecutive keyframes: the odometry chain
            continue
        error = between(between(keyframe_truth[a], keyframe_truth[b]), z)
        if np.hypot(error[0], error[1]) > linear or abs(error[2]) > angular:
            wrong.append(f"{a}→{b}: off by ({error[0]:+.2f} m, {error[1]:+.2f} m, "
                         f"{math.degrees(error[2]):+.1f}°)")
    return wrong
