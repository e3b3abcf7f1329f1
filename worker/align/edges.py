"""Edge features: points on image edges, measured across the edge only.

Spacecraft are mostly edges — silhouettes, panel borders, truss members — and an edge's position
across itself is geometry, hardly touched by a sun a few degrees off. Corner trackers leave them
out (an edge point cannot be located along the edge), so the pose would rest on a few dozen
corners. Here each edge point is a 1-D feature: its shift along the edge normal between two
images, found by Gauss–Newton on intensity profiles sampled across the edge.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.pyramid import WINDOW_MARGIN, WINDOW_PAD_PX

Array = NDArray[np.float64]
Image = NDArray[np.float32]

#: Profile samples: ±PROFILE_HALF_LEN px along the normal, ±PROFILE_HALF_WIDTH px across it.
PROFILE_HALF_LEN = 7
PROFILE_HALF_WIDTH = 2
#: Gaussian weight along the profile, px (keeps a neighbouring edge from pulling the fit).
PROFILE_SIGMA_PX = 3.0
#: Gauss–Newton iterations, the update (px) below which they stop, and the largest shift (px).
SHIFT_ITERATIONS = 8
SHIFT_TOL_PX = 0.005
SHIFT_MAX_PX = 6.0
#: A shift is trusted when the two profiles correlate at least this well after it.
MIN_PROFILE_NCC = 0.8
#: ... and when the target's edge has at least this share of the template's contrast (their
#: weighted standard deviations; both images are contrast-normalised alike). An edge of the
#: render that the reference lacks (a crest lit in the render and not in the reference, at a
#: low sun) can still correlate above MIN_PROFILE_NCC with a faint ripple; its step −g/H then
#: moves by that ripple's share of the way (3 % here), so the shift stays where it started and
#: the point reports no residual at any pose. Measured: the robustness suite's edge points have
#: ratios 0.66–1.5 (1st–99th percentile); at a 3–12° sun over terrain 63 % of the render's edge
#: points had 0.02–0.06, the rest about 1.
MIN_CONTRAST_RATIO = 0.3
#: Edge point spacing (px), and the Canny thresholds as fractions of the 99.5th percentile of
#: the gradient magnitude around the target (:func:`_strongest`; hysteresis: strong edges at
#: HIGH, continued down to LOW).
EDGE_SPACING_PX = 5
CANNY_LOW, CANNY_HIGH = 0.4, 1.0
#: Share of the image the square around the target must cover for the whole image to set the
#: thresholds instead (:func:`_strongest`).
SQUARE_SHARE = 0.5


def profile_grid() -> tuple[Array, Array, Array]:
    """Offsets along (J) and across (C) the normal of every profile sample, and the samples'
    weights W (Gaussian along the normal); flat arrays of one length."""
    j = np.arange(-PROFILE_HALF_LEN, PROFILE_HALF_LEN + 1, dtype=np.float64)
    c = np.arange(-PROFILE_HALF_WIDTH, PROFILE_HALF_WIDTH + 1, dtype=np.float64)
    J, C = np.meshgrid(j, c, indexing="ij")
    W = np.exp(-0.5 * (J / PROFILE_SIGMA_PX) ** 2)
    return J.ravel(), C.ravel(), W.ravel()


def sample(img: Image, x: Array, y: Array) -> Array:
    """Bilinear samples of ``img`` at float coordinates (any shape)."""
    shape, n = x.shape, x.size
    cols = 1024  # remap maps must stay below 32767 in each dimension
    pad = (-n) % cols
    mx = np.pad(x.ravel(), (0, pad)).reshape(-1, cols).astype(np.float32)
    my = np.pad(y.ravel(), (0, pad)).reshape(-1, cols).astype(np.float32)
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape).astype(np.float64)


def profiles(img: Image, pts: Array, normals: Array, s: Array | None = None) -> Array:
    """Intensity profiles (k, samples) of ``img`` across the edges at ``pts`` (k, 2) with unit
    ``normals`` (k, 2), each moved by s (k,) px along its normal (the profile_grid layout)."""
    J, C, _ = profile_grid()
    shift = J if s is None else J + s[:, None]
    tang = np.column_stack([-normals[:, 1], normals[:, 0]])
    x = pts[:, :1] + C * tang[:, :1] + shift * normals[:, :1]
    y = pts[:, 1:] + C * tang[:, 1:] + shift * normals[:, 1:]
    return sample(img, x, y)


def detect_edge_points(
    img: Image,
    mask: NDArray[np.uint8] | None,
    max_points: int,
    spacing_px: int = EDGE_SPACING_PX,
    thresholds: tuple[float, float] = (CANNY_LOW, CANNY_HIGH),
) -> tuple[Array, Array]:
    """Edge points (k, 2) and unit normals (k, 2): Canny edges, one point per grid cell.

    The point kept in a cell is its strongest edge pixel; the normal is the image gradient's
    direction there. ``img`` should be noise-free (a render).
    """
    g = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    top = _strongest(mag, mask)
    u8 = np.clip(g / max(float(g.max()), 1e-6) * 255.0, 0, 255).astype(np.uint8)
    scale = 255.0 / max(float(g.max()), 1e-6)  # Canny's Sobel sees u8, i.e. g × scale
    low, high = thresholds
    edges = cv2.Canny(u8, low * top * scale, high * top * scale, L2gradient=True)
    if mask is not None:
        edges[mask == 0] = 0
    ys, xs = np.nonzero(edges)
    if len(xs) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    strength = mag[ys, xs]
    cell = (ys // spacing_px) * (img.shape[1] // spacing_px + 1) + xs // spacing_px
    order = np.lexsort((-strength, cell))
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    keep = order[first]
    keep = keep[np.argsort(-strength[keep])][:max_points]
    pts = np.column_stack([xs[keep], ys[keep]]).astype(np.float64)
    n = np.column_stack([gx[ys[keep], xs[keep]], gy[ys[keep], xs[keep]]]).astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return pts, n


def _strongest(mag: Array, mask: NDArray[np.uint8] | None) -> float:
    """The 99.5th percentile of the gradient magnitude ``mag`` in the square around ``mask``'s
    bounds (× WINDOW_MARGIN + WINDOW_PAD_PX, centred: an estimate's refinement window), or in
    the whole image without a mask.

    Not in the whole image: how much sky surrounds the target would set the thresholds. With
    the target on 17 % of a 512² frame the percentile fell, weak shading edges came in, and an
    estimate of the bench's asteroid (a `combined` reference; the tracker's full estimates run
    on whole images) ended 0.9-1.3° off, the same with the refinement window 0.03-0.08°.
    An image the square covers SQUARE_SHARE of or more (a window: its ladder side is at most
    19 % larger than the square; a target that fills the frame) is taken whole, as before:
    the square alone there changed Aura's windowed estimates (median the same, its worst
    0.095° → 0.237°) for nothing."""
    region = mag
    if mask is not None and mask.any():
        ys, xs = np.nonzero(mask)
        cx, cy = 0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max())
        side = WINDOW_MARGIN * max(xs.max() - xs.min(), ys.max() - ys.min()) + WINDOW_PAD_PX
        x0, x1 = max(int(cx - side / 2), 0), min(int(cx + side / 2) + 1, mag.shape[1])
        y0, y1 = max(int(cy - side / 2), 0), min(int(cy + side / 2) + 1, mag.shape[0])
        if (x1 - x0) * (y1 - y0) < SQUARE_SHARE * mag.size:  # else a window, or a full frame
            region = mag[y0:y1, x0:x1]
    return float(np.percentile(region, 99.5)) or 1.0


def normal_shift(
    template: Image, target: Image, pts: Array, normals: Array, s0: Array | None = None
) -> tuple[Array, NDArray[np.bool_]]:
    """Shift s (k,) along each normal with target(p + (j + s) n) ≈ template(p + j n).

    Gauss–Newton on the profiles, with the template's gradient along the normal standing in
    for the target's at the match (so a noisy target does not bias it). Returns the shifts and
    which converged within SHIFT_MAX_PX with well-correlated profiles.
    """
    k = len(pts)
    if k == 0:
        return np.zeros(0), np.zeros(0, dtype=bool)
    W = profile_grid()[2]
    half = np.full(k, 0.5)
    T = profiles(template, pts, normals)
    # derivative along the normal by central differences of the template profile samples
    dT = profiles(template, pts, normals, half) - profiles(template, pts, normals, -half)
    H = np.sum(W * dT * dT, axis=1)
    Tc = T - np.sum(W * T, axis=1, keepdims=True) / W.sum()
    s = np.zeros(k) if s0 is None else s0.astype(np.float64).copy()
    # Each point iterates until its own step is below SHIFT_TOL_PX (the points still moving
    # are the only ones sampled again: most settle in two or three steps, a few take all).
    moving = np.arange(k)
    for _ in range(SHIFT_ITERATIONS):
        B = profiles(target, pts[moving], normals[moving], s[moving])
        B = B - np.sum(W * B, axis=1, keepdims=True) / W.sum()  # offsets cancel
        step = -np.sum(W * dT[moving] * (B - Tc[moving]), axis=1) / np.maximum(H[moving], 1e-12)
        step = np.clip(step, -1.0, 1.0)
        s[moving] += step
        moving = moving[np.abs(step) >= SHIFT_TOL_PX]
        if len(moving) == 0:
            break
    B = profiles(target, pts, normals, s)
    ncc, contrast = _weighted_ncc(T, B, W)
    ok = (np.abs(s) < SHIFT_MAX_PX) & (ncc > MIN_PROFILE_NCC) & (H > 1e-9)
    return s, ok & (contrast >= MIN_CONTRAST_RATIO)


def _weighted_ncc(a: Array, b: Array, w: Array) -> tuple[Array, Array]:
    """Weighted NCC of the profiles a and b (k, samples), and b's contrast over a's (the
    ratio of their weighted standard deviations)."""
    wn = w / w.sum()
    am = a - np.sum(wn * a, axis=1, keepdims=True)
    bm = b - np.sum(wn * b, axis=1, keepdims=True)
    num = np.sum(wn * am * bm, axis=1)
    var_a, var_b = np.sum(wn * am * am, axis=1), np.sum(wn * bm * bm, axis=1)
    ncc = num / np.maximum(np.sqrt(var_a * var_b), 1e-12)
    return ncc, np.sqrt(var_b / np.maximum(var_a, 1e-24))
