"""The Jacobian at the current pose (worker/align/learning.py), without Mitsuba: a stub renderer
moves a texture by a known linear map of the pose increment, and the learned Jacobian of every
feature recovers that map; the perturbations are sized to move the image by the requested
pixels; the analytic Jacobian matches the derivative of a pinhole projection."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_images import StubModel, StubRenderer, blobs

from schemas.options import EstimateOptions
from worker.align.learning import analytic_jacobian, learn_at_pose, perturbation_sizes
from worker.align.session import Session
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.posemath import increment_between, skew
from worker.engine.renderer import Window

CAMERA = PinholeCamera(128, 128, 100.0, 100.0, 63.5, 63.5)
R0, T0 = np.eye(3), np.array([0.0, 0.0, 10.0])
#: Image motion (px) per unit of each pose increment [δq, δt]: the renders' true Jacobian.
M = np.array([[20.0, 0.0, 5.0, 10.0, 0.0, 0.5], [0.0, 20.0, -5.0, 0.0, 10.0, 0.3]])


def texture_moved_by_the_pose(R: np.ndarray, t: np.ndarray, scale: float) -> np.ndarray:
    dx, dy = M @ increment_between(R0, T0, R, t)
    return blobs(128, shift=(float(dx), float(dy)), seed=2) ** 2.2  # linear light


def make_session(draw=texture_moved_by_the_pose, **options: object) -> Session:  # type: ignore[no-untyped-def]
    renderer = StubRenderer(CAMERA, draw, StubModel(radius=1.0))
    grey = np.zeros((128, 128), np.float32)
    return Session(
        renderer=renderer,  # type: ignore[arg-type]
        reference=grey,
        reference_grey=grey,
        options=EstimateOptions(**options).resolved(),  # type: ignore[arg-type]
        R=R0,
        t=T0,
        rng=np.random.default_rng(0),
    )


def grid_points() -> np.ndarray:
    y, x = np.mgrid[24:104:16, 24:104:16]
    return np.column_stack([x.ravel(), y.ravel()]).astype(np.float64)


def test_perturbations_move_the_image_by_the_requested_pixels() -> None:
    session = make_session()
    angle, half = perturbation_sizes(session)
    s_px = 100.0 * 1.0 / 10.0  # the target's apparent radius, f·r/d
    assert angle == pytest.approx(3.0 / s_px)  # perturbation_px = 3
    np.testing.assert_allclose(half, [3.0 * 10 / 100, 3.0 * 10 / 100, 3.0 * 10 / s_px])
    angle2, half2 = perturbation_sizes(session, shrink=0.5)
    assert angle2 == pytest.approx(angle / 2) and np.allclose(half2, half / 2)
    fixed = make_session(perturbation_rot_deg=1.0, perturbation_trans_frac=0.01)
    angle, half = perturbation_sizes(fixed)
    assert angle == pytest.approx(np.radians(1.0)) and np.allclose(half, 0.1)


@pytest.mark.parametrize("jacobian", ["per_feature", "common"])
def test_the_learned_jacobian_recovers_the_renders_motion(jacobian: str) -> None:
    session = make_session(jacobian=jacobian)
    points = grid_points()
    learned = learn_at_pose(session, points)
    assert learned.ok.mean() > 0.9
    assert learned.renders == session.options.n_samples + 1  # a base render and N_s others
    J = learned.J.reshape(-1, 2, 6)[learned.ok]
    np.testing.assert_allclose(np.median(J, axis=0), M, atol=0.04 * np.abs(M).max())
    assert np.percentile(np.abs(J - M), 90) < 0.08 * np.abs(M).max()


def stripes_moved_by_the_pose(R: np.ndarray, t: np.ndarray, scale: float) -> np.ndarray:
    """Vertical bands (edges along y, so only motion in x shows), moved by M's x row."""
    dx = float(M[0] @ increment_between(R0, T0, R, t))
    x = np.arange(128.0) - dx
    bands = sum(
        1.0 / (1.0 + np.exp(-(x - e) / 0.8)) * (-1) ** k for k, e in enumerate(range(16, 120, 16))
    )
    return np.tile(0.1 + 0.8 * np.abs(bands), (128, 1))


def test_edge_points_learn_only_the_motion_across_the_edge() -> None:
    # smaller perturbations: an edge's shift is measured from zero, to a few px
    session = make_session(draw=stripes_moved_by_the_pose, perturbation_px=1.5)
    y = np.linspace(30.0, 98.0, 5)
    points = np.array([[x, yy] for x in (32.0, 48.0, 64.0, 80.0) for yy in y])  # on the edges
    normals = np.tile([1.0, 0.0], (len(points), 1))
    learned = learn_at_pose(session, points, normals)
    assert learned.ok.mean() > 0.9
    J = learned.J.reshape(-1, 2, 6)[learned.ok]
    # an edge point's rows: the motion along its normal (here u), none across it; measured
    # from zero on 8-bit renders, an edge's shift comes out a few per cent short
    np.testing.assert_allclose(np.median(J[:, 0], axis=0), M[0], atol=0.06 * np.abs(M).max())
    np.testing.assert_allclose(J[:, 1], 0.0, atol=1e-9)


def test_a_render_without_features_to_track_fails_after_resampling() -> None:
    session = make_session(draw=lambda R, t, scale: np.zeros((128, 128)))
    with pytest.raises(TooFewFeaturesError, match="could be tracked"):
        learn_at_pose(session, grid_points())
    assert session.renderer.stats.renders == 4 * (session.options.n_samples + 1)


class _PlaneRaycaster(StubRenderer):
    """Rays hit the plane z = 10 (camera frame) at the session's pose R = I, t = T0."""

    def raycast(
        self,
        R: np.ndarray,
        t: np.ndarray,
        uv: np.ndarray,
        scale: float = 1.0,
        window: Window | None = None,
    ) -> tuple[np.ndarray, ...]:
        rays = self.camera_at(scale, window).rays(uv)
        X_cam = rays * (10.0 / rays[:, 2:3])
        hit = np.ones(len(uv), dtype=bool)
        hit[0] = False  # one ray misses the model
        return X_cam - t, hit


def test_the_analytic_jacobian_is_the_derivative_of_the_projection() -> None:
    session = make_session()
    session.renderer = _PlaneRaycaster(CAMERA, None, StubModel())
    points = grid_points()
    learned = analytic_jacobian(session, points)
    assert not learned.ok[0] and learned.ok[1:].all() and np.isnan(learned.J[:2]).all()
    X = session.renderer.raycast(R0, T0, points)[0]
    for k in range(1, len(points)):
        x, y, z = X[k] + T0
        P = np.array([[100.0 / z, 0.0, -100.0 * x / z**2], [0.0, 100.0 / z, -100.0 * y / z**2]])
        # R ← R·C(δq) ≈ R (I − 2[δq×]) moves a model point X by 2 [X×] δq
        expected = np.hstack([P @ (2.0 * skew(X[k])), P])
        np.testing.assert_allclose(learned.J[2 * k : 2 * k + 2], expected, rtol=1e-4, atol=1e-6)
