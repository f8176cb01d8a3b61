"""SE(3) helpers and the ground-vehicle projection of the 3D keyframe graph onto the planar backend."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.slam3d import planar, se3
from optimizer.cost import chi2


def transform(yaw: float, pitch: float, roll: float, translation: tuple[float, float, float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    out[:3, 3] = translation
    return out


def test_exp_and_log_are_inverse_and_exp_of_a_pure_rotation_rotates() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        tangent = np.concatenate([rng.normal(0, 2, 3), rng.normal(0, 0.8, 3)])
        np.testing.assert_allclose(se3.log(se3.exp(tangent)), tangent, atol=1e-9)
    quarter_turn = se3.exp([0, 0, 0, 0, 0, math.pi / 2])
    np.testing.assert_allclose(quarter_turn[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # screw motion: a quarter turn while moving 1 along the tangent ends on the arc of radius 2/π
    arc = se3.exp([1, 0, 0, 0, 0, math.pi / 2])
    np.testing.assert_allclose(arc[:3, 3], [2 / math.pi, 2 / math.pi, 0], atol=1e-12)


def test_inverse_relative_and_rotation_angle() -> None:
    a = transform(0.3, 0.1, -0.2, (1, 2, 3))
    b = transform(-1.0, 0.05, 0.0, (4, -1, 0.5))
    np.testing.assert_allclose(se3.inverse(a) @ a, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(a @ se3.relative(a, b), b, atol=1e-12)
    np.testing.assert_allclose(se3.rotation_angle(transform(0.7, 0, 0, (0, 0, 0))), 0.7)


def test_planar_pose_is_the_zyx_yaw_and_lift_keeps_height_roll_and_pitch() -> None:
    pose = transform(2.5, 0.2, -0.1, (3.0, -4.0, 1.5))
    np.testing.assert_allclose(planar.planar(pose), [3.0, -4.0, 2.5])
    lifted = planar.lift(np.array([[10.0, 20.0, -1.0]]), pose[None])[0]
    expected = transform(-1.0, 0.2, -0.1, (10.0, 20.0, 1.5))  # yaw replaced, pitch and roll kept
    np.testing.assert_allclose(lifted, expected, atol=1e-12)
    np.testing.assert_allclose(planar.lift(planar.planar(pose), pose), pose, atol=1e-12)


def test_planar_measurement_of_odometry_is_the_relative_planar_pose() -> None:
    a = transform(0.4, 0.05, 0.02, (1.0, 2.0, 0.3))
    b = transform(1.1, -0.03, 0.04, (3.0, 3.5, 0.5))
    measurement, _ = planar.project_constraints(a[None], se3.relative(a, b)[None], np.eye(6)[None])
    # b seen from a in the plane: rotate the position difference by −yaw_a
    c, s = math.cos(0.4), math.sin(0.4)
    dx, dy = 2.0, 1.5
    np.testing.assert_allclose(measurement[0], [c * dx + s * dy, -s * dx + c * dy, 0.7], atol=1e-12)


def test_a_step_along_a_pitched_frame_counts_only_its_horizontal_part() -> None:
    pitch = math.radians(10.0)
    a = transform(0.0, pitch, 0.0, (0, 0, 0))
    one_metre_ahead = transform(0.0, 0.0, 0.0, (1.0, 0.0, 0.0))  # along a's own (pitched) x axis
    measurement, _ = planar.project_constraints(a[None], one_metre_ahead[None], np.eye(6)[None])
    np.testing.assert_allclose(measurement[0], [math.cos(pitch), 0.0, 0.0], atol=1e-12)


def test_planar_information_is_the_marginal_of_x_y_and_yaw() -> None:
    rng = np.random.default_rng(0)
    root = rng.normal(size=(6, 6))
    information = root @ root.T + 6 * np.eye(6)
    _, projected = planar.project_constraints(np.eye(4)[None], np.eye(4)[None], information[None])
    # Marginalising in information form: Schur complement of the eliminated block (z, roll, pitch).
    keep, drop = [0, 1, 5], [2, 3, 4]
    schur = information[np.ix_(keep, keep)] - information[np.ix_(keep, drop)] @ np.linalg.solve(
        information[np.ix_(drop, drop)], information[np.ix_(drop, keep)]
    )
    np.testing.assert_allclose(projected[0], schur, rtol=1e-10)


def test_project_graph_gives_the_backend_a_planar_graph() -> None:
    poses = np.stack([transform(0.1 * k, 0.01, 0.0, (k, 0.2 * k, 0.1)) for k in range(4)])
    edge_from, edge_to = np.array([0, 1, 2, 0]), np.array([1, 2, 3, 3])
    relative = se3.relative(poses[edge_from], poses[edge_to])
    information = np.tile(np.diag([100.0] * 3 + [1000.0] * 3), (4, 1, 1))
    graph = planar.project_graph(poses, edge_from, edge_to, relative, information)
    assert graph.num_poses == 4 and graph.num_edges == 4
    np.testing.assert_allclose(graph.poses, planar.planar(poses))
    assert chi2(graph) == pytest.approx(0.0, abs=1e-18)  # consistent measurements: zero error
