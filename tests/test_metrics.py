"""Pose error metrics (worker/engine/metrics.py): the paper's ∠ΔR and ‖Δt‖, and the SPEED score."""

from __future__ import annotations

import numpy as np
import pytest

from worker.engine.metrics import rotation_error_deg, speed_score, translation_error
from worker.engine.posemath import axis_angle_to_matrix, quaternion_to_matrix


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quaternion_to_matrix(q / np.linalg.norm(q))


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def test_rotation_error_equals_the_papers_arccos_formula() -> None:
    rng = np.random.default_rng(0)
    for _ in range(500):
        R, R_hat = _random_rotation(rng), _random_rotation(rng)
        c = np.clip((np.trace(R.T @ R_hat) - 1.0) / 2.0, -1.0, 1.0)
        expected = np.degrees(np.arccos(c))
        assert rotation_error_deg(R, R_hat) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("angle_deg", [1e-6, 1e-4, 0.01, 0.3, 10.0, 90.0, 179.0, 180.0])
def test_rotation_error_recovers_known_angles(angle_deg: float) -> None:
    """A known offset is recovered; at small angles far more precisely than arccos of the
    trace (which cannot resolve angles below ~1e-6 rad in float64)."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        R = _random_rotation(rng)
        R_hat = R @ axis_angle_to_matrix(_unit(rng), np.radians(angle_deg))
        assert rotation_error_deg(R, R_hat) == pytest.approx(angle_deg, rel=1e-6, abs=1e-9)
        assert rotation_error_deg(R_hat, R) == pytest.approx(angle_deg, rel=1e-6, abs=1e-9)


def test_arccos_form_really_is_inaccurate_at_small_angles() -> None:
    """Guards the previous test: the trace formula is off by far more than its tolerance."""
    R_hat = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.radians(1e-6))
    naive = np.degrees(np.arccos(np.clip((np.trace(R_hat) - 1.0) / 2.0, -1, 1)))
    assert abs(naive - 1e-6) > 1e-7


def test_rotation_error_is_frame_invariant() -> None:
    """∠ΔR depends on Rᵀ R̂ only: the same change of frame on both sides leaves it unchanged."""
    rng = np.random.default_rng(2)
    for _ in range(50):
        R, R_hat, G = (_random_rotation(rng) for _ in range(3))
        assert rotation_error_deg(G @ R, G @ R_hat) == pytest.approx(
            rotation_error_deg(R, R_hat), abs=1e-9
        )


def test_translation_error() -> None:
    assert translation_error([1, 2, 3], [4, 6, 3]) == pytest.approx(5.0)
    assert translation_error([0, 0, 10], [0, 0, 10]) == 0.0


def test_speed_score_on_known_values() -> None:
    """‖t − t̂‖/‖t‖ + 2·arccos|⟨q̂, q⟩|: a 10° error adds 10° in radians."""
    R = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), 0.4)
    t = np.array([0.0, 6.0, 8.0])  # ‖t‖ = 10
    assert speed_score(R, t, R, t) == pytest.approx(0.0, abs=1e-12)
    assert speed_score(R, t, R, t + [0.0, 0.0, 1.0]) == pytest.approx(0.1)
    R_hat = R @ axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(10.0))
    assert speed_score(R, t, R_hat, t) == pytest.approx(np.radians(10.0), rel=1e-9)
    assert speed_score(R, t, R_hat, t + [3.0, 0.0, 0.0]) == pytest.approx(
        0.3 + np.radians(10.0), rel=1e-9
    )


def test_speed_score_ignores_the_quaternion_sign() -> None:
    """A rotation by 350° is the same attitude as −10°: its score is 10°, not 350°."""
    R = np.eye(3)
    R_hat = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.radians(350.0))
    assert speed_score(R, [0, 0, 5], R_hat, [0, 0, 5]) == pytest.approx(np.radians(10.0))
