"""The state of one estimate (worker/align/session.py) over a stub renderer: renders are made
once per pose and counted per session, the first and second views are kept, every iteration is
recorded with its errors against the truth and reported, and a cancel stops the next render."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_images import StubRenderer, blobs

from schemas.options import EstimateOptions
from worker.align.session import LinearFit, Session
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import EstimationCancelled
from worker.engine.metrics import rotation_error_deg
from worker.engine.posemath import apply_increment

CAMERA = PinholeCamera(64, 64, 70.0, 70.0, 31.5, 31.5)
R0, T0 = np.eye(3), np.array([0.0, 0.0, 10.0])


def make_session(**kwargs: object) -> Session:
    renderer = StubRenderer(CAMERA, lambda R, t, scale: np.full((64, 64), t[0] + 0.5))
    renderer.stats.renders = 7  # renders of earlier estimates with the same (shared) renderer
    reference = blobs(64)
    return Session(
        renderer=renderer,  # type: ignore[arg-type]
        reference=reference,
        reference_grey=reference,
        options=EstimateOptions(max_iterations=5).resolved(),
        R=R0,
        t=T0,
        **kwargs,  # type: ignore[arg-type]
    )


def test_the_current_view_is_rendered_once_per_pose() -> None:
    session = make_session()
    first = session.current_view()
    assert session.current_view() is first and session.renderer.stats.renders == 8
    moved = session.render_view(*apply_increment(R0, T0, [0, 0, 0, 0.1, 0, 0]))
    session.accept(moved)
    assert session.R is moved.R and session.t is moved.t and session.current_view() is moved
    assert session.views == {"first": first, "second": moved}
    assert np.allclose(moved.linear, 0.6)  # drawn at its own pose


def test_every_iteration_is_recorded_with_its_errors_and_reported() -> None:
    seen = []
    truth = (R0, np.array([0.1, 0.0, 10.0]))
    session = make_session(truth=truth, on_iteration=lambda rec, n: seen.append((rec, n)))
    session.current_view()
    rec = session.record("refine", 2.5, 0.01, 1e-3, True, 42)
    assert rec.iteration == 1 and rec.stage == "refine" and rec.accepted
    assert rec.cost == 2.5 and rec.lambda_ == 1e-3 and rec.features == 42
    assert rec.renders == 1  # this session's render only
    assert rec.translation_error == pytest.approx(0.1)
    assert rec.rotation_error_deg == pytest.approx(rotation_error_deg(R0, R0))
    assert seen == [(rec, 5)] and session.iterations == 1 and session.iterations_left == 4
    assert session.record("refine", 2.0, 0.0, 1e-2, False, 40).renders == 0


def test_a_cancel_stops_the_next_render() -> None:
    asked = [False]
    session = make_session(should_cancel=lambda: asked[0])
    session.current_view()
    asked[0] = True
    with pytest.raises(EstimationCancelled):
        session.render_view(R0, T0 + 1.0)
    with pytest.raises(EstimationCancelled):
        session.render_perturbed(R0, T0, seed=1)


def test_parts_are_timed_and_the_reference_is_described_once() -> None:
    session = make_session()
    with session.timed("match"):
        described = session.reference_described("orb", 100)
    assert session.reference_described("orb", 100)["orb"] is described["orb"]
    assert set(session.reference_described("both", 100)) == {"sift", "orb"}
    assert session.timings_s["match"] > 0.0 and session.range_ == pytest.approx(10.0)


def test_a_linear_fit_counts_its_features() -> None:
    fit = LinearFit(np.zeros((6, 6)), np.zeros(6), np.ones(3), np.zeros((3, 2)))
    assert fit.features == 3


def test_the_window_holds_the_lit_part_and_follows_the_target() -> None:
    """A bright 20×16 px patch imaged where the model's centre projects: the window is the
    smallest ladder side holding it with its margin, centred on it; the reference, the
    camera and the renders are then the window's, and it moves with the pose."""
    from worker.align.pyramid import WINDOW_MARGIN, WINDOW_PAD_PX, plan_windows

    camera = PinholeCamera(128, 96, 100.0, 100.0, 63.5, 47.5)

    def draw(R: np.ndarray, t: np.ndarray, scale: float) -> np.ndarray:
        image = np.zeros((96, 128), dtype=np.float32)
        u, v = (camera.project(t)[0] + 0.5).astype(int)
        image[v - 8 : v + 8, u - 10 : u + 10] = 1.0
        return image

    renderer = StubRenderer(camera, draw, window_sizes=plan_windows(camera, {1.0}))
    reference = blobs(128)[:96]
    session = Session(
        renderer=renderer,  # type: ignore[arg-type]
        reference=reference,
        reference_grey=reference,
        options=EstimateOptions().resolved(),
        R=R0,
        t=np.array([0.5, -0.3, 10.0]),
    )
    session.place_window(session.current_view())
    side = session.window_side
    assert side is not None and side >= WINDOW_MARGIN * 20 + WINDOW_PAD_PX
    assert [s for s in renderer.window_sides if WINDOW_MARGIN * 20 + WINDOW_PAD_PX <= s][0] == side
    w = session.window
    assert w is not None and session.camera.width == renderer.window_sizes[(side, 1.0)][0]
    u, v = camera.project(session.t)[0]
    cx, cy = (
        w.origin[0] + (session.camera.width - 1) / 2,
        w.origin[1] + (session.camera.height - 1) / 2,
    )
    assert abs(cx - u) <= 1.0 and abs(cy - v) <= 1.0  # centred on the patch
    x, y = w.origin
    np.testing.assert_array_equal(
        session.ref_grey, reference[y : y + session.camera.height, x : x + session.camera.width]
    )
    view = session.current_view()
    assert view.window == w and view.grey.shape == (session.camera.height, session.camera.width)
    pasted = view.in_frame().grey
    h, w_px = view.grey.shape
    assert pasted.shape == (96, 128) and pasted.sum() == pytest.approx(view.grey.sum())
    np.testing.assert_array_equal(pasted[y : y + h, x : x + w_px], view.grey)
    session.t = session.t + np.array([0.4, 0.0, 0.0])  # 4 px to the right
    session.centre_window()
    assert session.window is not None and session.window.origin[0] == x + 4
    assert session.current_view().window == session.window


def test_a_stage_spp_renders_anew_when_it_changes() -> None:
    """The coarse stage renders with its own spp (options.coarse_spp); the refinement's first
    view at the same level and pose is rendered again with options.spp, not reused."""
    session = make_session()
    session.stage_spp = 4
    coarse = session.current_view()
    assert coarse.spp == 4 and session.current_view() is coarse
    session.stage_spp = None
    fine = session.current_view()
    assert fine is not coarse and fine.spp == session.options.spp == 16
    assert session.renderer.stats.renders == 7 + 2
