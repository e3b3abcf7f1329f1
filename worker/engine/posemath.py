"""Attitude parameterisations and pose composition.

Conventions (docs/method.md): a pose maps model coordinates to camera coordinates, ``b = R a + t``.
The Gibbs vector q (classical Rodrigues parameters) enters through the paper's Cayley transform

    R = (I + [q×])⁻¹ (I − [q×]) = ((1 − qᵀq) I + 2 q qᵀ − 2 [q×]) / (1 + qᵀq),

so R ≈ I − 2[q×] for small q: the paper's q is minus the "active" tan(θ/2)·axis. Quaternions are
[w, x, y, z], scalar first, of the active rotation R. Updates are local: R ← R·C(δq), t ← t + δt.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.pose import GIBBS_NORM_MAX, Pose, PoseOut
from worker.engine.exceptions import InvalidPoseError

Array = NDArray[np.float64]

#: 1 + tr R below this means θ is too near 180° for a Gibbs vector.
GIBBS_SINGULARITY_TOL = 1e-9


def _vec3(v: ArrayLike, name: str) -> Array:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise InvalidPoseError(f"{name} must have shape (3,), got {a.shape}")
    return a


def _mat3(M: ArrayLike, name: str = "R") -> Array:
    a = np.asarray(M, dtype=np.float64)
    if a.shape != (3, 3):
        raise InvalidPoseError(f"{name} must have shape (3, 3), got {a.shape}")
    return a


def skew(v: ArrayLike) -> Array:
    """The cross-product matrix [v×], shape (3, 3), such that [v×] w = v × w."""
    x, y, z = _vec3(v, "v")
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def vee(S: ArrayLike) -> Array:
    """Inverse of :func:`skew` for the skew-symmetric part of S, shape (3,)."""
    S = _mat3(S, "S")
    return 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])


def gibbs_to_matrix(q: ArrayLike) -> Array:
    """Cayley transform R = ((1 − qᵀq) I + 2 q qᵀ − 2 [q×]) / (1 + qᵀq), shape (3, 3)."""
    q = _vec3(q, "q")
    qq = float(q @ q)
    return ((1.0 - qq) * np.eye(3) + 2.0 * np.outer(q, q) - 2.0 * skew(q)) / (1.0 + qq)


def matrix_to_gibbs(R: ArrayLike) -> Array:
    """Inverse Cayley transform q = vee(Rᵀ − R) / (1 + tr R), shape (3,).

    Raises InvalidPoseError at 180°, where the Gibbs vector is infinite.
    """
    R = _mat3(R)
    denom = 1.0 + np.trace(R)
    if denom < GIBBS_SINGULARITY_TOL:
        raise InvalidPoseError("attitude is 180° from identity: the Gibbs vector is singular")
    return 2.0 * vee(R.T) / denom


def quaternion_to_matrix(quat: ArrayLike) -> Array:
    """Active rotation matrix of a quaternion [w, x, y, z] (normalised first), shape (3, 3)."""
    qv = np.asarray(quat, dtype=np.float64)
    if qv.shape != (4,):
        raise InvalidPoseError(f"quaternion must have shape (4,), got {qv.shape}")
    n = np.linalg.norm(qv)
    if not np.isfinite(n) or n < 1e-12:
        raise InvalidPoseError("quaternion must be finite and non-zero")
    w, x, y, z = qv / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(R: ArrayLike) -> Array:
    """Quaternion [w, x, y, z] with w ≥ 0 of a rotation matrix (Shepperd's method), shape (4,)."""
    R = _mat3(R)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    return quat if quat[0] >= 0 else -quat


def axis_angle_to_matrix(axis: ArrayLike, angle_rad: float) -> Array:
    """Active rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues' formula), (3, 3)."""
    a = _vec3(axis, "axis")
    n = np.linalg.norm(a)
    if n < 1e-12:
        return np.eye(3)
    K = skew(a / n)
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def rotvec_to_matrix(rotvec: ArrayLike) -> Array:
    """Active rotation for a rotation vector θ·axis (radians), shape (3, 3)."""
    v = _vec3(rotvec, "rotvec")
    angle = float(np.linalg.norm(v))
    return axis_angle_to_matrix(v, angle) if angle > 0 else np.eye(3)


def matrix_to_axis_angle(R: ArrayLike) -> tuple[Array, float]:
    """Unit axis (3,) and angle in [0, π] radians of a rotation matrix; accurate near 0 and π."""
    quat = matrix_to_quaternion(R)
    w, v = quat[0], quat[1:]
    s = np.linalg.norm(v)
    angle = 2.0 * np.arctan2(s, w)
    axis = v / s if s > 1e-15 else np.array([1.0, 0.0, 0.0])
    return axis, float(angle)


def matrix_to_rotvec(R: ArrayLike) -> Array:
    """Rotation vector θ·axis (radians) of a rotation matrix, shape (3,)."""
    axis, angle = matrix_to_axis_angle(R)
    return axis * angle


def orthonormalize(R: ArrayLike) -> Array:
    """The nearest proper rotation matrix to R (SVD), shape (3, 3)."""
    U, _, Vt = np.linalg.svd(_mat3(R))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def apply_increment(R: ArrayLike, t: ArrayLike, dp: ArrayLike) -> tuple[Array, Array]:
    """Apply a local pose increment dp = [δq, δt]: R ← R·C(δq), t ← t + δt.

    The signs are those of docs/method.md ("Signs").
    """
    dp = np.asarray(dp, dtype=np.float64)
    if dp.shape != (6,):
        raise InvalidPoseError(f"dp must have shape (6,), got {dp.shape}")
    return _mat3(R) @ gibbs_to_matrix(dp[:3]), _vec3(t, "t") + dp[3:]


def increment_between(R0: ArrayLike, t0: ArrayLike, R1: ArrayLike, t1: ArrayLike) -> Array:
    """The increment dp with apply_increment(R0, t0, dp) == (R1, t1): [gibbs(R0ᵀR1), t1 − t0]."""
    return np.concatenate([matrix_to_gibbs(_mat3(R0).T @ _mat3(R1)), _vec3(t1, "t1") - t0])


def step_norm(dp: ArrayLike, range_: float) -> float:
    """‖δp‖ in mixed units made dimensionless: [rotation angle (rad), δt / range]."""
    dp = np.asarray(dp, dtype=np.float64)
    angle = 2.0 * np.arctan(np.linalg.norm(dp[:3]))
    return float(np.hypot(angle, np.linalg.norm(dp[3:]) / range_))


def pose_from_schema(pose: Pose) -> tuple[Array, Array]:
    """(R, t) of a request pose, whichever attitude form it was given in."""
    if pose.R is not None:
        R = orthonormalize(pose.R)
    elif pose.quaternion is not None:
        R = quaternion_to_matrix(pose.quaternion)
    elif pose.q is not None:
        R = gibbs_to_matrix(pose.q)
    else:  # the schema forbids it; keep the engine honest
        raise InvalidPoseError("pose has no attitude")
    return R, np.asarray(pose.t, dtype=np.float64)


def pose_to_schema(R: ArrayLike, t: ArrayLike) -> PoseOut:
    """A pose in every form. q is reported as null-free: near 180° it is very large but finite
    (just under the schema's GIBBS_NORM_MAX, along the rotation axis)."""
    R = orthonormalize(R)
    denom = 1.0 + np.trace(R)
    if denom > GIBBS_SINGULARITY_TOL:
        q = 2.0 * vee(R.T) / denom
    else:  # vee(Rᵀ) → 0 at 180°: the quotient would lose q's length (and give 0 at 180°)
        axis, angle = matrix_to_axis_angle(R)
        q = -min(float(np.tan(0.5 * angle)), 0.999 * GIBBS_NORM_MAX) * axis
    return PoseOut(
        R=R.tolist(),
        q=q.tolist(),
        quaternion=matrix_to_quaternion(R).tolist(),
        t=_vec3(t, "t").tolist(),
    )
