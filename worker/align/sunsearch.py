"""A search for the sun by the pattern of what it lights, for scenes that fill the frame.

Over terrain at a low sun most of the image is cast shadow, and which ground is lit moves far
with a sun a few degrees off: at 5–10° above the horizon a 3° error lights ground the reference
shows dark and darkens ground it shows lit. The features then find little in common between the
render and the reference, and the refinement's sun fit (:mod:`worker.align.sunfit`), which
measures the sun through the features, has nothing to work with. The lit pattern itself is
geometry (where shadows fall), so it is compared directly: at the coarse stage's pose, renders
with the sun tilted are thresholded into lit and dark, the reference into the same share of lit
pixels by rank (any exposure, gamma or reflectance law keeps the order of the levels that
matters: lit above shadow), and a compass search over the tilt maximises the correlation of the
two (slightly blurred) masks. The refinement's sun fit starts from the result.

The search runs twice. Before the coarse stage the pose is still a few degrees off, so the
reference's pattern lies tens of pixels from the render's: each pattern is compared at the
image shift that aligns it best (shifted_pattern_score), and the sun found is held fixed on the
model while the coarse stage moves the pose (search_sun_before_coarse). After the coarse stage
the patterns are compared where they are.

Measured on the bench's terrain cases (sun 3° off): at a 4–10° sun the search after the coarse
stage brought it within 0.16–0.6° of the true one; the worst fractal case at a 5–15° sun went
from 0.14° to 0.04°. The search before it: see the README's terrain section.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.session import RenderedView, Session
from worker.align.sunfit import SunTilt
from worker.engine.exceptions import TooFewFeaturesError
from worker.engine.photometry import zncc

Array = NDArray[np.float64]
T = TypeVar("T")

#: Compass steps of the tilt, degrees (each tried along ±e1, ±e2 until none improves).
STEPS_DEG = (2.0, 1.0, 0.5)
#: Renders after which the search stops (it finishes the four tries around a centre, so it
#: may make up to three more).
MAX_RENDERS = 28
#: Gaussian σ (px) of the masks before they are compared (a pose a pixel off still matches).
MASK_BLUR_PX = 2.0
#: Least share of the image the model must cover (at the pose) for the search to run: a target
#: on the sky is left to the features' sun fit.
MIN_COVERAGE = 0.95
#: Least share of the render on the dark side of its lit/dark split for the search to run (a
#: render with hardly any shadow has no pattern to compare; terrain at a 25–45° sun mostly
#: passes, and there the search moved no estimate by more than 0.002°).
MIN_SHADOW_FRACTION = 0.25
#: Smallest gain of the correlation that moves the sun.
MIN_GAIN = 0.01
#: Before the coarse stage: how far the reference's lit pattern may lie from the render's, a
#: fraction of the image's shorter side (an initial pose a few degrees off moves terrain seen
#: from 600 m by tens of pixels), and the renders that search may make (the sun may be the
#: request's error plus the pose's away, so it walks further).
MAX_SHIFT_FRACTION = 0.25
UNALIGNED_MAX_RENDERS = 40
#: Tilts of the sun from the request's (degrees; eight directions each, the smallest that
#: lights anything wins) tried when the render at the initial pose shows no sunlit ground.
LIGHT_UP_TILTS_DEG = (2.0, 4.0, 6.0)


def lit_mask(grey: Array) -> tuple[NDArray[np.bool_], float]:
    """The lit pixels of a (noise-free) render by Otsu's threshold, and their share."""
    u8 = np.clip(grey / max(float(grey.max()), 1e-6) * 255.0, 0, 255).astype(np.uint8)
    level, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = u8 > level
    return mask, float(mask.mean())


def _masks(render_grey: Array, ref_smooth: Array) -> tuple[Array, Array] | None:
    """The render's lit mask and the reference's brightest pixels of the same share, blurred
    by MASK_BLUR_PX (None when the render is all lit or all dark)."""
    mask, lit = lit_mask(render_grey)
    if not 0.0 < lit < 1.0:
        return None
    ref_mask = ref_smooth > np.quantile(ref_smooth, 1.0 - lit)
    a = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), MASK_BLUR_PX)
    b = cv2.GaussianBlur(ref_mask.astype(np.float32), (0, 0), MASK_BLUR_PX)
    return a, b


