"""Pose error metrics of the paper and the SPEED score."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from worker.engine.posemath import matrix_to_quaternion


def rotation_error_deg(R_true: ArrayLike, R_est: ArrayLike) -> float:
    """∠ΔR = arccos((tr(Rᵀ R̂) − 1) / 2) in degrees (computed stably through the quaternion)."""
    dR = np.asarray(R_true, dtype=np.float64).T @ np.asarray(R_est, dtype=np.float64)
    quat = matrix_to_quaternion(dR)
    # 2·atan2(‖v‖, |w|), not 2·arccos|w|: arccos is as ill-conditioned near 1 as the trace form.
    return float(np.degrees(2.0 * np.arctan2(np.linalg.norm(quat[1:]), abs(quat[0]))))


def translation_error(t_true: ArrayLike, t_est: ArrayLike) -> float:
    """‖t − t̂‖₂ in scene units."""
    return float(np.linalg.norm(np.asarray(t_true, float) - np.asarray(t_est, float)))


def speed_score(R_true: ArrayLike, t_true: ArrayLike, R_est: ArrayLike, t_est: ArrayLike) -> float:
    """SPEED score ‖t − t̂‖/‖t‖ + 2·arccos|⟨q̂, q⟩| (radians, unit quaternions)."""
    q_true = matrix_to_quaternion(R_true)
    q_est = matrix_to_quaternion(R_est)
    dot = min(1.0, abs(float(q_true @ q_est)))
    t_true = np.asarray(t_true, dtype=np.float64)
    return translation_error(t_true, t_est) / float(np.linalg.norm(t_true)) + 2.0 * np.arccos(dot)
