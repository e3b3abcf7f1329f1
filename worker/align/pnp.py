"""PnP on ray-cast correspondences: the coarse stage and the PnP-refinement baseline.

The render at the current guess shows where model points land; casting rays through the
render's matched features gives their 3D model coordinates, and the reference's matched
features are their images in the real camera: a PnP problem. A skewed camera is handled by
solving in skew-free normalised coordinates scaled back to pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.engine.camera import PinholeCamera
from worker.engine.posemath import matrix_to_rotvec, rotvec_to_matrix

Array = NDArray[np.float64]

#: RANSAC reprojection threshold, px.
PNP_RANSAC_THRESHOLD_PX = 3.0
#: Fewest inliers for a PnP pose to be trusted.
PNP_MIN_INLIERS = 8


@dataclass
class PnPResult:
    R: Array
    t: Array
    inliers: NDArray[np.bool_]  # over the correspondences given
    rms_px: float


def _normalised(camera: PinholeCamera, uv: Array) -> tuple[Array, Array]:
    """Pixels → skew-free pixels of the camera diag(fx, fx) with principal point 0, and K'."""
    h = np.column_stack([uv, np.ones(len(uv))])
    xn = np.linalg.solve(camera.K, h.T).T[:, :2]
    K1 = np.array([[camera.fx, 0.0, 0.0], [0.0, camera.fx, 0.0], [0.0, 0.0, 1.0]])
    return xn * camera.fx, K1


def solve_pnp(
    camera: PinholeCamera,
    X_model: Array,
    uv_ref: Array,
    R0: Array,
    t0: Array,
    threshold_px: float = PNP_RANSAC_THRESHOLD_PX,
    seed: int = 0,
) -> PnPResult | None:
    """RANSAC PnP from the guess (R0, t0), then LM refinement on the inliers.

    Returns None when fewer than PNP_MIN_INLIERS correspondences agree on a pose.
    """
    if len(X_model) < PNP_MIN_INLIERS:
        return None
    pts, K1 = _normalised(camera, uv_ref)
    obj = X_model.astype(np.float64).reshape(-1, 1, 3)
    img = pts.astype(np.float64).reshape(-1, 1, 2)
    rvec0 = matrix_to_rotvec(R0).reshape(3, 1)
    tvec0 = np.asarray(t0, dtype=np.float64).reshape(3, 1)
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K1,
        None,
        rvec0.copy(),
        tvec0.copy(),
        useExtrinsicGuess=True,
        iterationsCount=1000,
        reprojectionError=threshold_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or inl is None or len(inl) < PNP_MIN_INLIERS:
        return None
    mask = np.zeros(len(X_model), dtype=bool)
    mask[inl.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], K1, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K1, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - pts, axis=1)
    mask = err < threshold_px
    if mask.sum() < PNP_MIN_INLIERS:
        return None
    R = rotvec_to_matrix(rvec.ravel())
    t = tvec.ravel()
    if t[2] <= 0:
        return None
    return PnPResult(R, t, mask, float(np.sqrt(np.mean(err[mask] ** 2))))
