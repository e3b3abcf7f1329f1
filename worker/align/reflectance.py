"""The reflectance law, fitted from the image: Lambert, Lommel–Seeliger, or a mix of the two.

Our renders are Lambertian. Regolith is not: a Lommel–Seeliger-like law, I ∝ μ₀ / (μ₀ + μ),
does not darken towards the limb, so on a body whose features are all shading the reference's
brightness is not one function of the render's, no tone curve maps one onto the other, and
every feature on a shading gradient moves (measured on the bench's held-out asteroid, started at
the truth: 0.16° of drift under a Lommel–Seeliger/Lambert mix, 0.002° under Lambert). So when
the features are made, the model gives each pixel's cosines of incidence and emission (μ₀, μ,
from ray casts at the render's pose), and the share w of the family

    render × g_w,   g_w = (1 − w) + w · 2 / (μ₀ + μ)   (1 at normal incidence and emission)

that, with the tone curve fitted again against it, explains the reference best is found on a
grid and a parabola (:func:`fit_law`; on the asteroid under `regolith`, a 0.7/0.3 mix, it found
w = 0.50–0.54 against the 0.54 of that mix). A free tone curve absorbs most of a law's dependence on
μ₀; what tells the laws apart is the dependence on μ at a given μ₀, so the curve is fitted anew
for each w. With w ≥ W_MIN the reference, on the render's scale, is divided by g_w: it then
shows what a Lambertian surface would, and the features are made and measured on that. A
Lambertian reference gives w = 0 and nothing changes.

Opt-in (``options.reflectance = "fit"``): the reference is divided by a gain computed at the
estimated pose, and where the gain steps (a spacecraft's creases, between faces of other μ)
that step sits where the estimate puts the crease, not where the image shows it; on the
spacecraft of the robustness suite under `regolith` the estimates got worse (bench/README.md).
Smooth untextured bodies are what it is for.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.session import RenderedView, Session
from worker.engine.images import FloatImage, srgb_decode, srgb_encode, to_grey
from worker.engine.photometry import ToneCurve, on_render_scale, reference_tone_curve

Array = NDArray[np.float64]

#: Smallest fitted Lommel–Seeliger share that is applied, and the largest gain g_w.
W_MIN = 0.05
GAIN_MAX = 4.0
#: Fewest pixels that show the law (inside the target, sunlit and seen, lit) for a fit.
MIN_PIXELS = 500
#: Shares tried before the parabola through the best and its neighbours.
LAW_GRID = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
#: Smallest cosines of the pixels the law is fitted on, and their margin from the outline, px.
MIN_COSINE = 0.1
OUTLINE_MARGIN_PX = 3
#: Smoothing of both images before they are compared (noise, a pixel of misalignment), px.
SMOOTH_PX = 1.5


@dataclass(frozen=True)
class Angles:
    """Per pixel of a view's image: the cosines of incidence and emission, and whether the
    pixel shows the model (zeros elsewhere)."""

    mu0: Array
    mu: Array
    hit: NDArray[np.bool_]


@dataclass(frozen=True)
class Law:
    """A fitted law: its Lommel–Seeliger share, the tone curve fitted with it and the reference
    on the render's scale as a Lambertian surface would show it (linear grey)."""

    w: float
    curve: ToneCurve
    reference: FloatImage


def law_angles(session: Session, view: RenderedView) -> Angles:
    """μ₀, μ and the hits over the pixels ``view``'s render lights (ray casts at its pose)."""
    grey = to_grey(view.linear)
    mu0, mu = np.zeros(grey.shape), np.zeros(grey.shape)
    hit = np.zeros(grey.shape, dtype=bool)
    ys, xs = np.nonzero(grey > 0.0)
    if len(xs) == 0:
        return Angles(mu0, mu, hit)
    uv = np.column_stack([xs, ys]).astype(np.float64)
    renderer = session.renderer
    n, ok = renderer.surface_normals(view.R, view.t, uv, view.level, view.window)
    V = -renderer.camera_at(view.level, view.window).rays(uv)
    facing = np.einsum("ij,ij->i", n, V)
    n = np.where((facing < 0)[:, None], -n, n)  # two-sided: the side the camera sees
    mu0[ys, xs] = n @ np.asarray(renderer.lighting.sun_direction, dtype=np.float64)
    mu[ys, xs] = np.abs(facing)
    hit[ys, xs] = ok
    return Angles(mu0, mu, hit)


def law_gain(w: float, angles: Angles) -> NDArray[np.float32]:
    """g_w where the model is seen and sunlit (capped at GAIN_MAX), 1 elsewhere."""
    s = np.maximum(angles.mu0 + angles.mu, 2.0 / GAIN_MAX)
    g = np.minimum((1.0 - w) + w * 2.0 / s, GAIN_MAX)
    return np.where(angles.hit & (angles.mu0 > 0), g, 1.0).astype(np.float32)


def _law_pixels(render: Array, angles: Angles) -> NDArray[np.bool_] | None:
    side = 2 * OUTLINE_MARGIN_PX + 1
    inside = cv2.erode(angles.hit.astype(np.uint8), np.ones((side, side), np.uint8)) > 0
    sel = inside & (angles.mu0 > MIN_COSINE) & (angles.mu > MIN_COSINE)
    sel &= render > 0.05 * float(render.max())
    return sel if sel.sum() >= MIN_PIXELS else None


def _misfit(ref: Array, render: Array, sel: NDArray[np.bool_]) -> float:
    """Mean squared relative difference of the two, smoothed, over ``sel``."""
    a = cv2.GaussianBlur(ref.astype(np.float32), (0, 0), SMOOTH_PX)[sel]
    b = cv2.GaussianBlur(render.astype(np.float32), (0, 0), SMOOTH_PX)[sel]
    return float(np.mean(((a - b) / np.maximum(b, 1e-4)) ** 2))


def fit_law(
    reference: FloatImage, linear: FloatImage, angles: Angles
) -> tuple[Law, list[float]] | None:
    """The law that explains ``reference`` (as the camera gave it) best from ``linear`` (the
    render's light at the reference's sharpness), with the misfits of the grid; None when too
    few pixels show the law."""
    render = to_grey(linear)
    sel = _law_pixels(render, angles)
    if sel is None:
        return None

    def trial(w: float) -> tuple[float, Law]:
        g = law_gain(w, angles)
        curve = reference_tone_curve(reference, linear * g[..., None])
        ref = srgb_decode(on_render_scale(reference, curve))
        return _misfit(ref, render * g, sel), Law(w, curve, (ref / g).astype(np.float32))

    trials = [trial(w) for w in LAW_GRID]
    misfits = [m for m, _ in trials]
    i = int(np.argmin(misfits))
    best = trials[i]
    if 0 < i < len(LAW_GRID) - 1:
        a, b, c = misfits[i - 1 : i + 2]
        if a - 2 * b + c > 0:
            step = LAW_GRID[1] - LAW_GRID[0]
            refined = trial(LAW_GRID[i] + 0.5 * (a - c) / (a - 2 * b + c) * step)
            best = refined if refined[0] < best[0] else best
    return best[1], misfits


def lambertised(reference_grey: FloatImage, w: float, angles: Angles) -> FloatImage:
    """A reference on the render's scale (display grey) divided by g_w in linear light."""
    return srgb_encode(srgb_decode(reference_grey) / law_gain(w, angles)).astype(np.float32)
