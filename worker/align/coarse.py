"""Coarse stage: PnP on ray-cast correspondences between the reference and the render.

One render per iteration: match descriptors between the reference and the render at the
guess, cast rays through the render's matched features to get their model coordinates, and
solve PnP against the reference's features (RANSAC, so the inliers agree on one pose). It gets
into the basin of the learned-Jacobian refinement in a few renders; alone (method 'pnp') it is
the PnP-refinement baseline.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from schemas.estimate import StopReason
from worker.align.features import match_features
from worker.align.pnp import PnPResult, solve_pnp
from worker.align.session import LIT_FRACTION, RenderedView, Session
from worker.engine.images import FloatImage
from worker.engine.photometry import alignment_score, content_mask, normalise_pair
from worker.engine.posemath import axis_angle_to_matrix, increment_between, step_norm

#: Hand over to the refinement once a PnP step is below this ‖δp‖ (≈ 0.1°, 0.2 % of range):
#: PnP on ray-cast points jitters at about that level.
COARSE_HANDOVER_STEP = 1e-2
#: Silhouettes smaller than this (px²) are not aligned by moments.
MIN_SILHOUETTE_PX = 50
#: Fraction of the image border a silhouette may cover and still be aligned by moments: a
#: target grazing the frame keeps nearly all of its area (and the alignment score referees the
#: move), one the frame cuts in half or that fills it does not.
MAX_BORDER_FRACTION = 0.15
#: Smallest rise of the dissimilarity 1 − NCC that counts as a worse render.
SCORE_MARGIN = 0.002
#: Iterations the coarse stage may take before handing over.
COARSE_MAX_ITERATIONS = 5
#: The attitude search (options.attitude_search): rounds of (turns in degrees, axes spread over
#: the sphere), each about the best attitude so far; 158 renders at the coarse level.
SEARCH_ROUNDS: tuple[tuple[tuple[float, ...], int], ...] = (
    ((6.0, 12.0, 18.0), 26),
    ((3.0, 6.0), 26),
    ((1.5, 3.0), 14),
)


def silhouette_moments(grey: FloatImage, level: float) -> tuple[float, NDArray[np.float64]]:
    """Area (px²) and centroid (2,) of the pixels brighter than ``level``."""
    mask = grey > level
    area = float(mask.sum())
    if area == 0:
        return 0.0, np.zeros(2)
    ys, xs = np.nonzero(mask)
    return area, np.array([xs.mean(), ys.mean()])


def cut_by_frame(mask: NDArray[np.bool_]) -> bool:
    """Whether a silhouette mask reaches the image border (more than MAX_BORDER_FRACTION of
    the border pixels): the target fills the frame or extends past its edges."""
    border = np.concatenate([mask[0], mask[-1], mask[1:-1, 0], mask[1:-1, -1]])
    return bool(border.mean() > MAX_BORDER_FRACTION)


def frame_cuts(grey: FloatImage) -> bool:
    """Whether the frame cuts a render's lit silhouette (:func:`cut_by_frame`): its area and
    centroid then say nothing of the pose."""
    return cut_by_frame(grey > LIT_FRACTION * float(grey.max()))


def sphere_axes(n: int) -> NDArray[np.float64]:
    """``n`` unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3)."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + np.sqrt(5.0)) * i
    sin = np.sin(polar)
    return np.stack([np.cos(azimuth) * sin, np.sin(azimuth) * sin, np.cos(polar)], axis=1)


