"""PnP on correspondences (worker/align/pnp.py): synthetic 3D points projected by a known pose
through a skewed camera with fx ≠ fy; the pose is recovered from a guess degrees off, through
outliers, and too few or inconsistent correspondences give no pose."""

from __future__ import annotations

import numpy as np
import pytest

from worker.align.pnp import PNP_MIN_INLIERS, solve_pnp
from worker.engine.camera import PinholeCamera
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import axis_angle_to_matrix

CAMERA = PinholeCamera(160, 120, 180.0, 190.0, 82.0, 57.0, skew=1.5)
R_TRUE = axis_angle_to_matrix(np.array([0.3, -0.8, 0.5]), np.radians(35.0))
T_TRUE = np.array([0.2, -0.1, 6.0])


def points(n: int = 40, seed: int = 0) -> np.ndarray:
    """Model points in a 2 × 2 × 1 box around the origin."""
    return np.random.default_rng(seed).uniform([-1, -1, -0.5], [1, 1, 0.5], size=(n, 3))


def project(X: np.ndarray) -> np.ndarray:
    return CAMERA.project(X @ R_TRUE.T + T_TRUE)


def guess(deg: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """The truth turned ``deg`` degrees and moved about 5 % of the range."""
    turn = axis_angle_to_matrix(np.array([1.0, 1.0, 0.0]), np.radians(deg))
    return R_TRUE @ turn, T_TRUE + np.array([0.1, 0.05, 0.3])


def test_recovers_the_pose_from_exact_correspondences() -> None:
    X = points()
    res = solve_pnp(CAMERA, X, project(X), *guess())
    assert res is not None
    assert rotation_error_deg(R_TRUE, res.R) < 1e-4
    np.testing.assert_allclose(res.t, T_TRUE, atol=1e-5)
    assert res.inliers.all() and res.rms_px < 1e-3


def test_recovers_the_pose_through_noise_and_outliers() -> None:
    rng = np.random.default_rng(1)
    X = points(60, seed=1)
    uv = project(X) + rng.normal(scale=0.3, size=(60, 2))
    bad = rng.choice(60, 12, replace=False)
    uv[bad] += rng.uniform(15.0, 40.0, size=(12, 2)) * rng.choice([-1, 1], size=(12, 2))
    res = solve_pnp(CAMERA, X, uv, *guess(), seed=3)
    assert res is not None
    assert rotation_error_deg(R_TRUE, res.R) < 0.3
    assert np.linalg.norm(res.t - T_TRUE) / np.linalg.norm(T_TRUE) < 0.005
    assert not res.inliers[bad].any() and res.inliers.sum() >= 45
    assert res.rms_px == pytest.approx(0.3, rel=0.5)


def test_too_few_or_inconsistent_correspondences_give_no_pose() -> None:
    X = points()
    few = PNP_MIN_INLIERS - 1
    assert solve_pnp(CAMERA, X[:few], project(X[:few]), *guess()) is None
    rng = np.random.default_rng(2)
    scrambled = rng.uniform([0, 0], [160, 120], size=(len(X), 2))
    assert solve_pnp(CAMERA, X, scrambled, *guess()) is None
