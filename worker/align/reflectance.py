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

The reference is divided by a gain computed at the estimated pose, and where the gain steps (a
spacecraft's creases, between faces of other μ) that step sits where the estimate puts the
crease, not where the image shows it; and on a few flat faces (few distinct μ₀, μ) the share is
poorly told apart from the faces' albedos. On the spacecraft of the robustness suite under
`regolith` the estimates got worse (bench/README.md). So by default (``options.reflectance =
"auto"``) the law is fitted only on a smooth body (:func:`smoothness`): one whose shading
normal turns from pixel to pixel almost everywhere it is lit, without leaning far from its
triangles' normals. Measured on the robustness suite's views: Phobos and the bench's asteroid
turn on 0.98-1.0 of their lit pixels and lean at most 9.3° (90th percentile); the demo
satellite turns on 0.004-0.58 (flat panels); Aura shows too few lit pixels at half size to
decide, 0.4-0.7 at full size; ISS turns on 0.96-1.0 but leans 40-47° (its vertex normals were
averaged across its creases). ``"fit"`` fits the law on any target, ``"lambert"`` never.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.session import RenderedView, Session
from worker.engine.images import FloatImage, srgb_decode, srgb_encode, to_grey
from worker.engine.photometry import ToneCurve, on_render_scale, reference_tone_curve
from worker.engine.renderer import Renderer

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
#: Least level of a lit pixel, a fraction of the render's brightest.
LIT_FRACTION = 0.05
#: Smoothing of both images before they are compared (noise, a pixel of misalignment), px.
SMOOTH_PX = 1.5
#: A smooth body: at least this share of its lit pixels has a shading normal that turns by more
#: than TURN_MIN_DEG to the next pixel's (a flat face's normals differ by float rounding; a
#: sphere 10 000 px across turns by 0.018° per pixel). Decided on up to GATE_PIXELS pixels.
CURVED_MIN = 0.9
TURN_MIN_DEG = 0.01
GATE_PIXELS = 2000
#: ... and its shading normals lean from its triangles' by at most this (90th percentile), °:
#: a model whose vertex normals were averaged across its creases (ISS's lean 40-47°) turns
#: everywhere too, but it is a spacecraft (Phobos up to 9.3°, the bench's asteroid 2.3-2.7°).
LEAN_MAX_DEG = 20.0


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


@dataclass(frozen=True)
class Smoothness:
    """How smooth a target looks in a view, from ray casts (:func:`smoothness`): the share of
    its lit pixels whose shading normal turns from the next pixel's, and how far its shading
    normals lean from its triangles' (90th percentile, degrees)."""

    curved: float
    lean_deg: float

    @property
    def smooth_body(self) -> bool:
        return self.curved >= CURVED_MIN and self.lean_deg <= LEAN_MAX_DEG


def smoothness(renderer: Renderer, view: RenderedView) -> Smoothness | None:
    """The :class:`Smoothness` of the pixels ``view``'s render lights (away from the outline),
    from ray casts at up to GATE_PIXELS of them, evenly spread, and at their neighbours right
    and below; None when fewer than MIN_PIXELS are lit."""
    ys, xs = np.nonzero(_inside(_lit(to_grey(view.linear))))
    if len(xs) < MIN_PIXELS:
        return None
    pick = np.unique(np.linspace(0, len(xs) - 1, min(GATE_PIXELS, len(xs))).astype(int))
    uv = np.column_stack([xs[pick], ys[pick]]).astype(np.float64)
    k = len(uv)
    cast = np.vstack([uv, uv + (1.0, 0.0), uv + (0.0, 1.0)])
    n, ok = renderer.surface_normals(view.R, view.t, cast, view.level, view.window)
    g, _ = renderer.surface_normals(view.R, view.t, uv, view.level, view.window, geometric=True)
    n, ok = n.reshape(3, k, 3), ok.reshape(3, k)
    cos_min = np.minimum(np.einsum("ij,ij->i", n[0], n[1]), np.einsum("ij,ij->i", n[0], n[2]))
    seen = ok.all(axis=0)
    if seen.sum() < MIN_PIXELS // 2:
        return None
    lean = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", n[0], g)), 0.0, 1.0)))
    curved = float(np.mean(cos_min[seen] < np.cos(np.radians(TURN_MIN_DEG))))
    return Smoothness(curved, float(np.percentile(lean[seen], 90)))


def law_gain(w: float, angles: Angles) -> NDArray[np.float32]:
    """g_w where the model is seen and sunlit (capped at GAIN_MAX), 1 elsewhere."""
    s = np.maximum(angles.mu0 + angles.mu, 2.0 / GAIN_MAX)
    g = np.minimum((1.0 - w) + w * 2.0 / s, GAIN_MAX)
    return np.where(angles.hit & (angles.mu0 > 0), g, 1.0).astype(np.float32)


def _lit(render: Array) -> NDArray[np.bool_]:
    """The pixels of a render (linear grey) above LIT_FRACTION of its brightest."""
    return render > LIT_FRACTION * float(render.max())


def _inside(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``mask`` without its OUTLINE_MARGIN_PX nearest its outline."""
    side = 2 * OUTLINE_MARGIN_PX + 1
    return cv2.erode(mask.astype(np.uint8), np.ones((side, side), np.uint8)) > 0


def _law_pixels(render: Array, angles: Angles) -> NDArray[np.bool_] | None:
    sel = _inside(angles.hit) & (angles.mu0 > MIN_COSINE) & (angles.mu > MIN_COSINE)
    sel &= _lit(render)
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


def reported_share(w: float | None) -> float:
    """A session's fitted share as the result reports it: 0 when none was fitted or applied."""
    return 0.0 if w is None or w < W_MIN else round(w, 3)


def lambertised(reference_grey: FloatImage, w: float, angles: Angles) -> FloatImage:
    """A reference on the render's scale (display grey) divided by g_w in linear light."""
    return srgb_encode(srgb_decode(reference_grey) / law_gain(w, angles)).astype(np.float32)
