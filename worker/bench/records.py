"""Bench records: what one estimate of one case and method left, as plain JSON-ready data."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.estimate import EstimateResult


def failure(code: str, exc: Exception) -> dict[str, Any]:
    return {
        "failed": True,
        "error_code": code,
        "error": f"{type(exc).__name__}: {exc}",
        "rotation_deg": None,
        "rotation_vector_deg": None,
        "translation_pct": None,
        "range_error_pct": None,
        "translation": None,
        "speed_score": None,
        "iterations": None,
        "renders": None,
    }


def sigma_length(sigmas: Sequence[float]) -> float:
    """Per-axis 1-σ figures as one: the root of their sum of squares (the expected length of
    the error)."""
    return math.sqrt(sum(s * s for s in sigmas))


def _calibration(result: EstimateResult) -> dict[str, Any]:
    """The reported 1-σ (RMS over the axes: the expected size of the error) and how many σ the
    actual errors are."""
    cov, err = result.covariance, result.errors
    if cov is None or err is None:
        return {"sigma_rotation_deg": None, "sigma_translation": None,
                "rotation_sigmas": None, "translation_sigmas": None}  # fmt: skip
    s_rot = sigma_length(cov.sigma_rotation_deg)
    s_t = sigma_length(cov.sigma_translation)
    return {
        "sigma_rotation_deg": s_rot,
        "sigma_translation": s_t,
        "rotation_sigmas": err.rotation_deg / s_rot if s_rot > 0 else None,
        "translation_sigmas": err.translation / s_t if s_t > 0 else None,
    }


def rotation_vector_deg(R_est: NDArray[np.float64], R_true: NDArray[np.float64]) -> list[float]:
    """The rotation error R̂Rᵀ as a vector (axis × angle, degrees) in the camera frame: its
    length is ∠ΔR, and its direction tells a bias (the same for every estimator seed) from
    scatter (worker.bench.stats)."""
    from worker.engine.posemath import matrix_to_rotvec

    return [float(v) for v in np.degrees(matrix_to_rotvec(R_est @ R_true.T))]


def range_error_pct(t_est: NDArray[np.float64], t_true: NDArray[np.float64]) -> float:
    """The translation error along the true line of sight, % of the range, signed: > 0 when
    the estimate puts the target farther than it is. A sign that holds over a class's cases
    is a scale bias (the target's outline found too small or too large), which the
    translation error's size alone does not tell from scatter."""
    t_true = np.asarray(t_true, dtype=np.float64)
    return float(100.0 * (np.asarray(t_est) - t_true) @ t_true / (t_true @ t_true))


def outcome(
    result: EstimateResult, R_true: NDArray[np.float64], t_true: NDArray[np.float64]
) -> dict[str, Any]:
    """The record of an estimate that returned (``R_true``, ``t_true``: the case's true pose)."""
    from worker.engine.posemath import pose_from_schema

    err = result.errors
    assert err is not None  # every bench request carries the ground truth
    R_est, t_est = pose_from_schema(result.pose)
    return {
        "failed": False,
        "error_code": None,
        "error": None,
        "rotation_deg": err.rotation_deg,
        "rotation_vector_deg": rotation_vector_deg(R_est, R_true),
        "translation_pct": err.translation_pct_of_range,
        "range_error_pct": range_error_pct(t_est, t_true),
        "translation": err.translation,
        "speed_score": err.speed_score,
        "iterations": result.iterations,
        "renders": result.renders,
        "render_cost": result.render_cost,
        "engine_seconds": result.seconds,
        "converged": result.converged,
        "reason": result.reason,
        "features": result.features,
        "rms_residual_px": result.rms_residual_px,
        "alignment_score": result.alignment_score,
        "shading_normals": result.shading_normals,
        "reflectance_share": result.reflectance_share,
        "reflectance_roughness_deg": result.reflectance_roughness_deg,
        **_calibration(result),
        "timings_s": result.timings_s,
        "history": [
            {
                "stage": h.stage,
                "cost_px2": h.cost,
                "features": h.features,
                "renders": h.renders,
                "accepted": h.accepted,
                "seconds": h.seconds,
                "rotation_deg": h.rotation_error_deg,
                "translation": h.translation_error,
            }
            for h in result.history
        ],
    }