def pattern_score(render_grey: Array, ref_smooth: Array) -> float:
    """Correlation of the render's lit mask with the reference's brightest pixels of the
    same share (blurred by MASK_BLUR_PX)."""
    masks = _masks(render_grey, ref_smooth)
    return -1.0 if masks is None else zncc(*masks)


def shifted_pattern_score(render_grey: Array, ref_smooth: Array, max_shift_px: int) -> float:
    """pattern_score at the image shift (within ``max_shift_px`` each way) that aligns the two
    masks best: the pattern's likeness whatever the pose's error moves it by. The correlation
    is normalised over the whole masks, so a larger shift (less overlap) scores lower."""
    masks = _masks(render_grey, ref_smooth)
    if masks is None:
        return -1.0
    a, b = (m - m.mean() for m in masks)
    h, w = a.shape
    shape = (2 * h, 2 * w)  # zero-padded: no wrap-around
    corr = np.fft.irfft2(np.fft.rfft2(a, shape) * np.conj(np.fft.rfft2(b, shape)), shape)
    m = int(max_shift_px)
    rows = np.r_[0 : m + 1, shape[0] - m : shape[0]]
    cols = np.r_[0 : m + 1, shape[1] - m : shape[1]]
    best = float(corr[np.ix_(rows, cols)].max())
    return best / max(float(np.sqrt(np.sum(a * a) * np.sum(b * b))), 1e-12)


def _fills_frame(session: Session) -> bool:
    """Whether the model covers at least MIN_COVERAGE of the image at the session's pose."""
    return session.renderer.coverage(session.R, session.t) >= MIN_COVERAGE


def _smoothed_reference(session: Session) -> NDArray[np.float32]:
    """The reference's grey at the session's level, lightly smoothed (its noise), as
    pattern_score compares it."""
    return cv2.GaussianBlur(session.ref_grey.astype(np.float32), (0, 0), 1.0)


def search_sun(session: Session, aligned: bool = True) -> bool:
    """Tilt the renderer's sun to the one whose lit pattern best matches the reference's, at
    the session's pose and level; returns whether it moved. Runs only for a scene that fills
    the frame (MIN_COVERAGE) and whose render at the current sun is at least
    MIN_SHADOW_FRACTION in shadow. ``aligned=False`` (before the coarse stage, the pose still
    off): each pattern is compared at the image shift that aligns it best
    (shifted_pattern_score)."""
    if not _fills_frame(session):
        return False
    view = session.current_view()
    if view.window is not None or lit_mask(view.grey)[1] > 1.0 - MIN_SHADOW_FRACTION:
        return False
    ref = _smoothed_reference(session)
    if ref.shape != view.grey.shape:
        return False
    if aligned:
        score_of, max_renders = pattern_score, MAX_RENDERS
    else:
        shift = int(MAX_SHIFT_FRACTION * min(ref.shape))
        score_of = partial(shifted_pattern_score, max_shift_px=shift)
        max_renders = UNALIGNED_MAX_RENDERS
    sun = SunTilt(session)
    start = sun.ab.copy()
    best_ab, best = start, score_of(view.grey, ref)
    first = best
    renders = 0
    for step_deg in STEPS_DEG:
        step = np.tan(np.radians(step_deg))
        moved = True
        while moved and renders < max_renders:
            moved = False
            centre = best_ab
            for d in ((step, 0.0), (-step, 0.0), (0.0, step), (0.0, -step)):
                ab = sun.clip(centre + np.array(d))
                sun.set(ab)
                score = score_of(session.render_view(session.R, session.t).grey, ref)
                renders += 1
                if score > best:
                    best_ab, best, moved = ab, score, True
    if best - first < MIN_GAIN:
        sun.set(start)
        return False
    sun.set(best_ab)
    session.current = None  # rendered with the old sun
    return True


