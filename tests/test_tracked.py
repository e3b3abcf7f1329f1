"""The LM stage's feature sets (worker/align/tracked.py) on small synthetic images: the reference
is the render moved by a known sub-pixel shift and given another tone curve; corners and edge
points are found where the shift puts them, in the render and in a render moved further, and
descriptor matches measure the same shift."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import cv2
import numpy as np
from synthetic_images import blobs, discs, rectangles

from schemas.options import EstimateOptions
from worker.align.blur import Blur, streak_kernel
from worker.align.session import RenderedView
from worker.align.tracked import MatchedFeatures, TrackedFeatures, inherited_smear
from worker.engine.images import Box, on_sky
from worker.engine.photometry import BLUR_REACH_PX, render_to_grey

SHIFT = np.array([0.63, -0.41])
MOVE = np.array([1.2, 0.7])  # a further render, moved from the first
STILL = np.zeros(2)


def scene(shift: np.ndarray = STILL) -> np.ndarray:
    """Linear light of a textured target on the dark sky, moved by ``shift`` px. (The texture
    varies the edges' contrast: edge points are taken where the gradient is among the
    strongest of the image.)"""
    s = (float(shift[0]), float(shift[1]))
    return (rectangles(shift=s) * (0.3 + 0.7 * blobs(shift=s, seed=4))).astype(np.float32)


def view(shift: np.ndarray = STILL) -> RenderedView:
    linear = scene(shift)
    return RenderedView(np.eye(3), np.zeros(3), linear, render_to_grey(linear))


def session(**options: object) -> SimpleNamespace:
    """What the feature sets read of a session: the reference (the render moved by SHIFT, from
    another camera: 0.8× the light, gamma 2 instead of sRGB), the options, and that the target
    is no smooth body (no reflectance law is fitted: reflectance "auto")."""
    reference = (0.8 * scene(SHIFT)) ** 0.5
    return SimpleNamespace(
        ref_image=reference,
        ref_grey=reference,
        options=EstimateOptions(**options).resolved(),  # type: ignore[arg-type]
        smooth_body=False,
    )


def test_corners_and_edge_points_are_found_where_the_shift_puts_them() -> None:
    feats = TrackedFeatures(session(), view())  # type: ignore[arg-type]
    corners = len(feats.corners)
    assert corners >= 10 and len(feats.edges) >= 10
    h, ok = feats.measure(view(), None)
    assert ok.mean() > 0.8
    moved = feats.x_ref - h
    np.testing.assert_allclose(np.median(moved[:corners][ok[:corners]], axis=0), SHIFT, atol=0.05)
    # edge points only across the edge, where the other tone curve weighs more: to 0.1 px
    across = np.einsum("ki,ki->k", moved[corners:], feats.normals) - feats.normals @ SHIFT
    assert np.median(np.abs(across[ok[corners:]])) < 0.1


def test_a_render_moved_further_is_measured_from_the_guess() -> None:
    feats = TrackedFeatures(session(), view())  # type: ignore[arg-type]
    h, ok = feats.measure(view(), None)
    h2, ok2 = feats.measure(view(MOVE), h + MOVE)
    both = ok & ok2
    corners = len(feats.corners)
    np.testing.assert_allclose(
        np.median((h2 - h)[:corners][both[:corners]], axis=0), MOVE, atol=0.05
    )


def test_whitening_and_normals_mark_edge_points_as_one_dimensional() -> None:
    feats = TrackedFeatures(session(), view())  # type: ignore[arg-type]
    corners = len(feats.corners)
    assert np.isnan(feats.feature_normals[:corners]).all()
    np.testing.assert_allclose(np.linalg.norm(feats.feature_normals[corners:], axis=1), 1.0)
    A_edge = feats.A[corners:]
    np.testing.assert_allclose(np.linalg.matrix_rank(A_edge), 1)  # only across the edge
    assert feats.A.shape == (len(feats.x_ref), 2, 2)


def test_matched_features_measure_the_shift_and_track_into_other_renders() -> None:
    feats = MatchedFeatures(session(max_features=100), view())  # type: ignore[arg-type]
    assert len(feats.x_ref) >= 8
    np.testing.assert_allclose(np.median(feats.x_ref - feats.x_base, axis=0), SHIFT, atol=0.3)
    h, ok = feats.measure(feats.view, None)
    assert ok.all() and np.array_equal(h, feats.x_base)
    h2, ok2 = feats.measure(view(MOVE), feats.x_base + MOVE)
    assert ok2.mean() > 0.8
    np.testing.assert_allclose(np.median((h2 - feats.x_base)[ok2], axis=0), MOVE, atol=0.05)
    assert np.isnan(feats.feature_normals).all()
    np.testing.assert_array_equal(feats.A, np.broadcast_to(np.eye(2), feats.A.shape))


def test_a_window_pasted_on_the_sky_is_processed_only_around_itself() -> None:
    """A tracked frame's renders are a window pasted onto the sky (``RenderedView.sky_box``):
    its features are made, carried into the next frame and measured from the box grown by the
    blurs' reach only, and come out as from the whole image."""
    origin, size = (150, 90), (400, 320)
    box = Box.at((origin[0] - 20, origin[1] - 20), (168, 168))  # the window, 20 px around
    assert 2 * box.grown(BLUR_REACH_PX, (size[1], size[0])).pixels < size[0] * size[1]

    def on_frame(image: np.ndarray) -> np.ndarray:
        return on_sky(box.of(on_sky(image, origin, size)), (box.x0, box.y0), size)

    def frame_view(shift: np.ndarray, windowed: bool) -> RenderedView:
        linear = on_frame(scene(shift))
        grey = render_to_grey(linear)
        return RenderedView(np.eye(3), np.zeros(3), linear, grey, sky_box=box if windowed else None)

    def frame_session(shift: np.ndarray) -> SimpleNamespace:
        reference = on_frame((0.8 * scene(shift)) ** 0.5) + 0.01  # a faint sky around
        return SimpleNamespace(
            ref_image=reference,
            ref_grey=reference,
            options=EstimateOptions().resolved(),
            smooth_body=False,
        )

    out = []
    for windowed in (False, True):
        feats = TrackedFeatures(frame_session(SHIFT), frame_view(STILL, windowed))  # type: ignore[arg-type]
        h, ok = feats.measure(frame_view(STILL, windowed), None)
        motion = np.tile(MOVE, (len(feats.x_ref), 1))
        nxt = frame_view(MOVE, windowed)
        carried, keep = feats.carried(frame_session(SHIFT + MOVE), nxt, motion)  # type: ignore[arg-type]
        h2, ok2 = carried.measure(nxt, (h + motion)[keep])
        out.append((feats.x_ref, feats.A, h[ok], carried.x_ref, keep, h2[ok2], carried.A))
    whole, boxed = out
    assert len(whole[0]) >= 20 and whole[4].mean() > 0.8
    for a, b in zip(whole, boxed, strict=True):
        np.testing.assert_allclose(b, a, atol=2e-3)


