"""Photometry: bringing a camera's reference and our linear renders onto one scale.

The reference comes from a real camera or another renderer (unknown exposure, gamma, colour
response, blur, noise); the render is linear radiance from our own lights. Everything that
compares the two goes through here: the render's grey, the reference mapped onto the render's
tone scale (:func:`reference_on_render_scale`), local contrast normalisation for tracking, and
the alignment score. (Matching the two images' sharpness needs edges: ``worker.align.blur``.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.engine.images import Box, FloatImage, srgb_decode, to_display, to_grey

U8 = NDArray[np.uint8]

#: Blur applied before corners and KLT, px (sensor noise and render noise).
DENOISE_SIGMA_PX = 0.8
#: Smoothing before the alignment score, px.
SCORE_SMOOTH_PX = 1.5
#: Tone-curve fit: quantile bins and the smoothing applied before comparing pixels, px.
TONE_BINS = 48
TONE_SMOOTH_PX = 1.5
#: Knots are added by rank above the curve's last one (see _rank_knots_above) when more than
#: TONE_TOP_SHARE of the render's pixels lie above it and its TONE_TOP_QUANTILE level is over
#: TONE_TOP_RATIO × the last knot's; TONE_TOP_KNOTS of them, up to that quantile.
TONE_TOP_SHARE = 0.01
TONE_TOP_RATIO = 2.0
TONE_TOP_KNOTS = 8
TONE_TOP_QUANTILE = 0.999
#: Dark pixels the tone curve needs to anchor its foot on them (a target filling the frame
#: with no sky or shadow leaves none: the curve is then fitted on the lit levels alone).
MIN_SKY_PX = 50
#: Local contrast normalisation window (px) and the 8-bit gain of one local σ.
LCN_SIGMA_PX = 4.0
LCN_GAIN = 40.0
LCN_FLOOR = 0.3
#: How far (px) the blurs of local contrast normalisation reach, chained: 3 σ of each of the
#: reference-sharpness blur (≤ worker.align.blur.BLUR_MAX_PX), DENOISE_SIGMA_PX and LCN_SIGMA_PX
#: twice is 32 px; OpenCV's float kernels end at 4 σ (43 px), and a sky window adds its own
#: margin (≥ 8 px of sky on each side of the target). The margin a box of a render on the sky
#: needs for its normalisation to equal the whole image's.
BLUR_REACH_PX = 40


def render_to_grey(render_linear: FloatImage) -> FloatImage:
    """Display-encoded grey [0, 1] of a linear render: the light is averaged over the channels
    first, then encoded (see :func:`reference_on_render_scale` for why the order matters)."""
    return to_display(to_grey(render_linear))


def match_histogram(source: FloatImage, template: FloatImage, bins: int = 4096) -> FloatImage:
    """Map ``source`` monotonically so its grey-level distribution equals ``template``'s."""
    s_hist, edges = np.histogram(source, bins=bins, range=(0.0, 1.0))
    t_hist, _ = np.histogram(template, bins=bins, range=(0.0, 1.0))
    s_cdf = np.cumsum(s_hist).astype(np.float64) / max(source.size, 1)
    t_cdf = np.cumsum(t_hist).astype(np.float64) / max(template.size, 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    mapping = np.interp(s_cdf, t_cdf, centres)
    idx = np.clip((source * bins).astype(np.int64), 0, bins - 1)
    return mapping[idx].astype(np.float32)


def fit_tone_curve(
    reference: FloatImage, render: FloatImage, bins: int = TONE_BINS
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A monotone map (knots x → y) from reference grey levels to the render's, fitted on
    corresponding pixels of two roughly aligned images.

    Pixels are compared after smoothing and only where the render is locally flat, so a
    misalignment of a pixel or two does not matter. The knots bin the *render* (noise-free)
    levels by quantile and take the median reference level in each bin: binning by the noisy
    image instead would flatten the curve (regression dilution) and bend every edge. Unlike
    histogram matching, a few occluded pixels do not bend it either. A difference in sharpness
    does: the light a softer reference spreads into the render's flat dark parts lowers the
    curve's foot, so the render should be at the reference's sharpness (worker.align.tracked
    fits the curve again once it has measured the blur).
    """
    a = cv2.GaussianBlur(reference.astype(np.float32), (0, 0), TONE_SMOOTH_PX)
    b = cv2.GaussianBlur(render.astype(np.float32), (0, 0), TONE_SMOOTH_PX)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1)
    grad = np.hypot(gx, gy)
    lit = b > 0.02 * float(b.max())
    if lit.sum() < 50:
        return np.array([0.0, 1.0]), np.array([0.0, 1.0])
    flat = lit & (grad <= np.percentile(grad[lit], 50))
    av, bv = a[flat].astype(np.float64), b[flat].astype(np.float64)
    edges = np.unique(np.quantile(bv, np.linspace(0.0, 1.0, bins + 1)))
    idx = np.clip(np.searchsorted(edges, bv, side="right") - 1, 0, len(edges) - 2)
    ref_level, render_level = [], []
    anchored = (~lit).sum() >= MIN_SKY_PX
    if anchored:  # the dark sky (or shadow) anchors the curve's foot
        ref_level, render_level = [float(np.median(a[~lit]))], [0.0]
    for k in range(len(edges) - 1):
        sel = idx == k
        if sel.sum() >= 10:
            ref_level.append(float(np.median(av[sel])))
            render_level.append(float(np.median(bv[sel])))
    if not anchored:  # a scene that fills the frame (see _rank_knots_above)
        _rank_knots_above(a[lit], b[lit], ref_level, render_level)
    if len(ref_level) < 2:
        return np.array([0.0, 1.0]), np.array([0.0, 1.0])
    x = np.maximum.accumulate(np.asarray(ref_level))
    x = x + 1e-6 * np.arange(len(x))  # strictly increasing for interpolation
    return x, np.maximum.accumulate(np.asarray(render_level))


def _rank_knots_above(
    ref: NDArray[np.float32],
    render: NDArray[np.float32],
    ref_level: list[float],
    render_level: list[float],
) -> None:
    """Extend the knots (in place) by rank above the flat pixels' range when it leaves out
    much of the render's (TONE_TOP_SHARE of its pixels, up to TONE_TOP_RATIO × its level).

    The flat pixels can miss the bright levels: over terrain at a low sun nearly all of them
    are shadow lit by the ambient light, and the lit ground (a quarter of the image, every
    pixel of it on a slope or an edge) has too few to fill a bin. The curve then ends at a
    shadow level and maps the whole lit ground onto it: the reference went flat and not one
    feature matched. Above the last knot the two images are matched by rank instead (the
    same share of their pixels above each level), which needs them only roughly aligned.
    Only for a scene with no dark sky or shadow to anchor the curve's foot: a target on the
    sky keeps the knots as measured (a small one's curve can end below its brightest levels
    too, and rank knots there changed the tracker's sequences; measured 2026-12-03)."""
    top = render_level[-1] if render_level else 0.0
    share = float(np.mean(render > top))
    if share <= TONE_TOP_SHARE or np.quantile(render, TONE_TOP_QUANTILE) <= TONE_TOP_RATIO * top:
        return
    last_x = ref_level[-1] if ref_level else -np.inf  # no bin may have filled
    for q in np.linspace(1.0 - share, TONE_TOP_QUANTILE, TONE_TOP_KNOTS + 1)[1:]:
        x, y = float(np.quantile(ref, q)), float(np.quantile(render, q))
        if y > top and x > last_x:
            ref_level.append(x)
            render_level.append(y)
            top, last_x = y, x


def reference_on_render_scale(reference: FloatImage, render_linear: FloatImage) -> FloatImage:
    """The reference as a display-encoded grey image on the render's tone scale.

    One monotone curve (the camera's response relative to our sRGB encoding) is fitted on the
    pixels of all channels pooled, applied to each channel, decoded to light, averaged over the
    channels and encoded again — exactly how :func:`render_to_grey` makes the render's grey. A
    curve fitted on grey values instead cannot be right for every colour at once (the mean of
    gamma-encoded channels is not a function of the mean of sRGB-encoded ones), and its error
    moves the edges between differently coloured materials.
    """
    curve = reference_tone_curve(reference, render_linear)
    if render_linear.ndim == 2:
        return apply_tone_curve(to_grey(reference), curve)
    return on_render_scale(reference, curve)


ToneCurve = tuple[NDArray[np.float64], NDArray[np.float64]]


def reference_tone_curve(reference: FloatImage, render_linear: FloatImage) -> ToneCurve:
    """The curve of :func:`reference_on_render_scale`: fitted on every channel's pixels pooled
    (on the grey of each when either image is grey). The two images may be reduced alike
    first: the curve is a property of the camera, not of the image's size."""
    if reference.ndim == 2 or render_linear.ndim == 2:
        return fit_tone_curve(to_grey(reference), render_to_grey(render_linear))
    ref_c = np.moveaxis(reference[..., :3], -1, 0)
    ren_c = np.moveaxis(to_display(render_linear[..., :3]), -1, 0)
    return fit_tone_curve(np.concatenate(ref_c, axis=0), np.concatenate(ren_c, axis=0))


def on_render_scale(reference: FloatImage, curve: ToneCurve) -> FloatImage:
    """The reference through ``curve`` (from :func:`reference_tone_curve` with a colour
    render), as display-encoded grey on the render's tone scale."""
    if reference.ndim == 2:
        return apply_tone_curve(reference, curve)
    light = srgb_decode(apply_tone_curve(reference[..., :3], curve))
    return to_display(to_grey(light))


def apply_tone_curve(
    image: FloatImage, curve: tuple[NDArray[np.float64], NDArray[np.float64]]
) -> FloatImage:
    x, y = curve
    return np.interp(image, x, y).astype(np.float32)


def alignment_score(
    reference_grey: FloatImage, render_grey: FloatImage, box: Box | None = None
) -> float:
    """How well a render explains the reference: zero-mean normalised cross-correlation of the
    two (reference histogram-matched onto the render, both smoothed) over where either shows
    the target. 1 is a perfect match; it needs no features, so it can referee feature-based
    steps. ``box``: score only that part of the images (the target's)."""
    if box is not None:
        reference_grey, render_grey = box.of(reference_grey), box.of(render_grey)
    ref = match_histogram(reference_grey, render_grey)
    a = cv2.GaussianBlur(ref, (0, 0), SCORE_SMOOTH_PX)
    b = cv2.GaussianBlur(render_grey.astype(np.float32), (0, 0), SCORE_SMOOTH_PX)
    mask = (content_mask(to_u8(a, 1.0)) > 0) | (content_mask(to_u8(b, 1.0)) > 0)
    if mask.sum() < 16:
        return -1.0
    return zncc(a[mask], b[mask])


def zncc(a: NDArray[np.floating], b: NDArray[np.floating]) -> float:
    """Zero-mean normalised cross-correlation of two arrays of one shape (1: equal up to a
    gain and an offset)."""
    a, b = a - a.mean(), b - b.mean()
    return float(np.sum(a * b) / max(np.sqrt(np.sum(a * a) * np.sum(b * b)), 1e-12))


def to_u8(grey: FloatImage, white: float) -> U8:
    """Scale so that ``white`` maps to 255, and quantise."""
    return (np.clip(grey / max(white, 1e-6), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class NormalisedPair:
    """Reference and render on one 8-bit scale; ``*_smooth`` are denoised for corners/KLT."""

    ref: U8
    render: U8
    ref_smooth: U8
    render_smooth: U8


def normalise_pair(reference_grey: FloatImage, render_grey: FloatImage) -> NormalisedPair:
    """Bring a reference and a render (both grey, display-encoded) onto one 8-bit scale."""
    ref = match_histogram(reference_grey, render_grey)
    white = float(np.percentile(render_grey, 99.9)) or float(render_grey.max()) or 1.0
    ref8, ren8 = to_u8(ref, white), to_u8(render_grey, white)
    return NormalisedPair(ref8, ren8, smooth(ref8), smooth(ren8))


def normalise_render(render_grey: FloatImage, white: float) -> U8:
    """A further render on an existing pair's scale (same white point), denoised."""
    return smooth(to_u8(render_grey, white))


def contrast_scale(
    grey: FloatImage, sigma_px: float = LCN_SIGMA_PX, box: Box | None = None
) -> FloatImage:
    """The divisor of :func:`local_normalise`: local standard deviation plus a floor.

    ``box``: ``grey`` is flat (the sky) outside that part, far enough from what it shows for
    the blurs not to reach (a render's window grown by :data:`BLUR_REACH_PX`): only the box is
    computed, and the rest set to what the whole image's computation gives there, the floor.
    """
    part = grey if box is None else box.of(grey)
    g = cv2.GaussianBlur(part.astype(np.float32), (0, 0), DENOISE_SIGMA_PX)
    d = g - cv2.GaussianBlur(g, (0, 0), sigma_px)
    std = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px))
    flat = 0 if box is None else grey.shape[0] * grey.shape[1] - std.size
    floor = LCN_FLOOR * _percentile_above_zeros(std, 99.0, flat)
    scale = std + floor + 1e-6
    return scale if box is None else box.paste(scale, grey.shape, np.float32(0) + floor + 1e-6)


def _percentile_above_zeros(values: FloatImage, q: float, zeros: int) -> float:
    """``np.percentile`` of ``values`` and ``zeros`` more zeros (``values`` ≥ 0), without
    making them: the rank q % of the way through all of them, read among ``values``."""
    if zeros == 0:
        return float(np.percentile(values, q))
    rank = q / 100.0 * (values.size + zeros - 1) - zeros
    if rank <= 0.0:
        return 0.0
    return float(np.percentile(values, 100.0 * rank / max(values.size - 1, 1)))


def local_normalise_f(
    grey: FloatImage,
    scale: FloatImage | None = None,
    sigma_px: float = LCN_SIGMA_PX,
    box: Box | None = None,
) -> FloatImage:
    """Local contrast normalisation, (I − G∗I) / s, in local standard deviations (float).

    It removes what differs slowly between a reference and a render — exposure, gamma, the
    shading ramp of a sun a few degrees off, inter-reflections — and keeps the local structure
    KLT aligns, so tracking between them behaves like normalised cross-correlation. ``scale``
    (from :func:`contrast_scale` of the noise-free render) should be shared by the two images:
    a scale measured on a noisy reference is inflated most where the signal (and its shot
    noise) is strongest, which pulls every edge towards its bright side.

    ``box``: only that part is computed (see :func:`contrast_scale`), 0 elsewhere: exact for
    a render on the sky, for a reference what it shows there is left out.
    """
    part = grey if box is None else box.of(grey)
    g = cv2.GaussianBlur(part.astype(np.float32), (0, 0), DENOISE_SIGMA_PX)
    d = g - cv2.GaussianBlur(g, (0, 0), sigma_px)
    s = contrast_scale(grey, sigma_px, box) if scale is None else scale
    out = (d / (s if box is None else box.of(s))).astype(np.float32)
    return out if box is None else box.paste(out, grey.shape)


def local_normalise(
    grey: FloatImage, scale: FloatImage | None = None, sigma_px: float = LCN_SIGMA_PX
) -> U8:
    """:func:`local_normalise_f` as 8-bit around 128 (for OpenCV's KLT)."""
    return normalised_to_u8(local_normalise_f(grey, scale, sigma_px))


def normalised_to_u8(normalised: FloatImage, box: Box | None = None) -> U8:
    """A :func:`local_normalise_f` image as :func:`local_normalise` gives it (``box``: the
    part it shows, 0 elsewhere)."""
    part = normalised if box is None else box.of(normalised)
    out = np.clip(128.0 + LCN_GAIN * part, 0, 255).astype(np.uint8)
    return out if box is None else box.paste(out, normalised.shape, 128)


def smooth(img: U8) -> U8:
    return cv2.GaussianBlur(img, (0, 0), DENOISE_SIGMA_PX)


# -- descriptor matching -----------------------------------------------------------------


def content_mask(img: U8, dilate_px: int = 4) -> U8:
    """Pixels showing the target (above the dark background), dilated; 255 inside."""
    level = max(3, int(0.03 * float(np.percentile(img, 99.5))))
    mask = (img > level).astype(np.uint8) * 255
    if dilate_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1,) * 2)
        mask = cv2.dilate(mask, k)
    return mask
