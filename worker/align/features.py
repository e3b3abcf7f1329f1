"""Sparse features: descriptor matching, corners, KLT tracking and their weighting.

Images arrive already on one photometric scale (see :mod:`worker.engine.photometry`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

U8 = NDArray[np.uint8]
Points = NDArray[np.float64]  # (N, 2) pixel coordinates, OpenCV convention

#: KLT window and pyramid.
KLT_WINDOW_PX = 21
KLT_LEVELS = 3
#: A track is kept when tracking back lands within this of the start, px.
KLT_FB_MAX_PX = 0.5
#: Corner detection: minimum spacing, px, and quality relative to the strongest corner.
CORNER_MIN_DISTANCE_PX = 6
CORNER_QUALITY = 0.005
#: Structure tensor window (px) and the floor of its weaker eigenvalue (relative).
STRUCTURE_SIGMA_PX = 4.0
STRUCTURE_FLOOR = 0.05
#: USAC/MAGSAC inlier threshold for the fundamental matrix, px.
MAGSAC_THRESHOLD_PX = 2.0


@dataclass
class Matches:
    """Corresponding points: ref_pts[i] ↔ render_pts[i]; ``score`` lower is better."""

    ref_pts: Points
    render_pts: Points
    score: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.ref_pts)

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> Matches:
        return Matches(self.ref_pts[keep], self.render_pts[keep], self.score[keep])


EMPTY_MATCHES = Matches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))


def _detector(kind: str, max_features: int) -> cv2.Feature2D:
    if kind == "orb":
        return cv2.ORB_create(nfeatures=max(4 * max_features, 2000))
    return cv2.SIFT_create(nfeatures=max(4 * max_features, 4000), contrastThreshold=0.02)


Described = tuple[tuple[cv2.KeyPoint, ...], NDArray[np.generic] | None]


def describe(img: U8, detector: str, max_features: int, mask: U8 | None = None) -> Described:
    """Keypoints and descriptors of one image with one detector ('sift' or 'orb')."""
    kp, des = _detector(detector, max_features).detectAndCompute(img, mask)
    return tuple(kp), des


def _match_one(
    ref: U8 | Described,
    render: U8,
    detector: str,
    ratio: float,
    max_features: int,
    mask_ref: U8 | None,
    mask_render: U8 | None,
) -> Matches:
    """Ratio test and mutual best match with one detector (``ref`` may come described)."""
    kp_r, des_r = ref if isinstance(ref, tuple) else describe(ref, detector, max_features, mask_ref)
    kp_s, des_s = describe(render, detector, max_features, mask_render)
    if des_r is None or des_s is None or len(kp_r) < 2 or len(kp_s) < 2:
        return EMPTY_MATCHES
    norm = cv2.NORM_HAMMING if detector == "orb" else cv2.NORM_L2
    bf = cv2.BFMatcher(norm)
    fwd = bf.knnMatch(des_r, des_s, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(des_s, des_r)}
    keep = []
    for pair in fwd:
        if len(pair) < 2:
            continue
        m, n = pair
        if m.distance < ratio * n.distance and back.get(m.trainIdx) == m.queryIdx:
            keep.append((m.queryIdx, m.trainIdx, m.distance / max(n.distance, 1e-9)))
    if not keep:
        return EMPTY_MATCHES
    qi, ti, score = (np.array(c) for c in zip(*keep, strict=True))
    return Matches(
        np.array([kp_r[i].pt for i in qi], dtype=np.float64),
        np.array([kp_s[i].pt for i in ti], dtype=np.float64),
        score.astype(np.float64),
    )


def _merge(a: Matches, b: Matches, min_separation_px: float = 1.0) -> Matches:
    """Union of two match sets, dropping b's matches that duplicate one of a's."""
    if len(a) == 0 or len(b) == 0:
        return a if len(b) == 0 else b
    d = np.linalg.norm(b.ref_pts[:, None, :] - a.ref_pts[None, :, :], axis=2).min(axis=1)
    b = b.subset(d >= min_separation_px)
    return Matches(
        np.vstack([a.ref_pts, b.ref_pts]),
        np.vstack([a.render_pts, b.render_pts]),
        np.concatenate([a.score, b.score]),
    )


def match_features(
    ref: U8 | dict[str, Described],
    render: U8,
    detector: str = "both",
    ratio: float = 0.8,
    max_features: int = 600,
    mask_ref: U8 | None = None,
    mask_render: U8 | None = None,
) -> Matches:
    """Detect, describe and match; ratio test, mutual best match, then USAC/MAGSAC on F.

    ``ref`` may be given already described (a dict by detector, see :func:`describe`): the
    reference does not change during an estimate. ``detector`` 'both' pools SIFT and ORB
    matches: on thin, repetitive structure (trusses, solar arrays) ORB's FAST corners find
    several times more correct matches than SIFT's
    blobs, and on natural texture SIFT does better. The fundamental-matrix check removes gross
    mismatches only (it cannot see errors along epipolar lines); the estimator checks
    consistency with one pose after this.
    """
    kinds = ("sift", "orb") if detector == "both" else (detector,)
    matches = EMPTY_MATCHES
    for kind in kinds:
        ref_k = ref[kind] if isinstance(ref, dict) else ref
        matches = _merge(
            matches, _match_one(ref_k, render, kind, ratio, max_features, mask_ref, mask_render)
        )
    if len(matches) >= 12:
        try:
            _, inl = cv2.findFundamentalMat(
                matches.ref_pts,
                matches.render_pts,
                cv2.USAC_MAGSAC,
                MAGSAC_THRESHOLD_PX,
                0.999,
                10000,
            )
        except cv2.error:  # degenerate configurations (e.g. all points on a line)
            inl = None
        if inl is not None and inl.sum() >= 8:
            matches = matches.subset(inl.ravel().astype(bool))
    order = np.argsort(matches.score, kind="stable")[:max_features]
    return matches.subset(order)


# -- corners and KLT ---------------------------------------------------------------------
def detect_corners(img: U8, max_corners: int, mask: U8 | None = None) -> Points:
    """Shi–Tomasi corners, refined to sub-pixel, (N, 2)."""
    pts = cv2.goodFeaturesToTrack(
        img,
        maxCorners=max_corners,
        qualityLevel=CORNER_QUALITY,
        minDistance=CORNER_MIN_DISTANCE_PX,
        mask=mask,
        blockSize=7,
        useHarrisDetector=False,
    )
    if pts is None:
        return np.zeros((0, 2))
    pts = pts.astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.001)
    cv2.cornerSubPix(img, pts, (5, 5), (-1, -1), criteria)
    return pts.reshape(-1, 2).astype(np.float64)


def track(
    src: U8,
    dst: U8,
    pts: Points,
    guess: Points | None = None,
    fb_max_px: float = KLT_FB_MAX_PX,
    levels: int = KLT_LEVELS,
) -> tuple[Points, NDArray[np.bool_]]:
    """Pyramidal Lucas–Kanade from ``src`` to ``dst`` with a forward–backward check.

    Returns the tracked positions (N, 2) and a mask of the tracks that held.
    """
    n = len(pts)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    p0 = pts.astype(np.float32).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.003)
    win = (KLT_WINDOW_PX, KLT_WINDOW_PX)
    flags = 0
    p1 = None
    if guess is not None:
        p1 = guess.astype(np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        src, dst, p0, p1, winSize=win, maxLevel=levels, criteria=criteria, flags=flags
    )
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
        dst,
        src,
        p1,
        p0.copy(),
        winSize=win,
        maxLevel=levels,
        criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
    out = p1.reshape(-1, 2).astype(np.float64)
    h, w = dst.shape[:2]
    inside = (out[:, 0] >= 0) & (out[:, 1] >= 0) & (out[:, 0] <= w - 1) & (out[:, 1] <= h - 1)
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < fb_max_px) & inside
    return out, ok


def structure_whitening(
    img8: U8, pts: Points, sigma_px: float = STRUCTURE_SIGMA_PX, floor: float = STRUCTURE_FLOOR
) -> NDArray[np.float64]:
    """Per-feature 2×2 matrices A with AᵀA ∝ the local structure tensor, (k, 2, 2).

    A track's error covariance is about σ²·G⁻¹, G = Σ ∇I ∇Iᵀ over its window: along an edge
    (one large eigenvalue) the position is known only across the edge. Multiplying a feature's
    residual and Jacobian rows by A weighs each direction by what the image can tell. G is
    scaled to a largest eigenvalue of 1 (features count equally in their best direction) and
    the smallest is floored, so a clean corner is isotropic and a pure edge keeps a little
    weight along itself.
    """
    h, w = img8.shape
    c = np.clip(np.round(pts).astype(int), 0, [w - 1, h - 1])
    # Only around the points: the blur's kernel reaches 4 σ, the gradient 1 px more.
    reach = int(np.ceil(4 * sigma_px)) + 2
    if len(c) == 0:
        return np.zeros((0, 2, 2))
    lo = np.maximum(c.min(axis=0) - reach, 0)
    hi = np.minimum(c.max(axis=0) + reach + 1, [w, h])
    g = img8[lo[1] : hi[1], lo[0] : hi[0]].astype(np.float32)
    ix = cv2.Scharr(g, cv2.CV_32F, 1, 0)
    iy = cv2.Scharr(g, cv2.CV_32F, 0, 1)
    comps = [cv2.GaussianBlur(p, (0, 0), sigma_px) for p in (ix * ix, ix * iy, iy * iy)]
    c = c - lo
    gxx, gxy, gyy = (m[c[:, 1], c[:, 0]].astype(np.float64) for m in comps)
    G = np.stack([np.stack([gxx, gxy], -1), np.stack([gxy, gyy], -1)], -2)
    lam, V = np.linalg.eigh(G)
    lam = np.clip(lam / np.maximum(lam[:, 1:2], 1e-12), floor, 1.0)
    return np.einsum("kij,kj,klj->kil", V, np.sqrt(lam), V)