def test_a_set_carried_into_a_frame_measures_a_changing_blur_again() -> None:
    """Motion blur follows each exposure's motion: a set that found a streak measures it again
    in every frame it is carried into; one with another blur measures it in the first, and
    in the later ones only if it changed there (a defocus stays with the camera)."""
    linear = discs(seed=3).astype(np.float32)
    render = RenderedView(np.eye(3), np.zeros(3), linear, render_to_grey(linear))

    def frame(blurred: np.ndarray) -> SimpleNamespace:
        reference = (0.8 * blurred) ** 0.5
        options = EstimateOptions().resolved()
        return SimpleNamespace(ref_image=reference, ref_grey=reference, options=options,
                               smooth_body=False)  # fmt: skip

    def streak(angle_deg: float) -> SimpleNamespace:
        return frame(cv2.filter2D(linear, -1, streak_kernel(2.0, np.radians(angle_deg))))

    def defocus(sigma_px: float) -> SimpleNamespace:
        return frame(cv2.GaussianBlur(linear, (0, 0), sigma_px))

    def angle_deg(feats: TrackedFeatures) -> float:
        return float(np.degrees(feats.blur.angle_rad)) % 180.0

    def carry(feats: TrackedFeatures, into: SimpleNamespace) -> TrackedFeatures:
        still = np.zeros((len(feats.x_ref), 2))
        return feats.carried(into, render, still)[0]  # type: ignore[arg-type]

    feats = TrackedFeatures(streak(20.0), render)  # type: ignore[arg-type]
    assert feats.smeared and abs(angle_deg(feats) - 20.0) < 12.0, feats.blur
    carried = carry(feats, streak(110.0))
    assert carried.smeared and abs(angle_deg(carried) - 110.0) < 12.0, carried.blur
    assert abs(angle_deg(feats) - 20.0) < 12.0  # the set carried from keeps its own

    lens = TrackedFeatures(defocus(1.0), render)  # type: ignore[arg-type]
    assert lens.smeared is None and lens.blur.sigma_px > 0.7, lens.blur
    same = carry(lens, defocus(1.0))
    assert same.smeared is False and same.blur is lens.blur
    assert carry(same, streak(110.0)).blur is lens.blur  # no longer measured
    changed = carry(lens, defocus(0.4))
    assert changed.smeared and changed.blur.sigma_px < 0.6, changed.blur

    # A set made afresh (a tracker's relearning) goes on from what the carried one found: an
    # unchanged lens blur is not measured again, a changed one or a streak is, and a set never
    # carried (not checked yet) leaves the fresh set's own.
    fresh = TrackedFeatures(defocus(1.0), render)  # type: ignore[arg-type]
    assert fresh.smeared is None
    assert inherited_smear(same, fresh) is False
    assert inherited_smear(changed, fresh) is True
    assert inherited_smear(lens, fresh) is None
    assert inherited_smear(same, TrackedFeatures(streak(20.0), render)) is True  # type: ignore[arg-type]
    sharp = copy.copy(same)  # a set that found no blur (smeared False): nothing was checked
    sharp.blur = Blur()
    assert inherited_smear(sharp, fresh) is None
