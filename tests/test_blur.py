"""The relative blur between a reference and a render, from aligned edge profiles: a Gaussian
σ, or a streak (motion blur) and a Gaussian."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.synthetic_images import discs, rectangles
from worker.align.blur import Blur, blur_change_px, measure_blur, relative_blur, streak_kernel


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


@pytest.mark.parametrize(("length_px", "angle_deg"), [(1.5, 17.0), (1.5, 120.0), (2.5, 57.0)])
def test_a_streak_is_found_with_its_direction(length_px: float, angle_deg: float) -> None:
    """A reference smeared along one direction (motion blur): the streak is found, and the
    render blurred by it is closer to the reference than by the best single σ."""
    render = discs()
    reference = cv2.filter2D(render, -1, streak_kernel(length_px, np.radians(angle_deg)))
    blur = measure_blur(reference, render)
    assert blur.streak_px == pytest.approx(length_px, rel=0.25), blur
    off = (np.degrees(blur.angle_rad) - angle_deg + 90.0) % 180.0 - 90.0  # a streak has no sign
    assert abs(off) < 12.0, blur

    def residual(b: Blur) -> float:
        return float(np.abs(b.apply(render) - reference).mean())

    assert residual(blur) < 0.5 * residual(Blur(relative_blur(reference, render)))


@pytest.mark.parametrize("sigma_px", [0.5, 1.0])
def test_a_gaussian_blur_is_no_streak(sigma_px: float) -> None:
    render = discs(seed=1)
    blur = measure_blur(_softer(render, sigma_px), render)
    assert blur.streak_px == 0.0 and blur.sigma_px == pytest.approx(sigma_px, abs=0.12), blur


def test_a_streak_kernel_is_a_centred_line_of_unit_sum() -> None:
    k = streak_kernel(2.0, 0.0)
    assert k.sum() == pytest.approx(1.0) and k.shape[0] % 2 == 1
    centre = k.shape[0] // 2
    assert k[centre].sum() == pytest.approx(1.0)  # horizontal: all on the centre row
    assert k[centre, centre - 1] > 0 and k[centre, centre + 1] > 0
    assert k[centre, :centre].sum() == pytest.approx(k[centre, centre + 1 :].sum())


def test_blur_change_is_the_largest_difference_across_an_edge() -> None:
    """How far apart two blurs are: their spreads across an edge, compared over its direction."""
    assert blur_change_px(Blur(1.0), Blur(1.0)) == 0.0
    assert blur_change_px(Blur(1.0), Blur(1.2)) == pytest.approx(0.2)
    a, b = Blur(0.2, 1.5, 0.3), Blur(0.2, 1.5, 0.3 + np.pi)  # a streak has no sign
    assert blur_change_px(a, b) == pytest.approx(0.0, abs=1e-9)
    turned = blur_change_px(a, Blur(0.2, 1.5, 0.3 + np.pi / 2))
    # across the streak its spread is √(σ² + L²/12), along it σ
    assert turned == pytest.approx(np.sqrt(0.04 + 1.5**2 / 12) - 0.2, rel=0.1)
