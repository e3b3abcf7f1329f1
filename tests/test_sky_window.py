"""A tracked frame's sky window (worker/align/skywindow.py, ``Session.sky_window``): its
renders of the whole image render only a window that holds the target, pasted onto the sky.

Real Mitsuba renders of a few spheres near the image's centre: the pasted render is the whole
render (up to sampling noise) at a fraction of its cost, for the main and the perturbation
renders; the window is dropped when the reference shows something lit outside it or the model
is not all in front of the camera.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from test_projection import AMBIENT_ONLY, R_MODEL, SPP, T_MODEL, spheres_model

from schemas.options import EstimateOptions
from worker.align.pyramid import WINDOW_MARGIN, WINDOW_PAD_PX, plan_windows
from worker.align.session import Session
from worker.align.skywindow import SKY_KEEP, outline_points, sky_window
from worker.engine.camera import PinholeCamera
from worker.engine.images import Box
from worker.engine.photometry import render_to_grey
from worker.engine.posemath import axis_angle_to_matrix
from worker.engine.renderer import Renderer

CAMERA = PinholeCamera(160, 120, 150.0, 150.0, 79.5, 59.5)
#: Camera-frame sphere centres within ~25 px of the image centre, 8–10 units away.
CENTRES = np.array([[-0.9, -0.5, 9.0], [1.0, 0.3, 8.0], [0.2, 0.8, 10.0]])


@pytest.fixture(scope="module")
def scene(variant: str) -> tuple[Renderer, np.ndarray]:
    model = spheres_model(CENTRES)
    renderer = Renderer(
        model,
        CAMERA,
        AMBIENT_ONLY,
        scales=(1.0, 0.5),
        spp=SPP,
        window_sizes=plan_windows(CAMERA, {1.0, 0.5}),
    )
    return renderer, np.concatenate([p.vertices for p in model.parts]).astype(np.float32)


def _session(renderer: Renderer, reference: np.ndarray, grey: np.ndarray | None = None) -> Session:
    return Session(
        renderer=renderer,
        reference=reference,
        reference_grey=render_to_grey(reference) if grey is None else grey,
        options=EstimateOptions(spp=SPP, perturbation_spp=SPP).resolved(),
        R=R_MODEL,
        t=T_MODEL,
        perturbation_scales={1.0: 0.5},
    )


def test_a_frame_renders_only_its_window_pasted_onto_the_sky(
    scene: tuple[Renderer, np.ndarray],
) -> None:
    renderer, points = scene
    reference = renderer.render(R_MODEL, T_MODEL)
    session = _session(renderer, reference)
    sky = sky_window(points, session, (R_MODEL, T_MODEL))
    assert sky is not None
    side, centre = sky
    # the smallest side that holds the model's projected bounds with the ladder's margin
    X = points @ R_MODEL.T + T_MODEL
    uv = CAMERA.project(X)
    extent = float((uv.max(axis=0) - uv.min(axis=0)).max())
    assert WINDOW_MARGIN * extent + WINDOW_PAD_PX <= side < min(CAMERA.width, CAMERA.height)
    np.testing.assert_allclose(centre, (uv.max(axis=0) + uv.min(axis=0)) / 2)

    whole = session.render_view(R_MODEL, T_MODEL)
    whole_cost = session.render_cost
    session.sky_window = sky
    pasted = session.render_view(R_MODEL, T_MODEL)
    assert pasted.window is None and pasted.linear.shape == whole.linear.shape
    # the same image up to sampling noise, at the window's share of the pixels
    assert whole.grey.sum() > 0
    assert np.abs(pasted.grey - whole.grey).mean() < 0.01 * float(whole.grey.max())
    assert (
        np.abs(pasted.grey - np.roll(whole.grey, 2, axis=1)).mean()
        > 3 * np.abs(pasted.grey - whole.grey).mean()
    )
    window_cost = session.render_cost - whole_cost
    assert window_cost < 0.7 * whole_cost
    w, h = renderer.window_sizes[(side, 1.0)]
    # the view knows where it was pasted (its processing looks only there, worker.align.tracked)
    window = renderer.window_at(1.0, *sky)
    assert window is not None and pasted.sky_box == Box.at(window.origin, (w, h))
    assert whole.sky_box is None
    np.testing.assert_allclose(window_cost, w * h / (CAMERA.width * CAMERA.height))

    # the perturbation renders: the whole image at their scale, the window pasted in
    session.sky_window = None
    perturbed_whole = session.render_perturbed(R_MODEL, T_MODEL, seed=3)
    session.sky_window = sky
    perturbed = session.render_perturbed(R_MODEL, T_MODEL, seed=3)
    assert perturbed.shape == perturbed_whole.shape == (60, 80)
    assert np.abs(perturbed - perturbed_whole).mean() < 0.02 * float(perturbed_whole.max())


def test_a_side_is_kept_from_frame_to_frame_while_not_too_large(
    scene: tuple[Renderer, np.ndarray],
) -> None:
    renderer, points = scene
    session = _session(renderer, renderer.render(R_MODEL, T_MODEL))
    side, _ = sky_window(points, session, (R_MODEL, T_MODEL))  # type: ignore[misc]
    sides = renderer.window_sides
    larger = [s for s in sides if side < s <= SKY_KEEP * side]
    assert larger, sides
    assert sky_window(points, session, (R_MODEL, T_MODEL), keep=larger[-1])[0] == larger[-1]  # type: ignore[index]
    too_large = [s for s in sides if s > SKY_KEEP * side]
    assert too_large, sides
    assert sky_window(points, session, (R_MODEL, T_MODEL), keep=too_large[0])[0] == side  # type: ignore[index]
    smaller = [s for s in sides if s < side]
    assert sky_window(points, session, (R_MODEL, T_MODEL), keep=smaller[-1])[0] == side  # type: ignore[index]


def test_the_whole_image_is_rendered_when_the_reference_shows_light_outside_the_window(
    scene: tuple[Renderer, np.ndarray],
) -> None:
    renderer, points = scene
    reference = renderer.render(R_MODEL, T_MODEL)
    grey = render_to_grey(reference)
    assert sky_window(points, _session(renderer, reference, grey), (R_MODEL, T_MODEL)) is not None
    # something lit in a corner (the target is not where the prediction puts it)
    grey[2:8, 2:8] = float(grey.max())
    assert sky_window(points, _session(renderer, reference, grey), (R_MODEL, T_MODEL)) is None


def test_the_whole_image_is_rendered_when_the_model_is_not_all_in_front_of_the_camera(
    scene: tuple[Renderer, np.ndarray],
) -> None:
    renderer, points = scene
    session = _session(renderer, np.zeros((CAMERA.height, CAMERA.width, 3), np.float32))
    t_close = T_MODEL - [0.0, 0.0, 9.0]  # the camera among the spheres
    assert sky_window(points, session, (R_MODEL, t_close)) is None


def test_the_outline_points_bound_the_image_as_all_the_vertices_do() -> None:
    """outline_points: the vertices of the model's convex hull give the same projected bounds
    and the same least depth as all its vertices, exactly, at poses all round (so the sky
    window is the same), from a fraction of them; a flat model keeps all its vertices."""
    model = spheres_model(CENTRES)
    every = np.concatenate([p.vertices for p in model.parts]).astype(np.float32)
    outline = outline_points(model)
    assert outline.dtype == np.float32 and len(outline) < len(every) / 2
    rng = np.random.default_rng(7)
    for _ in range(200):
        R = axis_angle_to_matrix(rng.normal(size=3), rng.uniform(0.0, np.pi)).astype(np.float32)
        t = np.array([rng.normal(), rng.normal(), rng.uniform(8.0, 12.0)], dtype=np.float32)
        X, Y = every @ R.T + t, outline @ R.T + t
        assert X[:, 2].min() == Y[:, 2].min()
        uv, uv_outline = CAMERA.project(X), CAMERA.project(Y)
        np.testing.assert_array_equal(uv.min(axis=0), uv_outline.min(axis=0))
        np.testing.assert_array_equal(uv.max(axis=0), uv_outline.max(axis=0))

    flat_part = copy.copy(model.parts[0])
    flat_part.vertices = flat_part.vertices * np.array([1.0, 1.0, 0.0], dtype=np.float32)
    flat = copy.copy(model)
    flat.parts = [flat_part]
    assert len(outline_points(flat)) == len(flat_part.vertices)
