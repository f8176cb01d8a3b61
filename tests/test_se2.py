"""`se2.wrap_angle`'s fast path (no call to fmod for angles near [-π, π)) against Python's float modulo;
`se2.rigid_fit` against known motions."""

from __future__ import annotations

import math

import numpy as np

from optimizer import se2


def _python_wrap(theta: float) -> float:
    return (theta + math.pi) % (2.0 * math.pi) - math.pi


def _angles() -> list[float]:
    """Random angles near and far, and the floats next to every boundary of the fast path's ranges."""
    rng = np.random.default_rng(7)
    angles = [*rng.uniform(-40.0, 40.0, 2000), *rng.normal(0.0, 1e-6, 200), 0.0, -0.0, 5e-324, -5e-324,
              1e300, -1e300, 1e17, math.inf, -math.inf, math.nan]
    for boundary in (-5 * math.pi, -3 * math.pi, -math.pi, math.pi, 3 * math.pi, 5 * math.pi):
        for direction in (-math.inf, math.inf):
            value = boundary
            for _ in range(40):
                angles.append(value)
                value = float(np.nextafter(value, direction))
    return angles


def test_wrap_angle_is_pythons_modulo_to_the_bit() -> None:
    angles = _angles()
    expected = np.array([_python_wrap(a) for a in angles])
    with np.errstate(invalid="ignore"):  # inf's modulo is NaN, as in Python
        got = se2.wrap_angle(np.array(angles))
    same = (expected.view(np.int64) == got.view(np.int64)) | (np.isnan(expected) & np.isnan(got))
    assert same.all(), [a for a, s in zip(angles, same, strict=True) if not s][:5]
    assert all(se2.wrap_angle(a) == _python_wrap(a) for a in angles[:50])


def test_one_pose_each_gives_the_array_codes_bits() -> None:
    """`compose` and `relative` of two single poses (the frontends' per-scan calls, on Python floats)
    against the same poses in arrays, angles at every wrap boundary and non-finite ones included."""
    rng = np.random.default_rng(11)
    angles = _angles()
    count = len(angles)
    a = np.column_stack([rng.uniform(-50.0, 50.0, (count, 2)), angles])
    b = np.column_stack([rng.uniform(-50.0, 50.0, (count, 2)), rng.permutation(angles)])
    b[:20, 2] = a[:20, 2]  # a pose seen from itself
    for operation in (se2.compose, se2.relative):
        with np.errstate(invalid="ignore"):
            together = operation(a, b)
            one_by_one = np.array([operation(p, q) for p, q in zip(a, b, strict=True)])
        same = ((together.view(np.int64) == one_by_one.view(np.int64))
                | (np.isnan(together) & np.isnan(one_by_one)))
        assert same.all(), f"{operation.__name__}: {np.argwhere(~same)[:3].tolist()}"
    # Other shapes and types still broadcast through the array code.
    assert se2.relative(np.array([0, 0, 0]), np.array([[1.0, 2.0, 0.5]])).shape == (1, 3)
    np.testing.assert_array_equal(se2.compose([1.0, 0.0, 0.0], [1.0, 0.0, 0.0]), [2.0, 0.0, 0.0])


def test_rigid_fit_recovers_the_motion_between_two_point_sets() -> None:
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-20, 20, (40, 2)), rng.uniform(-np.pi, np.pi, 40)])
    motion = np.array([3.5, -7.25, 2.9])  # beyond π/2: the angle's quadrant matters
    moved = se2.compose(motion, points)
    np.testing.assert_allclose(se2.rigid_fit(points, moved), motion, atol=1e-12)
    # Noise on the targets: the fit is the least-squares one, so no small turn or shift lowers the residual.
    noisy = moved + np.column_stack([rng.normal(0, 0.1, (40, 2)), np.zeros(40)])
    fit = se2.rigid_fit(points, noisy)

    def residual(pose: np.ndarray) -> float:
        return float(np.sum((se2.compose(pose, points)[:, :2] - noisy[:, :2]) ** 2))

    for step in np.eye(3) * 1e-4:
        assert residual(fit) < residual(fit + step) and residual(fit) < residual(fit - step)
