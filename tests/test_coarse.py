"""The coarse stage (worker/align/coarse.py) without Mitsuba: a stub renderer draws a sphere as
the disk a pinhole camera sees, and moment alignment takes a guess 15 % off in range and off to
the side most of the way to the truth in one render; silhouette moments and the score rule."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_images import StubModel, StubRenderer

from schemas.options import EstimateOptions
from worker.align.coarse import (
    SCORE_MARGIN,
    _clearly_worse,
    placed_score,
    reference_silhouette,
    run_moment_alignment,
)
from worker.align.coarse import silhouette_moments as moments
from worker.align.session import Session
from worker.engine.camera import PinholeCamera
from worker.engine.images import to_display
from worker.engine.photometry import alignment_score

CAMERA = PinholeCamera(128, 128, 400.0, 400.0, 63.5, 63.5)  # the sphere: 40 px in radius
T_TRUE = np.array([0.5, -0.3, 10.0])


def sphere(R: np.ndarray, t: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Linear light of a unit sphere at the model origin: a disk of radius f/z around K t."""
    (u, v), radius = CAMERA.project(t)[0], CAMERA.fx / t[2]
    y, x = np.mgrid[0:128, 0:128].astype(np.float64)
    return 0.3 * (1.0 - np.tanh((np.hypot(x - u, y - v) - radius) / 1.4))  # a smooth rim


def make_session(t0: np.ndarray) -> Session:
    reference = to_display(sphere(np.eye(3), T_TRUE)).astype(np.float32)
    return Session(
        renderer=StubRenderer(CAMERA, sphere, StubModel(radius=1.0)),  # type: ignore[arg-type]
        reference=reference,
        reference_grey=reference,
        options=EstimateOptions().resolved(),
        R=np.eye(3),
        t=t0,
    )


def test_moments_of_a_disk() -> None:
    y, x = np.mgrid[0:100, 0:100]
    disk = (np.hypot(x - 40.0, y - 55.0) < 20.0).astype(np.float32)
    area, centroid = moments(disk, 0.5)
    assert area == pytest.approx(np.pi * 20.0**2, rel=0.01)
    np.testing.assert_allclose(centroid, [40.0, 55.0], atol=0.01)
    assert moments(np.zeros((10, 10)), 0.5)[0] == 0.0


def test_moment_alignment_fixes_most_of_a_range_and_lateral_error() -> None:
    t0 = np.array([0.8, -0.1, 11.5])  # 15 % too far, and off to the side
    session = make_session(t0)
    assert run_moment_alignment(session)
    error_before = np.linalg.norm(t0 - T_TRUE) / np.linalg.norm(T_TRUE)
    error_after = np.linalg.norm(session.t - T_TRUE) / np.linalg.norm(T_TRUE)
    assert error_before > 0.15 and error_after < 0.015  # (the rim widens both disks alike)
    (rec,) = session.history
    assert rec.stage == "coarse" and rec.accepted and rec.step_norm > 0.0
    assert session.renderer.stats.renders == 2  # the guess and the moved render


def test_moment_alignment_keeps_a_pose_it_cannot_improve() -> None:
    session = make_session(T_TRUE.copy())
    assert not run_moment_alignment(session)
    np.testing.assert_array_equal(session.t, T_TRUE)
    assert len(session.history) == 1 and not session.history[0].accepted


def test_moment_alignment_needs_a_silhouette() -> None:
    session = make_session(np.array([40.0, 0.0, 10.0]))  # the sphere is out of the view
    assert not run_moment_alignment(session) and session.history == []


def test_a_score_is_clearly_worse_only_beyond_its_jitter() -> None:
    best = 0.99  # dissimilarity 0.01
    assert not _clearly_worse(1.0 - 0.01 * 1.5 - SCORE_MARGIN + 1e-6, best)
    assert _clearly_worse(1.0 - 0.01 * 1.5 - SCORE_MARGIN - 1e-6, best)


def test_moment_alignment_skips_a_silhouette_the_frame_cuts() -> None:
    session = make_session(np.array([1.6, -0.3, 10.0]))  # the disk's centre at the right edge
    assert not run_moment_alignment(session) and session.history == []
    np.testing.assert_array_equal(session.t, [1.6, -0.3, 10.0])


def _pnp_sequence(monkeypatch: pytest.MonkeyPatch, poses: list[np.ndarray]) -> None:
    """Make the coarse stage's PnP return ``poses`` (translations, R = I) in turn."""
    from worker.align import coarse
    from worker.align.pnp import PnPResult

    answers = iter(poses)
    monkeypatch.setattr(
        coarse,
        "_pnp_from",
        lambda session, view: PnPResult(np.eye(3), next(answers), np.ones(20, bool), 0.5),
    )


@pytest.mark.parametrize("last_is_wrong", [True, False])
def test_the_last_pnp_pose_is_judged_by_its_render(
    monkeypatch: pytest.MonkeyPatch, last_is_wrong: bool
) -> None:
    # The iterations run out after a good PnP step and a last one that is (or is not) far
    # off: the last pose, like every other, stays only if its render is not clearly worse.
    from worker.align.coarse import run_pnp_stage

    good = T_TRUE + np.array([0.02, 0.0, 0.0])
    last = good + np.array([1.5, 0.0, 0.0]) if last_is_wrong else T_TRUE.copy()
    _pnp_sequence(monkeypatch, [good, last])
    session = make_session(T_TRUE + np.array([0.4, 0.2, 0.5]))
    progress, reason = run_pnp_stage(session, max_iterations=2, stop_step=1e-9)
    assert progress and reason is None
    np.testing.assert_array_equal(session.t, good if last_is_wrong else last)
    assert session.history[-1].accepted is not last_is_wrong
    assert len(session.history) == (3 if last_is_wrong else 2)


def test_a_placed_score_looks_past_the_silhouette_s_position_and_size() -> None:
    """search_attitude scores each candidate after moving and scaling its silhouette onto the
    reference's in the image: a disk off to the side and 15 % too far scores about as well as
    one in place, where the plain alignment score does not."""
    reference = to_display(sphere(np.eye(3), T_TRUE)).astype(np.float32)
    off = to_display(sphere(np.eye(3), np.array([0.8, -0.1, 11.5]))).astype(np.float32)
    score, own = placed_score(reference, off, reference_silhouette(reference))
    assert own is not None and own[0] < reference_silhouette(reference)[0]
    assert score > 0.98 > 0.9 > alignment_score(reference, off)
