"""The feature sets the learned-Jacobian LM works on, and how each is measured in a render.

- :class:`TrackedFeatures` (the default): fixed points of the reference — Shi–Tomasi corners
  (2-D) and edge points (1-D, across the edge) — found in each render by tracking from the
  noise-free render into the reference. One set serves the whole stage.
- :class:`MatchedFeatures` (the paper): descriptor matches with one render, re-made at each pose.

Both give, per feature, the reference position x̃ (k, 2), a whitening A (k, 2, 2) that weighs
the residual x̃ − h by what the image can tell (identity for a matched point, the structure
tensor for a corner, n nᵀ for an edge point), and ``measure(view, guess)`` → positions h in a
render and which were found.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.align.blur import Blur, blur_change_px, measure_blur
from worker.align.edges import detect_edge_points, normal_shift
from worker.align.features import detect_corners, match_features, structure_whitening, track
from worker.align.reflectance import fit_law, is_lambert, lambertised, law_angles, smoothness
from worker.align.session import RenderedView, Session
from worker.engine.images import Box, srgb_decode, srgb_encode, to_grey
from worker.engine.metrics import rotation_error_deg
from worker.engine.photometry import (
    BLUR_REACH_PX,
    content_mask,
    contrast_scale,
    local_normalise,
    local_normalise_f,
    normalise_pair,
    normalise_render,
    normalised_to_u8,
    on_render_scale,
    reference_tone_curve,
)

Array = NDArray[np.float64]

#: Rounds of render → reference tracking per corner measurement, the shift (px) below which
#: the rounds stop, and the shift (px) still left after them that drops a corner.
MEASURE_ROUNDS = 3
MEASURE_TOL_PX = 0.02
MEASURE_MAX_LEFT_PX = 0.25
#: Matches drawn before picking the most trackable (when fewer features are wanted).
MATCH_POOL = 200
#: Edge points used at most, per corner allowed.
EDGES_PER_CORNER = 3
#: A blur (not a streak) measured again in the first frame a set is carried into that changed
#: by more than this (px, :func:`blur_change_px`) is measured in every later frame too.
BLUR_CHANGE_PX = 0.15
#: A tracked frame whose law gain was placed this far (°) from where it converged is solved
#: again (:func:`law_misplaced`).
LAW_AGAIN_DEG = 0.2


class Features(Protocol):
    x_ref: Array  # (k, 2) positions in the reference
    A: Array  # (k, 2, 2) whitening of each feature's residual (see structure_whitening)
    feature_normals: Array  # (k, 2): an edge point's normal, NaN for 2-D features

    def measure(self, view: RenderedView, guess: Array | None) -> tuple[Array, NDArray[np.bool_]]:
        """Positions (k, 2) of the features in ``view`` and which of them were found."""
        ...


class TrackedFeatures:
    """Corners and edge points of the reference, found in each render by tracking."""

    def __init__(self, session: Session, view: RenderedView) -> None:
        self._grey: tuple[RenderedView, Array] | None = None
        self._normalised_view: tuple[RenderedView, Array, NDArray[np.uint8], Array] | None = None
        pair = normalise_pair(session.ref_grey, view.grey)
        mask = content_mask(pair.ref_smooth) & content_mask(pair.render_smooth)
        # The reference's tone curve is mapped onto the render's first: contrast normalisation
        # removes local gain and offset but not a different gamma, which shifts every blurred
        # edge towards its dark side.
        #: The curve, kept for the sets carried from this one (a camera's response does not
        #: change from frame to frame; fitting it again costs more than the rest of a frame).
        self.tone_curve = reference_tone_curve(session.ref_image, view.linear)
        ref_linear = srgb_decode(on_render_scale(session.ref_image, self.tone_curve))
        # Equal sharpness too: a corner blurred differently in the two images sits elsewhere.
        # Blur acts on light, so it is measured and applied in linear units, then encoded.
        self.blur = measure_blur(ref_linear, to_grey(view.linear))
        #: Whether a tracker's carried sets measure the blur again (see _blur_again): True
        #: for a streak (motion blur), None (not known yet) for another blur, False for none.
        self.smeared: bool | None = False
        if self.blur.active:
            self.smeared = True if self.blur.streak_px > 0.0 else None
            # The curve again, against the render at the reference's sharpness: against the
            # sharp one, the light a softer reference spreads into the render's flat dark parts
            # bent the curve's foot (dark levels mapped 10-15 % too low: a gamma) and moved
            # corners outwards (0.055 px at σ = 1 px; Aura started at the truth ended up to 0.49°
            # off, 0.069° with the refit).
            self.tone_curve = reference_tone_curve(session.ref_image, self.blur.apply(view.linear))
            ref_linear = srgb_decode(on_render_scale(session.ref_image, self.tone_curve))
        # The reflectance law: a regolith that does not darken towards the limb as Lambert
        # does bends every shading feature of an untextured body (worker.align.reflectance).
        #: Its Lommel–Seeliger share and Oren–Nayar c, kept for the sets carried from this one
        #: (both 0: Lambert).
        self.law_w, self.law_c = 0.0, 0.0
        if _law_wanted(session, view):
            ref_linear = self._fit_law(session, view, ref_linear)
        self.scale = contrast_scale(self._render_grey(view), box=work_box(view))
        ref_grey = srgb_encode(ref_linear)
        self.ref8 = local_normalise(ref_grey, self.scale)
        # Corners of the contrast-normalised reference: dim parts (a dark solar array) then
        # give corners as readily as the bright ones, which spreads the features out.
        self.corners = detect_corners(self.ref8, session.options.max_features, mask)
        render8, render_f = self._normalised(view)
        self.ref_f = local_normalise_f(ref_grey, self.scale)
        A_corners = structure_whitening(render8, self.corners)
        # Edge points come from the noise-free render; their reference positions are where
        # the reference shows the same edge, across it.
        pts, self.normals = detect_edge_points(
            render_f, mask, EDGES_PER_CORNER * session.options.max_features
        )
        s, ok = normal_shift(render_f, self.ref_f, pts, self.normals)
        self.edges, self.normals = pts[ok] + s[ok, None] * self.normals[ok], self.normals[ok]
        self.x_ref = np.vstack([self.corners, self.edges])
        A_edges = np.einsum("ki,kj->kij", self.normals, self.normals)
        self.A = np.concatenate([A_corners, A_edges])
        nan = np.full((len(self.corners), 2), np.nan)
        #: Per-feature normal for edge points, NaN for corners (used when learning J).
        self.feature_normals = np.vstack([nan, self.normals])
        #: Where the corners were found (a tracker carries them from here, see carried()).
        self.anchor = _Anchor(self.ref8, self.corners.copy())
        self.anchor_corners = np.arange(len(self.corners))

    def carried(
        self, session: Session, view: RenderedView, motion: Array
    ) -> tuple[TrackedFeatures, NDArray[np.bool_]]:
        """The same features in the session's (new) reference, a tracker's next frame: each
        tracked from the reference it was found in (the anchor, so that frame-to-frame errors
        do not add up) into the new one, starting from where ``motion`` (k, 2), their predicted
        image motion since the last frame, puts it; ``view`` is the render at the predicted
        pose (it sets the contrast scale and the whitening; the tone curve stays this set's).
        Returns the carried set (only the features found again) and which of this set's
        features it keeps."""
        new = copy.copy(self)
        anchor = self.anchor
        # Only the target's part of the new reference is looked at (a window's render: the
        # rest of the render is sky, and the reference should be dark there too).
        box = work_box(view)
        ref_image = session.ref_image
        if box is None:
            ref_grey = on_render_scale(ref_image, self.tone_curve)
        else:
            part = on_render_scale(box.of(ref_image), self.tone_curve)
            ref_grey = box.paste(part, view.grey.shape)
        if self.smeared is not False:
            blur = self._blur_again(ref_grey, view, box)
            if self.smeared is None:
                new.smeared = blur_change_px(blur, self.blur) > BLUR_CHANGE_PX
            if new.smeared:
                new.blur, new._grey, new._normalised_view = blur, None, None
        if self.law_w > 0 or self.law_c > 0:
            ref_grey = lambertised(ref_grey, self.law_w, law_angles(session, view), self.law_c)
        new.scale = contrast_scale(new._render_grey(view), box=box)
        new.ref_f = local_normalise_f(ref_grey, new.scale, box=box)
        new.ref8 = normalised_to_u8(new.ref_f, box)
        kc = len(self.corners)
        corners, ok_c = track(
            anchor.ref8, new.ref8, anchor.corners[self.anchor_corners], self.corners + motion[:kc]
        )
        # An edge point slides along its edge: only its shift across it is tracked, from the
        # last frame (its along-edge position is not the anchor's anyway).
        s0 = np.einsum("ki,ki->k", motion[kc:], self.normals)
        s, ok_e = normal_shift(self.ref_f, new.ref_f, self.edges, self.normals, s0)
        keep = np.concatenate([ok_c, ok_e])
        new.corners = corners[ok_c]
        new.anchor_corners = self.anchor_corners[ok_c]
        new.edges = (self.edges + s[:, None] * self.normals)[ok_e]
        new.normals = self.normals[ok_e]
        new.x_ref = np.vstack([new.corners, new.edges])
        A_corners = structure_whitening(new._normalised(view)[0], new.corners)
        new.A = np.concatenate([A_corners, self.A[kc:][ok_e]])
        new.feature_normals = self.feature_normals[keep]
        return new, keep

    def _blur_again(self, ref_grey: Array, view: RenderedView, box: Box | None) -> Blur:
        """The blur of a new frame (``ref_grey``: its reference on this set's tone scale),
        measured as in a fresh set, on the box only; this set's when none is found there.

        Motion blur follows the motion during each exposure. On the bench's `motion`
        sequences (a 1.5 px streak drawn afresh in every frame; the asteroid and Aura, approach
        and tumble, 12 frames) tracked frames that kept the first frame's blur ended 0.10-0.13°
        from the truth at the median of three, the fourth's worst frame 0.60° off; measured in
        every frame, medians 0.02-0.06°, the worst frame 0.18° (bench/README.md, "Motion blur
        measured again in tracked frames"). A blur that stays (defocus, a pixel filter) gained
        nothing from being measured in every frame and cost 0.05-0.15 s a frame. So a set with
        a streak measures it in every frame it is carried into; one with another blur measures
        it in the first, and goes on only if it changed by more than BLUR_CHANGE_PX
        (:func:`blur_change_px`). Aura's edges lie in few directions: there the streak is often
        not found, the σ found instead changes little, and the sequences gain less (medians
        0.128 → 0.090° and 0.033 → 0.031°, the worst frames 0.24 → 0.19° and 0.60 → 0.11°)."""
        linear = view.linear if box is None else box.of(view.linear)
        ref = ref_grey if box is None else box.of(ref_grey)
        blur = measure_blur(srgb_decode(ref), to_grey(linear))
        return blur if blur.active else self.blur

    def _fit_law(self, session: Session, view: RenderedView, ref_linear: Array) -> Array:
        """The reference as a Lambertian surface would show it, when another law explains it
        better (worker.align.reflectance); its tone curve is then the one fitted with that law.
        When the session's first fit finds Lambert (neither part applied), later sets fit no
        law; else each fits its own (keeping the first share and fitting only the tone curve
        at later sets doubled the drift on the bench's asteroid under `regolith`)."""
        if session.law is not None and is_lambert(session.law):
            return ref_linear
        linear = self.blur.apply(view.linear)
        fit = fit_law(session.ref_image, linear, law_angles(session, view))
        if fit is None:
            return ref_linear
        law = fit[0]
        if session.law is None:
            session.law = law.shape
        if law.lambert:
            return ref_linear
        self.tone_curve, self.law_w, self.law_c = law.curve, law.w, law.c
        return law.reference

    def _render_grey(self, view: RenderedView) -> Array:
        """The render's grey at the reference's sharpness (kept for the last view)."""
        if not self.blur.active:
            return view.grey
        if self._grey is None or self._grey[0] is not view:
            box = work_box(view)
            linear = view.linear if box is None else box.of(view.linear)
            grey = srgb_encode(self.blur.apply(to_grey(linear)))
            self._grey = (view, grey if box is None else box.paste(grey, view.grey.shape))
        return self._grey[1]

    def _normalised(self, view: RenderedView) -> tuple[NDArray[np.uint8], Array]:
        """The render's grey contrast-normalised on this set's scale, 8-bit (for KLT) and
        float (for edges); kept for the last view and scale, which a carried set's whitening
        and its first measurement share."""
        cached = self._normalised_view
        if cached is None or cached[0] is not view or cached[1] is not self.scale:
            box = work_box(view)
            f = local_normalise_f(self._render_grey(view), self.scale, box=box)
            cached = self._normalised_view = (view, self.scale, normalised_to_u8(f, box), f)
        return cached[2], cached[3]

    def measure(self, view: RenderedView, guess: Array | None) -> tuple[Array, NDArray[np.bool_]]:
        """Where each reference corner is in ``view``, found by tracking the other way.

        KLT takes its gradients from the image it tracks *from*; from the noisy reference they
        correlate with its (signal-dependent) noise and bias every track towards the bright
        side of an edge. So the render (noise-free) is tracked into the reference from the
        current guess h, and h moves by what is left, x̃ − x'(h), until that is negligible.
        """
        render8, render_f = self._normalised(view)
        guess = self.x_ref if guess is None else guess
        kc = len(self.corners)
        hc, okc = self._measure_corners(render8, guess[:kc])
        n = self.normals
        s0 = np.einsum("ki,ki->k", self.edges - guess[kc:], n)
        s, oke = normal_shift(render_f, self.ref_f, self.edges, n, s0)
        he = self.edges - s[:, None] * n
        return np.vstack([hc, he]), np.concatenate([okc, oke])

    def _measure_corners(
        self, img8: NDArray[np.uint8], guess: Array
    ) -> tuple[Array, NDArray[np.bool_]]:
        h = guess.copy()
        ok = np.ones(len(h), dtype=bool)
        left = np.zeros_like(h)
        for _ in range(MEASURE_ROUNDS):
            x_at, ok_i = track(img8, self.ref8, h, self.corners)
            ok &= ok_i
            left = self.corners - x_at
            h = np.where(ok[:, None], h + left, h)
            if not ok.any() or np.abs(left[ok]).max() < MEASURE_TOL_PX:
                break
        return h, ok & (np.hypot(*left.T) < MEASURE_MAX_LEFT_PX)


@dataclass(frozen=True)
class _Anchor:
    ref8: NDArray[np.uint8]  # the normalised reference the corners were found in
    corners: Array  # (kc, 2) their positions there


def _law_wanted(session: Session, view: RenderedView) -> bool:
    """Whether to fit the reflectance law (options.reflectance; "auto": on a smooth body only,
    decided once per session, at its first feature set that shows enough lit pixels)."""
    mode = session.options.reflectance
    if mode != "auto":
        return mode == "fit"
    if session.smooth_body is None:
        seen = smoothness(session.renderer, view)
        if seen is None:  # too few lit pixels here: decided at a later set
            return False
        session.smooth_body = seen.smooth_body
    return session.smooth_body


def law_misplaced(features: object, R_predicted: Array, R: Array) -> bool:
    """Whether a tracked frame, divided by its set's reflectance law gain at the predicted
    attitude (:meth:`TrackedFeatures.carried`), converged more than LAW_AGAIN_DEG from it: the
    gain then sits where the prediction put the body, and the frame is solved once more from
    where it ended. Measured on the bench's asteroid under `regolith` (12 frames, approach and
    tumble): the first tracked frame, predicted without a velocity ~0.8° off, ended 0.124° and
    0.092° off, solved again 0.043° and 0.031°."""
    if getattr(features, "law_w", 0.0) <= 0.0 and getattr(features, "law_c", 0.0) <= 0.0:
        return False
    return rotation_error_deg(R_predicted, R) > LAW_AGAIN_DEG


def inherited_smear(carried: object, fresh: object) -> bool | None:
    """The ``smeared`` of a set made afresh (``fresh``) where a tracker's ``carried`` set
    was: True once frames showed a changing blur or a streak (later ones measure it too);
    False when ``carried`` had measured its blur (not a streak) again in the frame it was
    carried into and found it unchanged, and ``fresh`` found no streak either: a lens's or a
    pixel filter's blur stays, and measuring it again in the first frame after every
    relearning cost that frame 0.07-0.2 s (bench/README.md, "A blur found unchanged is not
    measured again"); else ``fresh``'s own."""
    was = getattr(carried, "smeared", False)
    own: bool | None = getattr(fresh, "smeared", False)
    if was:
        return True
    blur = getattr(carried, "blur", None)
    if was is False and own is None and blur is not None and blur.active:
        return False
    return own


def work_box(view: RenderedView) -> Box | None:
    """The part of ``view``'s image that processing it needs: its sky box grown by the blurs'
    reach (outside it the render and every blur of it are sky); None: all of it."""
    return None if view.sky_box is None else view.sky_box.grown(BLUR_REACH_PX, view.grey.shape)


class MatchedFeatures:
    """Descriptor matches between the reference and one render; other renders are measured
    by tracking the render's features into them (render → render)."""

    def __init__(self, session: Session, view: RenderedView) -> None:
        opts = session.options
        pair = normalise_pair(session.ref_grey, view.grey)
        m = match_features(
            pair.ref,
            pair.render,
            opts.detector,
            opts.ratio,
            max(opts.max_features, MATCH_POOL),
            mask_render=content_mask(pair.render),
        )
        self.view = view
        self.white = float(np.percentile(view.grey, 99.9)) or 1.0
        self.base8 = pair.render_smooth
        keep = _trackable(self.base8, m.render_pts, opts.max_features)
        self.x_ref, self.x_base = m.ref_pts[keep], m.render_pts[keep]
        self.A = np.broadcast_to(np.eye(2), (len(self.x_ref), 2, 2))
        self.feature_normals = np.full((len(self.x_ref), 2), np.nan)

    def measure(self, view: RenderedView, guess: Array | None) -> tuple[Array, NDArray[np.bool_]]:
        if view is self.view:
            return self.x_base.copy(), np.ones(len(self.x_base), dtype=bool)
        return track(self.base8, normalise_render(view.grey, self.white), self.x_base, guess)


def _trackable(img8: NDArray[np.uint8], pts: Array, n: int) -> NDArray[np.intp]:
    """Indices of at most ``n`` points, the most trackable first (largest smaller eigenvalue
    of the structure tensor), spread out: a point closer than 1/(2√n) of the image's size to
    one already taken is skipped while others remain. With a handful of features (the
    paper's four) a blob or a point on an edge would be lost in the first perturbed render."""
    if len(pts) <= n:
        return np.arange(len(pts))
    eig = cv2.cornerMinEigenVal(img8, 7)
    c = np.clip(np.round(pts).astype(int), 0, [img8.shape[1] - 1, img8.shape[0] - 1])
    order = np.argsort(-eig[c[:, 1], c[:, 0]], kind="stable")
    spacing = max(img8.shape) / (2.0 * np.sqrt(n))
    taken: list[int] = []
    for i in order:
        if all(np.hypot(*(pts[i] - pts[j])) >= spacing for j in taken):
            taken.append(int(i))
        if len(taken) == n:
            break
    rest = [int(i) for i in order if int(i) not in taken]
    return np.array((taken + rest)[:n], dtype=np.intp)
