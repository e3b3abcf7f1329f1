"""The refinement's window: a film that sees a movable sub-rectangle of the image.

Geometry first (a cropped camera, the planned window sizes), then real renders: the spheres of
tests/test_projection.py imaged through windows at several origins land where the cropped
camera projects them (the window moves through the sensor's principal point while the render
kernel is replayed, so a stale origin would show here), and a window's render is the crop of
the whole image's. Last, a full estimate with and without the window.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_projection import (
    AMBIENT_ONLY,
    R_MODEL,
    R_OVER_D,
    SPP,
    T_MODEL,
    TOLERANCE_PX,
    disc_centroids,
    ellipse_centre,
    sphere_centres_cam,
    spheres_model,
)

from worker.align.pyramid import WINDOW_LADDER, WINDOW_MARGIN, ladder_side, plan_windows
from worker.engine.camera import PinholeCamera
from worker.engine.renderer import Renderer, Window

CAMERA = PinholeCamera(160, 120, 150.0, 150.0, 90.3, 52.6)
WINDOW = (64, 48)
SIDE = 64  # the key of the window sensor in these tests


def test_a_cropped_camera_images_a_point_where_the_whole_image_does_shifted() -> None:
    X = np.random.default_rng(0).uniform([-2, -2, 8], [2, 2, 12], size=(20, 3))
    crop = CAMERA.cropped(30, 17, 64, 48)
    np.testing.assert_allclose(crop.project(X), CAMERA.project(X) - [30, 17])
    np.testing.assert_allclose(
        crop.rays(CAMERA.project(X) - [30, 17]), CAMERA.rays(CAMERA.project(X))
    )
    with pytest.raises(ValueError, match="not inside"):
        CAMERA.cropped(100, 0, 64, 48)


def test_the_window_ladder_has_a_square_sensor_per_side_and_scale() -> None:
    camera = PinholeCamera(1920, 1200, 2000.0, 2000.0, 959.5, 599.5)
    sizes = plan_windows(camera, {1.0, 0.5, 0.25})
    sides = sorted({side for side, _ in sizes})
    assert len(sides) == len(WINDOW_LADDER) and max(sides) < 1200
    for side in sides:
        assert sizes[(side, 1.0)] == (side + 2, side + 2)
        assert sizes[(side, 0.25)] == (-(-side // 4) + 2, -(-side // 4) + 2)
    # consecutive sides differ by 2^(1/4): a chosen window is at most 19 % larger than needed
    assert all(b / a < 1.2 for a, b in zip(sides, sides[1:], strict=False))


def test_the_smallest_side_that_holds_the_target_is_chosen() -> None:
    sides = [300, 357, 424, 504]
    assert WINDOW_MARGIN * 250 + 16 <= 300 < WINDOW_MARGIN * 260 + 16
    assert ladder_side(sides, 250.0) == 300
    assert ladder_side(sides, 260.0) == 357
    assert ladder_side(sides, 340.0) == 424
    assert ladder_side(sides, 480.0) is None  # fills the image: no window


@pytest.fixture(scope="module")
def spheres(variant: str) -> tuple[Renderer, np.ndarray]:
    centres = sphere_centres_cam(CAMERA)
    renderer = Renderer(
        spheres_model(centres),
        CAMERA,
        AMBIENT_ONLY,
        scales=(1.0,),
        spp=SPP,
        window_sizes={(SIDE, 1.0): WINDOW},
    )
    return renderer, centres


@pytest.mark.parametrize("origin", [(30, 35), (70, 72), (0, 40), (30, 35)])
def test_discs_in_a_window_sit_where_the_cropped_camera_projects_them(
    spheres: tuple[Renderer, np.ndarray], origin: tuple[int, int]
) -> None:
    renderer, centres = spheres
    image = renderer.render(R_MODEL, T_MODEL, window=Window(SIDE, origin))
    assert image.shape == (WINDOW[1], WINDOW[0], 3)
    cam = renderer.camera_at(1.0, Window(SIDE, origin))
    expected = np.array([ellipse_centre(cam, c, R_OVER_D * np.linalg.norm(c)) for c in centres])
    margin = 3.0 * R_OVER_D * cam.fx + 2.0
    inside = np.all((expected > margin) & (expected < np.array(WINDOW) - 1 - margin), axis=1)
    assert inside.any(), "no whole disc in this window: move the origin"
    centroids = disc_centroids(image, expected[inside], margin)
    err = np.linalg.norm(centroids - expected[inside], axis=1)
    assert err.max() < TOLERANCE_PX, f"centroid errors {np.round(err, 3)} px"


def test_a_window_renders_the_crop_of_the_whole_image(spheres: tuple[Renderer, np.ndarray]) -> None:
    renderer, _ = spheres
    whole = renderer.render(R_MODEL, T_MODEL)
    x, y = 40, 30
    window = renderer.render(R_MODEL, T_MODEL, window=Window(SIDE, (x, y)))
    crop = whole[y : y + WINDOW[1], x : x + WINDOW[0]]
    assert crop.sum() > 0
    # Same scene and spp: they differ by sampling noise only (on the discs' edges) ...
    assert np.abs(window - crop).mean() < 0.01 * crop.max()
    # ... and far more from the crop a few pixels away.
    shifted = whole[y + 3 : y + 3 + WINDOW[1], x : x + WINDOW[0]]
    assert np.abs(window - shifted).mean() > 3 * np.abs(window - crop).mean()


@pytest.mark.slow
def test_an_estimate_with_a_window_is_as_accurate_for_less(variant: str, tmp_path) -> None:  # noqa: ANN001
    """The demo satellite at half the frame: with the window, the refinement renders less
    (render_cost, in full-size renders) and ends as close to the truth; the artifacts still
    show the whole image."""
    from schemas.camera import Camera
    from schemas.options import EstimateOptions
    from worker.bench.synth import CaseSpec, make_case
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.images import decode_image, encode_png
    from worker.engine.meshes import load_model
    from worker.entry import run_estimate

    path = demo_satellite_path(tmp_path)
    size = 384
    camera = Camera(width=size, height=size, fx=1.17 * size, fy=1.17 * size,
                    cx=size / 2 - 0.5, cy=size / 2 - 0.5)  # fmt: skip
    case = make_case(load_model(path), camera, CaseSpec(3.0, 0.03, fill=0.5), seed=1)
    image = encode_png(case.reference)
    # Eight estimator seeds each: on this view one estimate moves by up to 0.15° with the seed
    # and with the CPU, so medians are compared, not one pair; three seeds were too few (on an
    # AMD EPYC VM, 2026-12-05: seeds 0–2 windowed 0.087, 0.143, 0.060° against whole 0.033,
    # 0.022, 0.034°, while seeds 0–7 gave medians 0.072° and 0.041°).
    errors: dict[bool, list[float]] = {True: [], False: []}
    costs: dict[bool, list[float]] = {True: [], False: []}
    for seed in range(8):
        for window in (True, False):
            options = EstimateOptions(window=window, seed=seed)
            result, artifacts = run_estimate(
                path, image, case.request.model_copy(update={"options": options})
            )
            assert result.converged, result.reason
            assert result.errors is not None and result.errors.rotation_deg < 0.3
            errors[window].append(result.errors.rotation_deg)
            costs[window].append(result.render_cost)
            if window:
                windowed_artifacts = artifacts
    assert np.median(errors[True]) < np.median(errors[False]) + 0.05
    assert sum(costs[True]) < 0.8 * sum(costs[False])
    for name in ("overlay_final", "difference", "final_render"):
        assert decode_image(windowed_artifacts[name], 10**7).shape[:2] == (size, size)