def search_attitude(session: Session) -> bool:
    """Turn the target about its centre to the attitude whose render explains the reference
    best, in rounds about the best so far (SEARCH_ROUNDS), then place it as moment alignment
    does. Each candidate is scored after moving its silhouette onto the reference's in the
    image (centroid and area, :func:`placed_score`), so a start off in position as well is not
    answered by an attitude that moves the silhouette instead (bench/README.md, "A lost frame
    searches its attitude"). For a start too far off in attitude for descriptor matches: a
    tracked ISS that jumped 12° matched 11 features with its render at the prediction and PnP
    failed. Returns whether the pose moved; the placed render must align better than the
    start's. Skipped when the frame cuts the target or the camera is inside the model's
    bounding sphere (terrain: turning the model about its centre would carry the ground away)."""
    model = session.renderer.model
    centre = session.R @ model.centre + session.t
    start = session.current_view()
    ref = reference_silhouette(session.ref_grey)
    if (
        float(np.linalg.norm(centre)) <= model.radius
        or frame_cuts(start.grey)
        or ref[0] < MIN_SILHOUETTE_PX
    ):
        return False
    with session.timed("match"):
        best = (*placed_score(session.ref_grey, start.grey, ref), start)
    for turns, n_axes in SEARCH_ROUNDS:
        R_best = best[2].R
        for axis in sphere_axes(n_axes):
            for deg in turns:
                R = axis_angle_to_matrix(axis, float(np.radians(deg))) @ R_best
                view = session.render_view(R, centre - R @ model.centre)
                with session.timed("match"):
                    score, silhouette = placed_score(session.ref_grey, view.grey, ref)
                if score > best[0] and silhouette is not None:
                    best = (score, silhouette, view)
    return best[1] is not None and _move_if_better(session, start, best[2], best[1], ref)


#: A silhouette: its area (px²) and centroid (x, y), of the working level's image.
Silhouette = tuple[float, NDArray[np.float64]]


def reference_silhouette(ref: FloatImage) -> Silhouette:
    """The reference's lit silhouette: pixels well above the sky's level and noise."""
    sky = float(np.median(ref))
    noise = 1.4826 * float(np.median(np.abs(ref - sky)))
    level = sky + max(6.0 * noise, 0.05 * (float(np.percentile(ref, 99.9)) - sky))
    return silhouette_moments(ref, level)


def render_silhouette(grey: FloatImage) -> Silhouette:
    return silhouette_moments(grey, LIT_FRACTION * float(grey.max()))


def placed_score(
    ref: FloatImage, grey: FloatImage, silhouette: Silhouette
) -> tuple[float, Silhouette | None]:
    """The alignment score of a render moved and scaled in the image so its silhouette has the
    reference's (``silhouette``) centroid and area, and the render's silhouette (None, and the
    score as it stands, when it has none)."""
    own = render_silhouette(grey)
    if own[0] < MIN_SILHOUETTE_PX:
        return alignment_score(ref, grey), None
    s = float(np.sqrt(silhouette[0] / own[0]))
    (xr, yr), (x, y) = silhouette[1], own[1]
    M = np.float32([[s, 0.0, xr - s * x], [0.0, s, yr - s * y]])
    h, w = grey.shape
    moved = cv2.warpAffine(grey.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR)
    return alignment_score(ref, moved), own


def _move_if_better(
    session: Session, start: RenderedView, view: RenderedView, own: Silhouette, ref: Silhouette
) -> bool:
    """Move ``view``'s target so its silhouette has the reference's centroid (turning its
    centre towards that ray) and area (scaling its range); keep the move, recorded as a coarse
    iteration, only when its render aligns better with the reference than ``start``'s."""
    centre = view.R @ session.renderer.model.centre + view.t
    d_ren, d_ref = session.camera.rays(own[1])[0], session.camera.rays(ref[1])[0]
    axis = np.cross(d_ren, d_ref)
    turn = axis_angle_to_matrix(axis, float(np.arcsin(min(np.linalg.norm(axis), 1.0))))
    t_new = turn @ centre * float(np.sqrt(own[0] / ref[0])) - view.R @ session.renderer.model.centre
    with session.timed("match"):
        before = alignment_score(session.ref_grey, start.grey)
        moved = session.render_view(view.R, t_new)
        after = alignment_score(session.ref_grey, moved.grey)
    if after <= before:
        session.record("coarse", 0.0, 0.0, 0.0, False, 0)
        return False
    step = step_norm(increment_between(start.R, start.t, view.R, t_new), session.range_)
    session.accept(moved)
    session.record("coarse", 0.0, step, 0.0, True, 0)
    return True


