"""Photometry (worker/engine/photometry.py) on small synthetic images: the tone curve inverts a
known gamma and exposure, the relative blur recovers a known one, local contrast normalisation
ignores gain and offset, histogram matching copies a distribution, the alignment score prefers
the aligned render, and the content mask finds the target on the sky."""

from __future__ import annotations

import numpy as np
from synthetic_images import blobs, rectangles

from worker.engine.images import Box, srgb_decode, to_display
from worker.engine.photometry import (
    BLUR_REACH_PX,
    _percentile_above_zeros,
    alignment_score,
    apply_tone_curve,
    content_mask,
    contrast_scale,
    fit_tone_curve,
    local_normalise_f,
    match_histogram,
    normalise_pair,
    reference_on_render_scale,
    render_to_grey,
    to_u8,
)


def scene() -> np.ndarray:
    """A linear 'render': shapes of several brightnesses with a texture on them."""
    return (rectangles() * (0.6 + 0.4 * blobs(seed=5))).astype(np.float32)


def test_the_tone_curve_inverts_a_known_gamma_and_exposure() -> None:
    render = to_display(scene())
    reference = (0.7 * render) ** 1.8  # another camera: darker, another gamma
    curve = fit_tone_curve(reference, render)
    lit = render > 0.1
    mapped = apply_tone_curve(reference, curve)
    assert np.median(np.abs(mapped - render)[lit]) < 0.01
    assert np.all(np.diff(curve[0]) > 0) and np.all(np.diff(curve[1]) >= 0)  # monotone


def test_the_tone_curve_reaches_a_lit_ground_that_has_no_flat_pixels() -> None:
    # Terrain at a low sun: three quarters of the frame in shadow lit by the ambient light
    # (smooth, dim), the lit ground in patches whose every pixel lies on a slope. The flat
    # pixels the curve is fitted on are then all shadow; the lit levels must still map right.
    y, x = np.mgrid[0:128, 0:128].astype(np.float64)
    shadow = 0.04 + 0.01 * np.sin(x / 17.0) * np.cos(y / 23.0)
    lit_ground = 0.35 + 0.25 * np.sin(x / 1.3) * np.sin(y / 1.7)
    patches = (np.sin(x / 9.0) + np.sin(y / 11.0)) > 1.0
    render = to_display(np.where(patches, lit_ground, shadow)).astype(np.float32)
    reference = np.clip((0.7 * render) ** 1.8, 0, 1).astype(np.float32)
    curve = fit_tone_curve(reference, render)
    mapped = apply_tone_curve(reference, curve)
    assert 0.15 < patches.mean() < 0.35
    assert np.median(np.abs(mapped - render)[patches]) < 0.03
    assert np.all(np.diff(curve[0]) > 0) and np.all(np.diff(curve[1]) >= 0)  # monotone


def test_a_frame_too_small_to_fill_a_bin_still_gets_a_monotone_curve() -> None:
    # 10 × 10 px, all lit: about 50 flat pixels over 48 bins leave no bin its 10 pixels, so
    # the curve is made of the rank knots alone (or the identity).
    rng = np.random.default_rng(1)
    render = (0.2 + 0.6 * rng.random((10, 10))).astype(np.float32)
    curve = fit_tone_curve((0.7 * render) ** 1.8, render)
    assert len(curve[0]) >= 2
    assert np.all(np.diff(curve[0]) > 0) and np.all(np.diff(curve[1]) >= 0)


def test_the_reference_is_brought_onto_the_renders_scale() -> None:
    linear = scene()
    reference = np.clip(0.7 * linear, 0, 1) ** (1 / 2.2)  # gamma 2.2 instead of sRGB
    mapped = reference_on_render_scale(reference, linear)
    lit = linear > 0.05
    assert np.median(np.abs(mapped - render_to_grey(linear))[lit]) < 0.01
    colour = np.dstack([reference] * 3)  # colour images pool the channels: the same answer
    np.testing.assert_allclose(
        reference_on_render_scale(colour, np.dstack([linear] * 3)), mapped, atol=0.01
    )


def test_local_normalisation_ignores_gain_and_offset() -> None:
    grey = to_display(scene())
    np.testing.assert_allclose(
        local_normalise_f(grey), local_normalise_f(0.5 * grey + 0.2), atol=1e-3
    )


def test_normalising_a_box_of_a_render_on_the_sky_is_normalising_the_whole() -> None:
    """A render's window pasted onto the sky: computing only around the window (by the blurs'
    reach) gives the whole image's contrast scale and normalisation, the floor included."""
    render = np.zeros((200, 260), np.float32)
    box = Box.at((90, 40), (128, 128))
    render[box.slices] = to_display(scene())
    grown = box.grown(BLUR_REACH_PX, render.shape)
    assert grown.pixels < render.size
    whole = contrast_scale(render)
    np.testing.assert_allclose(contrast_scale(render, box=grown), whole, rtol=1e-6)
    np.testing.assert_allclose(
        local_normalise_f(render, whole, box=grown), local_normalise_f(render, whole), atol=1e-5
    )


def test_a_percentile_among_zeros_not_made() -> None:
    rng = np.random.default_rng(2)
    values = rng.random(500).astype(np.float32)
    for zeros in (0, 1, 300, 5000, 60000):
        with_zeros = np.concatenate([values, np.zeros(zeros, np.float32)])
        for q in (50.0, 99.0, 99.9):
            np.testing.assert_allclose(
                _percentile_above_zeros(values, q, zeros), np.percentile(with_zeros, q), rtol=1e-5
            )


def test_histogram_matching_copies_the_template_distribution() -> None:
    source, template = blobs(seed=1), np.sqrt(blobs(seed=2))
    matched = match_histogram(source, template)
    q = np.linspace(0.2, 0.95, 10)  # (below: a mass of sky pixels in one bin)
    np.testing.assert_allclose(np.quantile(matched, q), np.quantile(template, q), atol=0.01)
    assert np.corrcoef(matched.ravel(), source.ravel())[0, 1] > 0.9  # order kept


def test_the_alignment_score_prefers_the_aligned_render() -> None:
    reference = to_display(scene()) ** 1.3
    scores = [
        alignment_score(reference, to_display(np.roll(scene(), shift, axis=1)))
        for shift in (0, 1, 3, 8)
    ]
    assert scores[0] > 0.98
    assert scores == sorted(scores, reverse=True)
    assert alignment_score(reference, np.zeros_like(reference)) <= scores[-1]


def test_the_content_mask_covers_the_target_and_not_the_sky() -> None:
    img = to_u8(rectangles(rects=((40.0, 40.0, 80.0, 80.0, 0.8),)), 1.0)
    mask = content_mask(img, dilate_px=4)
    assert mask[60, 60] == 255 and mask[38, 60] == 255  # inside, and within the dilation
    assert mask[10, 10] == 0 and mask[60, 100] == 0


def test_a_pair_shares_the_renders_white_point() -> None:
    render = to_display(scene())
    pair = normalise_pair(0.5 * render, render)
    assert pair.render.max() == 255 and abs(int(pair.ref.max()) - 255) <= 2
    assert np.abs(pair.ref.astype(int) - pair.render.astype(int)).mean() < 3


def test_srgb_round_trip_through_the_renders_grey() -> None:
    linear = scene()
    np.testing.assert_allclose(srgb_decode(render_to_grey(linear)), linear, atol=1e-5)
