"""The reflectance law, fitted from the image: Lambert, Lommel–Seeliger, Oren–Nayar, or a mix.

Our renders are Lambertian. Regolith is not: a Lommel–Seeliger-like law, I ∝ μ₀ / (μ₀ + μ),
does not darken towards the limb, so on a body whose features are all shading the reference's
brightness is not one function of the render's, no tone curve maps one onto the other, and
every feature on a shading gradient moves (measured on the bench's held-out asteroid, started at
the truth: 0.16° of drift under a Lommel–Seeliger/Lambert mix, 0.002° under Lambert). So when
the features are made, the model gives each pixel's cosines of incidence and emission (μ₀, μ,
from ray casts at the render's pose) and Oren–Nayar's geometric term X = max(0, cos Δφ) sin α
tan β, and the share w and roughness c of the family

    render × g,   g = [(1 − w) + w · 2 / (μ₀ + μ)] · (1 + c X)   (1 at normal incidence and
    emission; Oren–Nayar's A + B X over Lambert is A (1 + c X), c = B / A)

that, with the tone curve fitted again against it, explains the reference best is found
(:func:`fit_law`; on the asteroid under `regolith`, a 0.7/0.3 mix, it found w = 0.50–0.54
against the 0.54 of that mix, c = 0; under Oren–Nayar at σ = 40°, c = 0.46–0.52 against 0.54).
A free tone curve absorbs most of a law's dependence on μ₀; what tells the laws apart is the
dependence on μ (and, for Oren–Nayar, on the azimuths) at a given μ₀, so the curve is fitted
anew for each trial. When the law is not Lambert's the reference, on the render's scale, is
divided by g: it then shows what a Lambertian surface would, and the features are made and
measured on that. A Lambertian reference gives w = c = 0 and nothing changes.

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

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.blur import grid_vertex
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
#: Oren–Nayar's c = B / A tried alone (0.37 at a roughness σ of 25°, 0.9 as σ → ∞; the last
#: also bounds the joint fit), and the smallest applied.
ROUGH_GRID = (0.3, 0.6, 0.9)
C_MIN = 0.05
#: The joint law is kept only when its misfit is under this share of the share's alone; the
#: joint refinement's steps at most, its difference step and the step that ends it.
JOINT_GAIN = 0.5
JOINT_STEPS = 4
JOINT_H = 0.05
JOINT_TOL = 0.005
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
    #: Oren–Nayar's geometric term max(0, cos Δφ) sin α tan β (α, β the larger and smaller of
    #: the two angles, Δφ their azimuths' difference about the normal); None: not cast.
    rough: Array | None = None


@dataclass(frozen=True)
class Law:
    """A fitted law: its Lommel–Seeliger share, the tone curve fitted with it and the reference
    on the render's scale as a Lambertian surface would show it (linear grey)."""

    w: float
    curve: ToneCurve
    reference: FloatImage
    c: float = 0.0

    @property
    def shape(self) -> tuple[float, float]:
        """(w, c): what a session keeps of its first fit."""
        return self.w, self.c

    @property
    def lambert(self) -> bool:
        """Whether the fit found Lambert (nothing applied)."""
        return is_lambert(self.shape)


def is_lambert(shape: tuple[float, float]) -> bool:
    """Whether a law's (w, c) is Lambert's: neither part large enough to be applied."""
    return shape[0] < W_MIN and shape[1] < C_MIN


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
    L = np.asarray(renderer.lighting.sun_direction, dtype=np.float64)
    mu0[ys, xs] = n @ L
    mu[ys, xs] = np.abs(facing)
    hit[ys, xs] = ok
    rough = np.zeros(grey.shape)
    rough[ys, xs] = oren_nayar_term(n, L, V)
    return Angles(mu0, mu, hit, rough)


def oren_nayar_term(n: Array, L: Array, V: Array) -> Array:
    """Oren–Nayar's max(0, cos Δφ) sin α tan β per row of unit normals ``n`` (k, 3) and view
    directions ``V`` (k, 3), for the sun direction ``L`` (3,)."""
    mu0, mu_signed = n @ L, np.einsum("ij,ij->i", n, V)
    li, lv = L[None] - mu0[:, None] * n, V - mu_signed[:, None] * n
    norm = np.linalg.norm(li, axis=1) * np.linalg.norm(lv, axis=1)
    cos_phi = np.einsum("ij,ij->i", li, lv) / np.maximum(norm, 1e-12)
    mu0, mu = np.clip(mu0, 0.0, 1.0), np.clip(np.abs(mu_signed), 0.0, 1.0)
    lo, hi = np.minimum(mu0, mu), np.maximum(mu0, mu)  # cos α, cos β
    tan_beta = np.sqrt(1.0 - hi**2) / np.maximum(hi, 1e-3)
    return np.clip(cos_phi, 0.0, None) * np.sqrt(1.0 - lo**2) * tan_beta


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


def law_gain(w: float, angles: Angles, c: float = 0.0) -> NDArray[np.float32]:
    """g_w (× Oren–Nayar's 1 + c X) where the model is seen and sunlit (capped at GAIN_MAX),
    1 elsewhere."""
    s = np.maximum(angles.mu0 + angles.mu, 2.0 / GAIN_MAX)
    g = (1.0 - w) + w * 2.0 / s
    if c > 0.0 and angles.rough is not None:
        g = g * (1.0 + c * angles.rough)
    g = np.minimum(g, GAIN_MAX)
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


def _residuals(ref: Array, render: Array, sel: NDArray[np.bool_]) -> Array:
    """Relative differences of the two, smoothed, over ``sel`` (their mean square: the misfit)."""
    a = cv2.GaussianBlur(ref.astype(np.float32), (0, 0), SMOOTH_PX)[sel]
    b = cv2.GaussianBlur(render.astype(np.float32), (0, 0), SMOOTH_PX)[sel]
    return ((a - b) / np.maximum(b, 1e-4)).astype(np.float64)


