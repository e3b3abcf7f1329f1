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

A moving camera or target smears the image along one direction: an edge across the motion is
soft, one along it sharp, and one Gaussian σ for all of them leaves each wrong (on the bench's
`motion` references, a 1.5 px streak, the estimate drifted 0.03-0.11° from the truth; blurring
the renders by the true streak instead, 0.005-0.04°). So when the single σ is at least
STREAK_SEARCH_PX, the edges are binned by the direction φ of their normal, each bin's σ_φ is
found on the same grid, and σ_φ² = σ₀² + L²/24 + (L²/24) cos 2(φ − θ), fitted linearly, gives
a straight streak of length L along θ after a Gaussian σ₀ (:func:`_streak_guess`); that and its
neighbours are tried on the profiles, and the best is kept when it fits them better than the
single σ (:class:`Blur`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

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
#: Smallest Gaussian σ applied, px; single σ from which a streak (motion blur) is searched
#: for, the streak's directions tried (over 180°) and its shortest length kept, px.
BLUR_MIN_PX = 0.05
STREAK_SEARCH_PX = 0.25
STREAK_ANGLES = 8
STREAK_STEP_RAD = np.pi / 16
STREAK_MIN_PX = 0.6
#: A streak is kept when its profiles' misfit is under this share of the single σ's.
STREAK_GAIN = 0.8


@dataclass(frozen=True)
class Blur:
    """How to blur the render's light to the reference's sharpness: a straight streak of
    ``streak_px`` along ``angle_rad`` (image x right, y down; 0: none), then a Gaussian σ."""

    sigma_px: float = 0.0
    streak_px: float = 0.0
    angle_rad: float = 0.0

    @property
    def active(self) -> bool:
        return self.sigma_px > BLUR_MIN_PX or self.streak_px > 0.0

    def apply(self, img: NDArray[np.float32]) -> NDArray[np.float32]:
        """``img`` (H, W) or (H, W, C) blurred so."""
        if self.streak_px > 0.0:
            img = cv2.filter2D(img, -1, streak_kernel(self.streak_px, self.angle_rad))
        if self.sigma_px > BLUR_MIN_PX:
            # OpenCV samples the Gaussian at whole pixels: below ~0.6 px it spreads less than
            # σ (σ 0.25 → 0.03 px, 0.4 → 0.28, 0.5 → 0.46; exact from 0.75), here and on the
            # measuring grid alike. Kernels of the exact variance were tried and not kept
            # (bench/README.md, "The blur on the pixel grid and through the tone curve").
            img = cv2.GaussianBlur(img, (0, 0), self.sigma_px)
        return img


def blur_change_px(a: Blur, b: Blur) -> float:
    """How far apart two blurs are: the largest difference (px) of their spreads across an
    edge, over the edge's direction φ (the spread of σ and a streak of L along θ across an edge
    of normal φ: √(σ² + L²/24 (1 + cos 2(φ − θ))), as in :func:`_streak_guess`)."""
    phi = np.linspace(0.0, np.pi, STREAK_ANGLES, endpoint=False)

    def spread(x: Blur) -> Array:
        return np.sqrt(x.sigma_px**2 + x.streak_px**2 / 24 * (1 + np.cos(2 * (phi - x.angle_rad))))

    return float(np.max(np.abs(spread(a) - spread(b))))


def streak_kernel(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    """A centred straight streak of ``length_px`` at ``angle_rad``, splatted bilinearly, sum 1."""
    n = 2 * int(np.ceil(0.5 * length_px)) + 3
    s = np.linspace(-0.5 * length_px, 0.5 * length_px, 16 * n)
    x, y = n // 2 + s * np.cos(angle_rad), n // 2 + s * np.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    k = np.zeros((n, n), np.float64)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy),
                      (1, 1, fx * fy)):  # fmt: skip
        np.add.at(k, (y0 + dy, x0 + dx), w)
    return (k / k.sum()).astype(np.float32)


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
    reference's (one σ for every direction). Both are grey, linear, on one tone scale and
    roughly aligned."""
    return _measure(reference_linear, render_linear, streaks=False).sigma_px


def measure_blur(reference_linear: FloatImage, render_linear: FloatImage) -> Blur:
    """The :class:`Blur` that makes the render's edges as soft as the reference's: a Gaussian,
    or a streak and a Gaussian when the reference is smeared along one direction."""
    return _measure(reference_linear, render_linear, streaks=True)


def _measure(reference_linear: FloatImage, render_linear: FloatImage, streaks: bool) -> Blur:
    ref_enc = srgb_encode(reference_linear).astype(np.float32)
    ren = render_linear.astype(np.float32)
    ren_enc = srgb_encode(ren).astype(np.float32)
    pts, n = detect_edge_points(
        local_normalise_f(ren_enc), None, MAX_EDGES, thresholds=EDGE_THRESHOLDS
    )
    if len(pts) < MIN_EDGES:
        return Blur()
    W = profile_grid()[2]

    def misfit_of(
        img: NDArray[np.float32], s: Array | None
    ) -> tuple[Array, Array, NDArray[np.bool_]]:
        s, ok = normal_shift(img, ref_enc, pts, n, s)
        return _misfit(profiles(ref_enc, pts, n, s), profiles(img, pts, n), W), s, ok

    misfits, keep = [], np.ones(len(pts), dtype=bool)
    s = None  # each σ's alignment starts from the last one's (the shifts change little)
    for sigma in BLUR_GRID_PX:
        img = ren_enc if sigma == 0 else srgb_encode(cv2.GaussianBlur(ren, (0, 0), sigma))
        m, s, ok = misfit_of(img.astype(np.float32), s)
        keep &= ok
        misfits.append(m)
    per = np.array(misfits)[:, keep]
    if per.shape[1] < MIN_EDGES:
        return Blur()
    cost = _trimmed(per)
    best = Blur(grid_vertex(cost, int(np.argmin(cost)), BLUR_GRID_PX))
    if not streaks or best.sigma_px < STREAK_SEARCH_PX:
        return best

    def trial(blur: Blur) -> float:
        m, _, ok = misfit_of(srgb_encode(blur.apply(ren)).astype(np.float32), s)
        ok &= keep
        return float(_trimmed(m[ok][None])[0]) if ok.sum() >= MIN_EDGES else np.inf

    guess = _streak_guess(per, n[keep])
    if guess is None:
        return best
    return _streak(trial, guess, best, float(cost.min()))


def _streak_guess(per: Array, normals: Array) -> Blur | None:
    """A streak and a Gaussian from how soft the edges are by the direction of their normal:
    the edges in each of STREAK_ANGLES bins of normal angle φ give a σ_φ (their trimmed
    misfit curve's minimum), and an edge across a streak of length L at angle θ after a
    Gaussian σ₀ is about as soft as a Gaussian of σ_φ² = σ₀² + (L²/12) cos²(φ − θ) =
    σ₀² + L²/24 + (L²/24) cos 2(φ − θ), fitted linearly; None when that is no streak."""
    phi = np.mod(np.arctan2(normals[:, 1], normals[:, 0]), np.pi)
    bins = np.minimum((phi / np.pi * STREAK_ANGLES).astype(int), STREAK_ANGLES - 1)
    rows, var = [], []
    for b in range(STREAK_ANGLES):
        if (bins == b).sum() >= MIN_EDGES // 2:
            curve = _trimmed(per[:, bins == b])
            centre = (b + 0.5) * np.pi / STREAK_ANGLES
            rows.append([1.0, np.cos(2 * centre), np.sin(2 * centre)])
            var.append(grid_vertex(curve, int(np.argmin(curve)), BLUR_GRID_PX) ** 2)
    if len(rows) < 4:
        return None
    alpha, beta, gamma = np.linalg.lstsq(np.array(rows), np.array(var), rcond=None)[0]
    amplitude = float(np.hypot(beta, gamma))  # L² / 24
    length = float(np.sqrt(24.0 * amplitude))
    if length < STREAK_MIN_PX:
        return None
    angle = float(0.5 * np.arctan2(gamma, beta))
    return Blur(float(np.sqrt(max(alpha - amplitude, 0.0))), length, angle)


def _streak(trial: Callable[[Blur], float], guess: Blur, gaussian: Blur, cost: float) -> Blur:
    """The best of ``guess`` and its neighbours (direction ± STREAK_STEP_RAD, length × 0.75
    and × 1.25, and without its Gaussian part) when its streak's variance L²/12 is at least
    its Gaussian's and its trimmed misfit under STREAK_GAIN of ``gaussian``'s (``cost``),
    else ``gaussian``."""
    candidates = [guess]
    for da in (-STREAK_STEP_RAD, STREAK_STEP_RAD):
        candidates.append(Blur(guess.sigma_px, guess.streak_px, guess.angle_rad + da))
    for f in (0.75, 1.25):
        candidates.append(Blur(guess.sigma_px, f * guess.streak_px, guess.angle_rad))
    if guess.sigma_px > BLUR_MIN_PX:
        candidates.append(Blur(0.0, guess.streak_px, guess.angle_rad))
    # A streak that only trims a large Gaussian (a few per cent of its variance; the renders'
    # own edges differ that much by direction) or fits only a little better is no motion blur:
    # on Aura's σ = 1 px references one 0.9 px long fitted 5-7 % better and moved the estimate.
    candidates = [c for c in candidates if c.streak_px**2 / 12.0 >= c.sigma_px**2]
    costs = [trial(c) for c in candidates]
    if not costs or min(costs) >= STREAK_GAIN * cost:
        return gaussian
    return candidates[int(np.argmin(costs))]


def _trimmed(per: Array) -> Array:
    """Per row (a blur), the mean of its TRIM_FRACTION best-fitting profiles' misfits."""
    m = max(int(TRIM_FRACTION * per.shape[1]), 1)
    return np.sort(per, axis=1)[:, :m].mean(axis=1)


def grid_vertex(values: Sequence[float] | Array, i: int, grid: Sequence[float] | Array) -> float:
    """The point ``grid[i]`` of an evenly spaced grid moved to the vertex of the parabola through
    its value and its neighbours' (when they bracket a minimum), within the grid."""
    value = float(grid[i])
    if 0 < i < len(values) - 1:
        c0, c1, c2 = values[i - 1 : i + 2]
        curvature = c0 - 2.0 * c1 + c2
        if curvature > 0:
            value += 0.5 * (c0 - c2) / curvature * float(grid[1] - grid[0])
    return float(np.clip(value, grid[0], grid[-1]))
