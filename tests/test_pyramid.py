"""Coarse to fine (worker/align/pyramid.py): the levels an estimate works at, and a session
working at a reduced level (the reference and the camera scaled together)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_images import StubRenderer, rectangles

from schemas.options import EstimateOptions
from worker.align.pyramid import (
    COARSE_SIDE_PX,
    COARSE_TARGET_PX,
    FIRST_PASS_SIDE_PX,
    FIRST_PASS_TARGET_PX,
    level_for,
    level_spp,
    perturbation_scale,
    plan_levels,
)
from worker.align.session import Session
from worker.engine.camera import PinholeCamera

SPEED_CAMERA = PinholeCamera(1920, 1200, 3003.0, 3003.0, 960.5, 600.2)


@pytest.mark.parametrize(
    ("width", "height", "target_px", "level"),
    [
        (512, 512, 300.0, 0.5),  # 256 px short side, the target 150 px across
        (640, 480, 300.0, 0.5),
        (1920, 1200, 700.0, 0.25),  # 300 px short side
        (1920, 1200, 300.0, 0.5),  # a small target keeps 120 px: the next level up
        (160, 160, 100.0, 1.0),  # already small: no reduced level
        (512, 512, 150.0, 1.0),
    ],
)
def test_a_reduced_level_keeps_the_image_and_the_target_large_enough(
    width: int, height: int, target_px: float, level: float
) -> None:
    camera = PinholeCamera(width, height, 500.0, 500.0, width / 2, height / 2)
    assert level_for(camera, target_px, FIRST_PASS_SIDE_PX, FIRST_PASS_TARGET_PX) == level
    # the coarse stage works at the first pass's level (at full size when PnP fails there)
    assert level_for(camera, target_px, COARSE_SIDE_PX, COARSE_TARGET_PX) == level


def test_the_plan_has_a_sensor_for_every_level_and_perturbation_scale() -> None:
    plan = plan_levels(SPEED_CAMERA, 700.0, 0.5, pyramid=True)
    assert (plan.coarse, plan.first_pass) == (0.25, 0.25)
    # perturbations: half the level, but never below 256 px on the short side nor above it
    assert plan.perturbation == {0.25: 0.213, 1.0: 0.5}
    assert plan.scales == (1.0, 0.5, 0.25, 0.213)
    flat = plan_levels(SPEED_CAMERA, 700.0, 0.5, pyramid=False)
    assert (flat.coarse, flat.first_pass) == (1.0, 1.0) and flat.scales == (1.0, 0.5)
    assert perturbation_scale(1.0, 1.0, SPEED_CAMERA) == 1.0  # the paper: full size


def _session(scales: tuple[float, ...]) -> Session:
    camera = PinholeCamera(128, 96, 120.0, 118.0, 61.3, 47.9, skew=1.5)
    reference = rectangles(side=128)[:96]
    renderer = StubRenderer(camera, scales=scales)
    return Session(
        renderer=renderer,  # type: ignore[arg-type]
        reference=reference,
        reference_grey=reference,
        options=EstimateOptions().resolved(),
        R=np.eye(3),
        t=np.array([0.0, 0.0, 10.0]),
    )


def test_a_session_at_a_reduced_level_scales_the_reference_with_the_camera() -> None:
    session = _session((1.0, 0.5))
    full = session.camera
    session.set_level(0.5)
    cam = session.camera
    assert (cam.width, cam.height) == (64, 48) and session.ref_grey.shape == (48, 64)
    assert cam.fx == pytest.approx(full.fx / 2) and cam.skew == pytest.approx(full.skew / 2)
    assert cam.cx == pytest.approx((full.cx + 0.5) / 2 - 0.5)
    # area averaging: the mean brightness is kept
    assert session.ref_grey.mean() == pytest.approx(session.reference_grey.mean(), rel=1e-3)
    view = session.current_view()
    assert view.level == 0.5 and session.renderer.stats.renders == 1
    session.set_level(1.0)
    assert session.current_view().level == 1.0 and session.renderer.stats.renders == 2


@pytest.mark.parametrize(
    ("spp", "level", "floor", "expected"),
    [
        (16, 1.0, 4, 16),
        (16, 0.5, 4, 4),  # spp·level²
        (64, 0.5, 4, 16),
        (16, 0.25, 4, 4),  # 1 by area, but never below the perturbation renders' spp
        (2, 0.25, 4, 2),  # nor above the full-resolution spp
    ],
)
def test_a_reduced_level_renders_as_many_samples_per_unit_area(
    spp: int, level: float, floor: int, expected: int
) -> None:
    assert level_spp(spp, level, floor) == expected


def test_a_level_without_a_sensor_is_refused() -> None:
    session = _session((1.0,))
    with pytest.raises(ValueError, match="no sensor"):
        session.set_level(0.5)
