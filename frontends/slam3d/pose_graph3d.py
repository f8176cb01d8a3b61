"""A full SE(3) polish of the keyframe graph after the planar SGD: what fixes height, roll and pitch drift.

The backend (the paper's SGD) optimizes x, y and yaw; `planar.lift` keeps every keyframe's height, roll
and pitch from the odometry, so a loop that comes back to its start 0.5 m "higher" stays 0.5 m off even
though the loop closure measured it. This module finishes the job in SE(3): Levenberg–Marquardt on the
same constraints (the 4×4 relative transforms and 6×6 information the frontend made), started from the
lifted planar optimum, so it only has to move the few degrees of freedom the plane did not see and
converges in a handful of iterations. The SGD stays the first stage: it is what survives poor starts.

Error of a constraint a → b measuring Z: e = log(Z⁻¹ T_a⁻¹ T_b) ∈ R⁶ (tx, ty, tz, rx, ry, rz: the
frontend's information order), poses perturbed on the right, T ← T·exp(δ). Jacobians:
∂e/∂δ_b = J_r⁻¹(e), ∂e/∂δ_a = −J_r⁻¹(e)·Ad(T_b⁻¹ T_a), with J_r⁻¹(e) ≈ I + ½ ad(e) (exact to second
order; residuals at the lifted optimum are small). The first keyframe is held fixed (the gauge).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.sparse.linalg import spsolve

from frontends.errors import FrontendError
from frontends.slam3d import se3

FloatArray = NDArray[np.float64]

DOF = 6
INITIAL_DAMPING = 1e-6
MAX_DAMPING = 1e8


@dataclass(frozen=True, eq=False)
class PolishResult:
    poses: FloatArray
    """(K, 4, 4) polished keyframe poses."""
    chi2_before: float
    chi2_after: float
    iterations: int
    converged: bool
    """The relative χ² decrease fell below the tolerance (False: stopped at the iteration limit or when
    no damping made progress)."""


def hat(vectors: FloatArray) -> FloatArray:
    """(..., 3, 3) skew-symmetric matrices of (..., 3) vectors."""
    out = np.zeros((*vectors.shape[:-1], 3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -z, y, -x
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = z, -y, x
    return out


def _so3_terms(omega: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """sin θ/θ, (1 − cos θ)/θ², (1 − sin θ/θ)/θ² for (...,) rotation vectors (Taylor near 0)."""
    theta2 = np.sum(omega * omega, axis=-1)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (1.0 - a) / safe**2)
    return a, b, c


def exp_many(tangents: ArrayLike) -> FloatArray:
    """(..., 4, 4) SE(3) exponentials of (..., 6) tangents (tx, ty, tz, rx, ry, rz)."""
    tangents = np.asarray(tangents, dtype=np.float64)
    omega = tangents[..., 3:]
    a, b, c = _so3_terms(omega)
    skew = hat(omega)
    skew2 = skew @ skew
    eye = np.eye(3)
    rotation = eye + a[..., None, None] * skew + b[..., None, None] * skew2
    v = eye + b[..., None, None] * skew + c[..., None, None] * skew2
    return se3.from_rotation_translation(rotation, np.einsum("...ij,...j->...i", v, tangents[..., :3]))


def log_many(transforms: ArrayLike) -> FloatArray:
    """(..., 6) SE(3) logarithms of (..., 4, 4) transforms (rotations below π)."""
    transforms = np.asarray(transforms, dtype=np.float64)
    rotation = transforms[..., :3, :3]
    theta = se3.rotation_angle(transforms)
    vee = np.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        axis=-1,
    )
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    scale = np.where(small, 0.5 + theta**2 / 12.0, safe / (2.0 * np.sin(safe)))
    omega = scale[..., None] * vee
    _, b, c = _so3_terms(omega)
    skew = hat(omega)
    v = np.eye(3) + b[..., None, None] * skew + c[..., None, None] * (skew @ skew)
    translation = np.linalg.solve(v, transforms[..., :3, 3:4])[..., 0]
    return np.concatenate([translation, omega], axis=-1)


def adjoint(transforms: FloatArray) -> FloatArray:
    """(..., 6, 6) adjoints in (translation, rotation) order: [[R, t^ R], [0, R]]."""
    rotation = transforms[..., :3, :3]
    out = np.zeros((*transforms.shape[:-2], DOF, DOF))
    out[..., :3, :3] = rotation
    out[..., 3:, 3:] = rotation
    out[..., :3, 3:] = hat(transforms[..., :3, 3]) @ rotation
    return out


def _inverse_right_jacobian(errors: FloatArray) -> FloatArray:
    """I + ½ ad(e), ad(ρ, φ) = [[φ^, ρ^], [0, φ^]]: J_r⁻¹ to second order."""
    ad = np.zeros((len(errors), DOF, DOF))
    rotation_hat = hat(errors[:, 3:])
    ad[:, :3, :3] = rotation_hat
    ad[:, 3:, 3:] = rotation_hat
    ad[:, :3, 3:] = hat(errors[:, :3])
    return np.eye(DOF) + 0.5 * ad


def residuals(
    poses: FloatArray, edge_from: NDArray[np.int64], edge_to: NDArray[np.int64], relative: FloatArray
) -> FloatArray:
    """(M, 6) errors log(Z⁻¹ T_a⁻¹ T_b) of every constraint at (K, 4, 4) `poses`."""
    return log_many(se3.inverse(relative) @ se3.inverse(poses[edge_from]) @ poses[edge_to])


def chi2(
    poses: ArrayLike, edge_from: ArrayLike, edge_to: ArrayLike, relative: ArrayLike, information: ArrayLike
) -> float:
    """Σ eᵀ Ω e over the constraints."""
    errors = residuals(
        np.asarray(poses, dtype=np.float64),
        np.asarray(edge_from, dtype=np.int64),
        np.asarray(edge_to, dtype=np.int64),
        np.asarray(relative, dtype=np.float64),
    )
    return float(np.einsum("mi,mij,mj->", errors, np.asarray(information, dtype=np.float64), errors))


def _normal_equations(
    poses: FloatArray,
    edge_from: NDArray[np.int64],
    edge_to: NDArray[np.int64],
    relative: FloatArray,
    information: FloatArray,
) -> tuple[sp.csr_matrix, FloatArray, float]:
    errors = residuals(poses, edge_from, edge_to, relative)
    jr_inverse = _inverse_right_jacobian(errors)
    jacobian_to = jr_inverse
    jacobian_from = -jr_inverse @ adjoint(se3.inverse(poses[edge_to]) @ poses[edge_from])
    weighted_error = np.einsum("mij,mj->mi", information, errors)
    count = len(poses)
    gradient = np.zeros((count, DOF))
    np.add.at(gradient, edge_from, np.einsum("mji,mj->mi", jacobian_from, weighted_error))
    np.add.at(gradient, edge_to, np.einsum("mji,mj->mi", jacobian_to, weighted_error))
    blocks, block_rows, block_cols = [], [], []
    for left, left_index in ((jacobian_from, edge_from), (jacobian_to, edge_to)):
        for right, right_index in ((jacobian_from, edge_from), (jacobian_to, edge_to)):
            blocks.append(np.einsum("mki,mkl,mlj->mij", left, information, right))
            block_rows.append(left_index)
            block_cols.append(right_index)
    values = np.concatenate(blocks)  # (4M, 6, 6)
    rows = DOF * np.concatenate(block_rows)[:, None, None] + np.arange(DOF)[None, :, None]
    cols = DOF * np.concatenate(block_cols)[:, None, None] + np.arange(DOF)[None, None, :]
    size = DOF * count
    hessian = sp.coo_matrix(
        (
            values.ravel(),
            (np.broadcast_to(rows, values.shape).ravel(), np.broadcast_to(cols, values.shape).ravel()),
        ),
        shape=(size, size),
    ).tocsr()
    total = float(np.einsum("mi,mi->", errors, weighted_error))
    return hessian, gradient.ravel(), total


def polish(
    poses: ArrayLike,
    edge_from: ArrayLike,
    edge_to: ArrayLike,
    relative: ArrayLike,
    information: ArrayLike,
    *,
    max_iterations: int = 20,
    tolerance: float = 1e-6,
) -> PolishResult:
    """Levenberg–Marquardt on SE(3) from (K, 4, 4) `poses` over constraints `edge_from` → `edge_to`
    measuring `relative` (M, 4, 4) with `information` (M, 6, 6); keyframe 0 fixed. Raises
    `FrontendError` on arrays that do not fit together or poses that are not finite."""
    current = np.array(poses, dtype=np.float64)
    first = np.asarray(edge_from, dtype=np.int64)
    second = np.asarray(edge_to, dtype=np.int64)
    measured = np.asarray(relative, dtype=np.float64)
    weights = np.asarray(information, dtype=np.float64)
    count = len(current)
    if current.shape[1:] != (4, 4) or not np.all(np.isfinite(current)):
        raise FrontendError(f"SE(3) polish needs finite (K, 4, 4) poses, got shape {current.shape}")
    if not (len(first) == len(second) == len(measured) == len(weights)):
        raise FrontendError("SE(3) polish: constraint arrays differ in length")
    if len(first) and (min(first.min(), second.min()) < 0 or max(first.max(), second.max()) >= count):
        raise FrontendError("SE(3) polish: a constraint names a keyframe that does not exist")
    before = chi2(current, first, second, measured, weights)
    if count < 2 or len(first) == 0:
        return PolishResult(current, before, before, 0, True)
    total = before
    damping = INITIAL_DAMPING
    free = slice(DOF, None)  # keyframe 0 is the gauge
    iterations = 0
    converged = False
    while iterations < max_iterations and not converged:
        iterations += 1
        hessian, gradient, total = _normal_equations(current, first, second, measured, weights)
        reduced = hessian[free, free].tocsc()
        diagonal = sp.diags(reduced.diagonal())
        improved = False
        while damping <= MAX_DAMPING:
            step = spsolve(reduced + damping * diagonal, -gradient[free])
            candidate = current.copy()
            candidate[1:] = current[1:] @ exp_many(step.reshape(-1, DOF))
            trial = chi2(candidate, first, second, measured, weights)
            if np.isfinite(trial) and trial <= total:
                improved = True
                converged = total - trial <= tolerance * max(total, 1e-12)
                current, total = candidate, trial
                damping = max(damping / 10.0, INITIAL_DAMPING)
                break
            damping *= 10.0
        if not improved:
            break
    return PolishResult(current, before, total, iterations, converged)
