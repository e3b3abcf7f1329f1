"""Sparse features (worker/align/features.py) on small synthetic images: KLT recovers a known
sub-pixel shift, corners land on the drawn corners, the structure tensor's whitening knows a
corner from an edge, and descriptor matches agree with the shift between two images."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_images import blobs, rectangles, u8

from worker.align.features import (
    EMPTY_MATCHES,
    Matches,
    detect_corners,
    match_features,
    structure_whitening,
    track,
)

SHIFT = (1.37, -0.62)


def test_klt_recovers_a_sub_pixel_shift() -> None:
    src, dst = u8(blobs()), u8(blobs(shift=SHIFT))
    y, x = np.mgrid[24:104:12, 24:104:12]
    pts = np.column_stack([x.ravel(), y.ravel()]).astype(np.float64)
    moved, ok = track(src, dst, pts)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.median(moved[ok] - pts[ok], axis=0), SHIFT, atol=0.05)


def test_klt_starts_from_a_guess_and_drops_points_that_leave_the_image() -> None:
    src, dst = u8(blobs()), u8(blobs(shift=(6.0, 0.0)))
    pts = np.array([[60.0, 60.0], [125.0, 60.0]])  # the second ends up outside (x > 127)
    moved, ok = track(src, dst, pts, guess=pts + [6.0, 0.0])
    assert ok[0] and not ok[1]
    np.testing.assert_allclose(moved[0], [66.0, 60.0], atol=0.05)
    empty, none = track(src, dst, np.zeros((0, 2)))
    assert empty.shape == (0, 2) and none.shape == (0,)


def test_corners_land_on_the_drawn_corners() -> None:
    img = u8(rectangles(rects=((30.0, 40.0, 90.0, 80.0, 0.9),)))
    corners = detect_corners(img, 20)
    truth = np.array([[30.0, 40.0], [90.0, 40.0], [30.0, 80.0], [90.0, 80.0]])
    nearest = np.linalg.norm(corners[:, None] - truth[None], axis=2).min(axis=0)
    assert len(corners) == 4 and np.all(nearest < 0.5), nearest


def test_no_corners_in_a_flat_image() -> None:
    assert detect_corners(np.zeros((64, 64), np.uint8), 10).shape == (0, 2)


def test_whitening_is_isotropic_at_a_corner_and_one_sided_on_an_edge() -> None:
    img = u8(rectangles(rects=((30.0, 30.0, 100.0, 100.0, 0.9),)))
    corner, edge = np.array([[30.0, 30.0]]), np.array([[30.0, 65.0]])  # edge: x = 30, vertical
    A_corner, A_edge = structure_whitening(img, corner)[0], structure_whitening(img, edge)[0]
    assert np.linalg.eigvalsh(A_corner.T @ A_corner).min() > 0.3  # both directions count
    w, V = np.linalg.eigh(A_edge.T @ A_edge)
    assert w[1] == pytest.approx(1.0) and w[0] < 0.1  # only across the edge...
    assert abs(V[0, 1]) > 0.99  # ...which is x


def test_matches_agree_with_the_shift_between_two_images() -> None:
    ref, render = u8(blobs(seed=3)), u8(blobs(seed=3, shift=SHIFT))
    matches = match_features(ref, render, detector="both", max_features=200)
    assert len(matches) >= 8
    moved = matches.render_pts - matches.ref_pts
    np.testing.assert_allclose(np.median(moved, axis=0), SHIFT, atol=0.3)
    assert np.all(np.diff(matches.score) >= 0)  # best first


def test_matches_subset_and_length() -> None:
    m = Matches(np.arange(6.0).reshape(3, 2), np.arange(6.0).reshape(3, 2) + 1, np.arange(3.0))
    sub = m.subset(np.array([2, 0]))
    assert len(sub) == 2 and sub.score.tolist() == [2.0, 0.0]
    assert len(EMPTY_MATCHES) == 0