def fit_law(
    reference: FloatImage, linear: FloatImage, angles: Angles
) -> tuple[Law, list[float]] | None:
    """The law that explains ``reference`` (as the camera gave it) best from ``linear`` (the
    render's light at the reference's sharpness), with the misfits of the share's grid; None
    when too few pixels show the law. The share w is searched on a grid (c = 0) and Oren–Nayar
    alone (w = 0) on another; when the latter fits better, Gauss–Newton steps refine w and c
    together from there (the two trade off along a valley, so a search in one then the other
    stops on its floor), and that law is kept when its misfit is under JOINT_GAIN of the share's
    alone (a second parameter also fits some of the tone curve's and the noise's error: on the
    bench's `regolith` references a joint fit lowered the misfit by up to 40 % and moved w
    from the 0.5 it recovers alone; on Oren–Nayar references, σ = 40°, by 2-50×).
    """
    render = to_grey(linear)
    sel = _law_pixels(render, angles)
    if sel is None:
        return None
    tried: dict[tuple[float, float], _Trial] = {}

    def trial(w: float, c: float) -> _Trial:
        key = (round(w, 6), round(c, 6))
        if key not in tried:
            g = law_gain(w, angles, c)
            curve = reference_tone_curve(reference, linear * g[..., None])
            ref = srgb_decode(on_render_scale(reference, curve))
            law = Law(w, curve, (ref / g).astype(np.float32), c)
            r = _residuals(ref, render * g, sel)
            tried[key] = _Trial(float(np.mean(r**2)), law, r)
        return tried[key]

    law, misfits = _search(lambda w: trial(w, 0.0), LAW_GRID)
    lommel = trial(law.w, 0.0)
    rough = min((trial(0.0, c) for c in ROUGH_GRID), key=lambda t: t.misfit)
    if rough.misfit >= lommel.misfit:
        return law, misfits
    joint = _joint(trial, rough.law)
    return (joint if trial(joint.w, joint.c).misfit < JOINT_GAIN * lommel.misfit else law), misfits


@dataclass(frozen=True)
class _Trial:
    misfit: float
    law: Law
    residuals: Array


def _search(trial: Callable[[float], _Trial], grid: tuple[float, ...]) -> tuple[Law, list[float]]:
    """The best of ``trial`` over an evenly spaced ``grid`` and a parabola through the best
    and its neighbours, with the grid's misfits."""
    trials = [trial(x) for x in grid]
    misfits = [t.misfit for t in trials]
    i = int(np.argmin(misfits))
    vertex = grid_vertex(misfits, i, grid)
    if vertex == grid[i]:  # no parabola (the best at the grid's end): nothing to try again
        return trials[i].law, misfits
    refined = trial(vertex)
    return (refined if refined.misfit < trials[i].misfit else trials[i]).law, misfits


def _joint(trial: Callable[[float, float], _Trial], law: Law) -> Law:
    """(w, c) refined from ``law`` by bounded Gauss–Newton steps on the residuals (forward
    differences), each kept only when it lowers the misfit."""
    hi = np.array([LAW_GRID[-1], ROUGH_GRID[-1]])
    x = np.array([law.w, law.c])
    now = trial(*x)
    for _ in range(JOINT_STEPS):
        cols = []
        for k in range(2):
            h = np.zeros(2)
            h[k] = JOINT_H if x[k] + JOINT_H <= hi[k] else -JOINT_H
            cols.append((trial(*(x + h)).residuals - now.residuals) / h[k])
        J = np.column_stack(cols)
        free = np.ones(2, dtype=bool)
        for _ in range(2):  # a parameter at a bound that the step would push out stays there
            dx = np.zeros(2)
            dx[free] = np.linalg.lstsq(J[:, free], -now.residuals, rcond=None)[0]
            out = ((x <= 0.0) & (dx < 0.0)) | ((x >= hi) & (dx > 0.0))
            if not out.any():
                break
            free &= ~out
        step = np.clip(x + dx, 0.0, hi) - x
        for _ in range(3):  # halved while it does not lower the misfit
            if not free.any() or np.abs(step).max() < JOINT_TOL:
                return now.law
            new = trial(*(x + step))
            if new.misfit < now.misfit:
                break
            step = 0.5 * step
        else:
            return now.law
        x, now = x + step, new
    return now.law


def reported_law(shape: tuple[float, float] | None) -> tuple[float, float]:
    """A session's first fitted law (w, c) as the result reports it, (w, Oren–Nayar roughness
    σ in degrees): (0, 0) when none was fitted or applied."""
    if shape is None or is_lambert(shape):
        return 0.0, 0.0
    return round(shape[0], 3), round(roughness_deg(shape[1]), 1)


def roughness_deg(c: float) -> float:
    """Oren–Nayar's roughness σ (degrees) whose B / A is ``c`` (0 below C_MIN; 90 from 0.78)."""
    if c < C_MIN:
        return 0.0
    sigma = np.radians(np.linspace(0.0, 90.0, 901))
    s2 = sigma**2
    ratio = 0.45 * s2 / (s2 + 0.09) / (1.0 - 0.5 * s2 / (s2 + 0.33))
    return float(np.degrees(np.interp(c, ratio, sigma)))


def lambertised(reference_grey: FloatImage, w: float, angles: Angles, c: float = 0.0) -> FloatImage:
    """A reference on the render's scale (display grey) divided by the law's gain in linear
    light."""
    gain = law_gain(w, angles, c)
    return srgb_encode(srgb_decode(reference_grey) / gain).astype(np.float32)
