"""The SE(3) polish of the keyframe graph: exact on consistent graphs, and it removes height drift."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.errors import FrontendError
from frontends.slam3d import planar, se3
from frontends.slam3d.pose_graph3d import chi2, exp_many, log_many, polish


def _random_poses(rng: np.random.Generator, count: int, spread: float) -> np.ndarray:
    rotation = Rotation.from_rotvec(rng.normal(0.0, 0.4, (count, 3))).as_matrix()
    return se3.from_rotation_translation(rotation, rng.normal(0.0, spread, (count, 3)))


def test_exp_and_log_agree_with_scipy_rotations() -> None:
    rng = np.random.default_rng(1)
    tangents = np.concatenate([rng.normal(0, 2, (50, 3)), rng.normal(0, 0.8, (50, 3))], axis=1)
    tangents[0, 3:] = 0.0  # no rotation
    tangents[1, 3:] = 1e-7  # a tiny one
    transforms = exp_many(tangents)
    np.testing.assert_allclose(
        transforms[:, :3, :3], Rotation.from_rotvec(tangents[:, 3:]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(log_many(transforms), tangents, atol=1e-9)
    # the translation of exp(ρ, 0) is ρ itself; a pure rotation has none
    np.testing.assert_allclose(transforms[0, :3, 3], tangents[0, :3], atol=1e-15)


def _ring(count: int, radius: float) -> np.ndarray:
    """Poses on a flat circle, heading along it."""
    angle = 2.0 * math.pi * np.arange(count) / count
    rotation = Rotation.from_euler("z", (angle + math.pi / 2)[:, None]).as_matrix()
    position = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(count)], axis=1)
    return se3.from_rotation_translation(rotation, position)


def _graph(truth: np.ndarray, pairs: list[tuple[int, int]]) -> tuple[np.ndarray, ...]:
    first = np.array([a for a, _ in pairs])
    second = np.array([b for _, b in pairs])
    relative = se3.inverse(truth[first]) @ truth[second]
    information = np.broadcast_to(np.diag([100.0] * 3 + [1000.0] * 3), (len(pairs), 6, 6)).copy()
    return first, second, relative, information


def test_a_consistent_graph_is_solved_exactly_from_a_perturbed_start() -> None:
    rng = np.random.default_rng(7)
    truth = _random_poses(rng, 12, 5.0)
    pairs = [(k, k + 1) for k in range(11)] + [(0, 6), (3, 11), (9, 2)]  # one stored "reversed"
    first, second, relative, information = _graph(truth, pairs)
    noise = exp_many(np.concatenate([rng.normal(0, 0.3, (12, 3)), rng.normal(0, 0.05, (12, 3))], axis=1))
    start = truth @ noise
    start[0] = truth[0]
    result = polish(start, first, second, relative, information)
    assert result.chi2_before > 100.0
    assert result.chi2_after < 1e-12 and result.converged
    np.testing.assert_allclose(result.poses, truth, atol=1e-7)


def test_the_loop_closure_takes_out_the_height_drift() -> None:
    count = 60
    truth = _ring(count, 30.0)
    pairs = [(k, k + 1) for k in range(count - 1)]
    first, second, relative, information = _graph(truth, pairs)
    # the odometry climbs: 1.5 cm and 0.03° of pitch per step (a 1.2 m error after the loop)
    climb = se3.from_rotation_translation(
        Rotation.from_euler("y", -0.03, degrees=True).as_matrix(), [0, 0, 0.015]
    )
    drifting = relative @ climb
    chain = [np.eye(4)]
    for step in drifting:
        chain.append(chain[-1] @ step)
    chain = truth[0] @ np.array(chain)
    # the loop closure (last keyframe seen from the first) measures the true relation
    loop_first, loop_second, loop_relative, loop_information = _graph(truth, [(0, count - 1)])
    first = np.concatenate([first, loop_first])
    second = np.concatenate([second, loop_second])
    relative = np.concatenate([drifting, loop_relative])
    information = np.concatenate([information, loop_information])
    # what the planar stage gives: x, y, yaw right, height, roll, pitch from the odometry
    lifted = planar.lift(planar.planar(truth), chain)
    assert abs(lifted[-1, 2, 3]) > 0.8
    result = polish(lifted, first, second, relative, information)
    assert result.chi2_after < 0.05 * result.chi2_before
    heights = result.poses[:, 2, 3]
    # the drift is spread over the loop: both ends agree with the loop closure, the middle at most half
    assert abs(heights[-1]) < 0.05
    assert np.abs(heights).max() < 0.6 * abs(lifted[-1, 2, 3])
    assert chi2(result.poses, first, second, relative, information) == pytest.approx(result.chi2_after)
    # the plane is not disturbed
    planar_error = np.abs(planar.planar(result.poses)[:, :2] - planar.planar(truth)[:, :2]).max()
    assert planar_error < 0.1


def test_no_constraints_no_change_and_bad_input_is_refused() -> None:
    poses = _ring(3, 1.0)
    empty = np.zeros((0, 4, 4))
    result = polish(poses, [], [], empty, np.zeros((0, 6, 6)))
    np.testing.assert_array_equal(result.poses, poses)
    with pytest.raises(FrontendError, match="does not exist"):
        polish(poses, [0], [3], np.eye(4)[None], np.eye(6)[None])
    bad = poses.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(FrontendError, match="finite"):
        polish(bad, [0], [1], np.eye(4)[None], np.eye(6)[None])
