"""`se2.wrap_angle`'s fast path (no call to fmod for angles near [-π, π)) against Python's float modulo."""

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
