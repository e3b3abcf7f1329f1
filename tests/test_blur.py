"""The relative blur between a reference and a render, from aligned edge profiles."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.synthetic_images import rectangles
from worker.align.blur import relative_blur


def _softer(linear: np.ndarray, sigma_px: float) -> np.ndarray:
    return cv2.GaussianBlur(linear, (0, 0), sigma_px)


@pytest.mark.parametrize("sigma_px", [0.5, 0.8, 1.2])
def test_a_blur_of_known_size_is_recovered(sigma_px: float) -> None:
    render = rectangles(side=160, width_px=0.3)
    assert relative_blur(_softer(render, sigma_px), render) == pytest.approx(sigma_px, abs=0.12)


def test_gain_offset_noise_and_a_small_misalignment_do_not_change_it() -> None:
    render = rectangles(side=160, width_px=0.3)
    reference = 0.6 * _softer(rectangles(side=160, shift=(0.35, -0.2), width_px=0.3), 0.8) + 0.02
    reference = reference + np.random.default_rng(0).normal(0.0, 0.01, reference.shape)
    assert relative_blur(reference.astype(np.float32), render) == pytest.approx(0.8, abs=0.15)


def test_equal_sharpness_and_a_sharper_reference_give_no_blur() -> None:
    render = _softer(rectangles(side=160, width_px=0.3), 0.6)
    assert relative_blur(render, render) < 0.2
    sharper = rectangles(side=160, width_px=0.3)  # the render cannot be sharpened: σ = 0
    assert relative_blur(sharper, render) < 0.2


def test_an_image_without_edges_gives_no_blur() -> None:
    flat = np.full((64, 64), 0.3, dtype=np.float32)
    assert relative_blur(flat, flat) == 0.0