def search_sun_before_coarse(session: Session) -> bool:
    """The sun searched at the initial pose, each pattern compared at its best image shift,
    then held fixed in the model frame (Renderer.hold_sun) while the coarse stage moves the
    pose; returns whether it moved (release_sun lets it go).

    Why held: the sun is given in the camera frame, so the initial pose's error tilts it
    against the ground by as much. Over terrain at a 3–6° sun a start 5° off put it below
    the horizon, and the sun the search finds there (the camera-frame sun that lights the
    reference's pattern at that pose) lights that pattern only at that attitude: once PnP
    corrects the pose it would tilt away again, with the pose's correction.
    """
    if not search_sun(session, aligned=False):
        return False
    sun = np.asarray(session.renderer.lighting.sun_direction, dtype=np.float64)
    session.renderer.hold_sun(np.asarray(session.R).T @ sun)
    return True


def coarse_under_searched_sun(session: Session, coarse: Callable[[], T]) -> T:
    """``coarse()`` (the coarse stage) under the sun search_sun_before_coarse finds, held
    while it runs and let go after (release_sun).

    When the search moved the sun and the stage still finds too few features, the stage runs
    again from where it started (pose, level, samples) with the sun as it was: at a sun a few
    degrees above ridged terrain, where ~2 % of the frame is lit, the pattern's likeness has
    false maxima, and the search climbed to one (0.49 where the true sun scores 0.60) whose
    render lit other ridge tops than the reference; PnP found no match at either level and the
    estimate failed (`proxpose bench --terrain --sun-elevation 6,12 --seed 41`, the ridged
    terrain's third case). Again under the request's sun it ends 0.16° off.
    """
    lighting, pose = session.renderer.lighting, (session.R, session.t)
    level, spp = session.level, session.stage_spp
    try:
        if not search_sun_before_coarse(session):
            return coarse()
        try:
            return coarse()
        except TooFewFeaturesError:
            session.renderer.set_lighting(lighting)  # (lets the held sun go)
            session.R, session.t = pose
            session.set_level(level)
            session.stage_spp, session.current, session.fit = spp, None, None
            return coarse()
    finally:
        release_sun(session)


def release_sun(session: Session) -> None:
    """Let a sun held by search_sun_before_coarse turn with the camera again, from the
    session's pose (whose render keeps its lighting)."""
    session.renderer.release_sun(session.R)


def light_up(session: Session, lit: Callable[[RenderedView], bool]) -> bool:
    """Over a scene that fills the frame, make the render at the initial pose sunlit when it
    is not; returns whether the sun was tilted for that.

    The sun is given in the camera frame, so an initial pose a few degrees off tilts the
    ground by as much against it: a sun 3° above the horizon can be below it at the initial
    pose (one of 14 offset starts in two bench runs of the terrain band at a 3–12° sun), and
    the estimate would fail as unlit. The sun is tilted by the smallest of LIGHT_UP_TILTS_DEG
    whose render ``lit`` accepts, in the direction whose lit pattern best matches the
    reference's (pattern_score); the coarse stage, the search and the refinement's sun fit go
    on from there. A target on the sky, or a render already lit, is left alone (no render
    made)."""
    if lit(session.current_view()) or not _fills_frame(session):
        return False
    ref = _smoothed_reference(session)
    sun = SunTilt(session)
    start = sun.ab.copy()
    for tilt_deg in LIGHT_UP_TILTS_DEG:
        r = np.tan(np.radians(tilt_deg))
        best: tuple[float, Array] | None = None
        for angle in np.arange(8) * (np.pi / 4):
            ab = sun.clip(start + r * np.array([np.cos(angle), np.sin(angle)]))
            sun.set(ab)
            view = session.render_view(session.R, session.t)
            if lit(view) and view.grey.shape == ref.shape:
                score = pattern_score(view.grey, ref)
                if best is None or score > best[0]:
                    best = (score, ab)
        if best is not None:
            sun.set(best[1])
            session.current = None  # rendered with the old sun
            return True
    sun.set(start)
    return False
