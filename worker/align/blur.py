"""How much softer the reference is than our render, measured on aligned edge profiles.

A reference from a real lens, another renderer's pixel filter or a moving camera is softer than
our box-filtered render, and an edge blurred differently in the two images is found at a
different place (an asymmetric edge moves towards its dark side as it blurs). So the render is
blurred to the reference's sharpness before features are measured. The blur is found where it
shows: across edges. At each edge point of the render (a Canny edge, with its normal) the
reference's intensity profile across the edge is aligned to the render's (a shift along the
normal) and compared after a gain and offset fit; the Gaussian σ that, applied to the render's
light, makes the profiles agree best is the relative blur. Aligning each profile first makes it
insensitive to a pose still a few tenths of a pixel off; comparing after gain and offset makes it
insensitive to exposure and tone; the reference's noise adds the same misfit at every σ (only the
render is blurred), so it does not pull the estimate. A reference sharper than the render (our
textures are prefiltered) gives σ = 0.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.edges import detect_edge_points, normal_shift, profile_grid, profiles
from worker.engine.images import FloatImage, srgb_encode
from worker.engine.photometry import local_normalise_f

Array = NDArray[np.float64]

#: Largest relative blur considered, px (Gaussian σ).
BLUR_MAX_PX = 2.0
#: Grid of σ (px) the misfit is evaluated on before a parabola refines the minimum.
BLUR_GRID_PX = np.arange(0.0, BLUR_MAX_PX + 1e-9, 0.25)
#: Edge points used at most, and fewest needed for a measurement.
MAX_EDGES = 800
MIN_EDGES = 20
#: Canny thresholds (fractions of the strongest gradients) of the edges measured: weaker edges
#: than the features' own, since the blur is one number for the whole image.
EDGE_THRESHOLDS = (0.1, 0.25)
#: Fraction of the best-fitting profiles averaged (the rest: occlusions, texture changes).
TRIM_FRACTION = 0.8


def _misfit(a: Array, b: Array, W: Array) -> Array:
    """1 − ρ² of the weighted fit a ≈ g·b + c per profile (the unexplained fraction)."""
    w = W / W.sum()
    am = a - (w * a).sum(1, keepdims=True)
    bm = b - (w * b).sum(1, keepdims=True)
    sab = (w * am * bm).sum(1)
    sbb = (w * bm * bm).sum(1)
    saa = (w * am * am).sum(1)
    return 1.0 - sab**2 / np.maximum(saa * sbb, 1e-12)


def relative_blur(reference_linear: FloatImage, render_linear: FloatImage) -> float:
    """Gaussian σ (px) to apply to the render's light so its edges are as soft as the
    reference's. Both are grey, linear, on one tone scale and roughly aligned."""
    ref_enc = srgb_encode(reference_linear).astype(np.float32)
    ren = render_linear.astype(np.float32)
    ren_enc = srgb_encode(ren).astype(np.float32)
    pts, n = detect_edge_points(
        local_normalise_f(ren_enc), None, MAX_EDGES, thresholds=EDGE_THRESHOLDS
    )
    if len(pts) < MIN_EDGES:
        return 0.0
    W = profile_grid()[2]
    misfits, keep = [], np.ones(len(pts), dtype=bool)
    s = None  # each σ's alignment starts from the last one's (the shifts change little)
    for sigma in BLUR_GRID_PX:
        img = ren_enc if sigma == 0 else srgb_encode(cv2.GaussianBlur(ren, (0, 0), sigma))
        img = img.astype(np.float32)
        s, ok = normal_shift(img, ref_enc, pts, n, s)
        keep &= ok
        misfits.append(_misfit(profiles(ref_enc, pts, n, s), profiles(img, pts, n), W))
    per = np.array(misfits)[:, keep]
    if per.shape[1] < MIN_EDGES:
        return 0.0
    m = int(TRIM_FRACTION * per.shape[1])
    cost = np.sort(per, axis=1)[:, :m].mean(axis=1)
    i = int(np.argmin(cost))
    sigma = float(BLUR_GRID_PX[i])
    if 0 < i < len(cost) - 1:
        c0, c1, c2 = cost[i - 1 : i + 2]
        curvature = c0 - 2.0 * c1 + c2
        if curvature > 0:
            step = float(BLUR_GRID_PX[1] - BLUR_GRID_PX[0])
            sigma += 0.5 * (c0 - c2) / curvature * step
    return float(np.clip(sigma, 0.0, BLUR_MAX_PX))