def run_moment_alignment(session: Session) -> bool:
    """Move the target so its lit silhouette has the reference's area and centroid.

    A guess 10–20 % off in range makes descriptor matching fail on thin, repetitive structure;
    matching the silhouette's area fixes most of the range error and its centroid most of the
    lateral one, before any feature is needed. The move is kept only if its render aligns
    better with the reference (alignment score); returns whether it was kept.
    """
    view = session.current_view()
    if frame_cuts(view.grey):
        return False
    ref, own = reference_silhouette(session.ref_grey), render_silhouette(view.grey)
    if ref[0] < MIN_SILHOUETTE_PX or own[0] < MIN_SILHOUETTE_PX:
        return False
    return _move_if_better(session, view, view, own, ref)


def run_pnp_stage(
    session: Session, max_iterations: int, stop_step: float
) -> tuple[bool, StopReason | None]:
    """Iterate PnP from the session's pose. Returns (made_progress, stop reason if converged).

    Each PnP pose is judged by its render, not by its own reprojection error: PnP on ray-cast
    points can fit a wrong pose well (a small or nearly planar target leaves it ambiguous), so
    a step whose render explains the reference worse (lower alignment score) is undone and the
    stage ends. Stops too after ``max_iterations`` or when a step is below ``stop_step``.
    """
    progress = False
    best: tuple[RenderedView, float, float] | None = None  # view, score, its PnP cost
    for _ in range(min(max_iterations, session.iterations_left)):
        view = session.current_view()
        score, undone = _judge(session, view, best)
        if undone:
            return progress, "pnp_converged"
        cost = best[2] if best is not None else np.nan
        best = (view, score, cost)
        res = _pnp_from(session, view)
        if res is None:
            return progress, None
        step = step_norm(increment_between(view.R, view.t, res.R, res.t), session.range_)
        session.R, session.t = res.R, res.t
        best = (view, score, res.rms_px**2) if not np.isfinite(cost) else best
        progress = True
        session.record("coarse", res.rms_px**2, step, 0.0, True, int(res.inliers.sum()))
        if step < stop_step:
            return progress, "pnp_converged"
    if best is not None and progress:
        # The iterations ran out: the last PnP pose is judged by its render like the others
        # (unjudged, one from a handful of matches on a small target could end 10° off). The
        # render is not made current: a kept pose goes on as it did before it was judged.
        _judge(session, session.render_view(session.R, session.t), best)
    return progress, None


def _judge(
    session: Session, view: RenderedView, best: tuple[RenderedView, float, float] | None
) -> tuple[float, bool]:
    """The alignment score of ``view`` (the render at the session's pose), and whether the
    pose was undone: when the render is clearly worse than ``best``'s (view, score, cost), the
    session goes back to that view and records the step as rejected."""
    with session.timed("match"):
        score = alignment_score(session.ref_grey, view.grey)
    if best is None or not _clearly_worse(score, best[1]):
        return score, False
    session.accept(best[0])
    session.record("coarse", best[2], 0.0, 0.0, False, 0)
    return score, True


def _clearly_worse(score: float, best: float) -> bool:
    """Whether an alignment score is worse than the best by more than its jitter.

    The score's dissimilarity 1 − NCC grows about quadratically with misalignment; a render
    is judged worse only when it grows by half and by SCORE_MARGIN, so sub-degree PnP moves on
    a small target (where the score is blunt) are not undone by noise in the score.
    """
    return (1.0 - score) > 1.5 * (1.0 - best) + SCORE_MARGIN


def _pnp_from(session: Session, view: RenderedView) -> PnPResult | None:
    """Match the reference to ``view``, cast rays through the render's features, solve PnP."""
    opts = session.options
    with session.timed("match"):
        pair = normalise_pair(session.ref_grey, view.grey)
        n = max(opts.max_features, 300)
        matches = match_features(
            session.reference_described(opts.detector, n),
            pair.render,
            opts.detector,
            opts.ratio,
            n,
            mask_render=content_mask(pair.render),
        )
    if len(matches) < max(opts.min_features, 8):
        return None
    with session.timed("pnp"):
        X, hit = session.raycast(view.R, view.t, matches.render_pts)
        return solve_pnp(
            session.camera, X[hit], matches.ref_pts[hit], view.R, view.t, seed=opts.seed
        )
