"""Pinhole camera model in OpenCV conventions, and how to render it exactly with Mitsuba.

Mitsuba's perspective sensor has square pixels, no skew, and a principal point given as an
offset from the film centre. A camera with fx ≠ fy or a skew is rendered through a square-pixel
*source* camera with the same centre and then warped: two pinhole cameras with one centre differ
by the homography K K₀⁻¹, which is affine here because both K are upper triangular.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.camera import Camera

Array = NDArray[np.float64]

#: Margin (px) of the source render around the warped target image.
WARP_MARGIN_PX = 2


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] and an image size, OpenCV pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0

    @classmethod
    def from_schema(cls, camera: Camera) -> PinholeCamera:
        return cls(
            camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, camera.skew
        )

    @property
    def K(self) -> Array:
        """The 3×3 intrinsic matrix."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_square_pixel(self) -> bool:
        """True when Mitsuba can render this camera directly (fx == fy, no skew)."""
        return self.skew == 0.0 and math.isclose(self.fx, self.fy, rel_tol=1e-9)

    def scaled(self, scale: float) -> PinholeCamera:
        """The same camera imaging onto a ``scale``-times resized image.

        Pixel centres map as (u + ½)·s − ½, so cx' = (cx + ½)·s − ½ with the exact per-axis
        ratio of the rounded sizes.
        """
        w = max(8, round(self.width * scale))
        h = max(8, round(self.height * scale))
        sx, sy = w / self.width, h / self.height
        return PinholeCamera(
            w,
            h,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            self.skew * sx,
        )

    def cropped(self, x0: int, y0: int, width: int, height: int) -> PinholeCamera:
        """The same camera imaging onto the ``width`` × ``height`` window of its image whose
        top-left pixel is (x0, y0): only the principal point moves, cx' = cx − x0."""
        if not (0 <= x0 and 0 <= y0 and x0 + width <= self.width and y0 + height <= self.height):
            raise ValueError(
                f"window {width}x{height} at ({x0}, {y0}) is not inside the "
                f"{self.width}x{self.height} image"
            )
        return PinholeCamera(width, height, self.fx, self.fy, self.cx - x0, self.cy - y0, self.skew)

    def project(self, X_cam: ArrayLike) -> Array:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3): s·[u v 1]ᵀ = K X."""
        X = np.atleast_2d(np.asarray(X_cam, dtype=np.float64))
        x = X @ self.K.T
        return x[:, :2] / x[:, 2:3]

    def rays(self, uv: ArrayLike) -> Array:
        """Unit ray directions (N, 3) in the camera frame through pixel coordinates (N, 2)."""
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        h = np.column_stack([uv, np.ones(len(uv))])
        d = np.linalg.solve(self.K, h.T).T
        return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class RenderPlan:
    """How to render a camera with Mitsuba: a square-pixel source camera and, when needed, the
    affine map (2×3) from target pixel coordinates to source pixel coordinates."""

    source: PinholeCamera
    target: PinholeCamera
    target_to_source: Array | None  # None: source is the target, no warp

    @property
    def x_fov_deg(self) -> float:
        """Mitsuba's horizontal field of view of the source film, degrees."""
        return math.degrees(2.0 * math.atan(self.source.width / (2.0 * self.source.fx)))

    @property
    def principal_point_offset(self) -> tuple[float, float]:
        """Mitsuba's principal point offset (fractions of the film size) of the source camera.

        Mitsuba's continuous film coordinates put pixel centres at i + ½, so the OpenCV principal
        point c sits at c + ½; Mitsuba measures its offset from the film centre in film sizes.
        """
        s = self.source
        return ((s.cx + 0.5) / s.width - 0.5, (s.cy + 0.5) / s.height - 0.5)


def plan_render(camera: PinholeCamera) -> RenderPlan:
    """A RenderPlan for ``camera`` (exact: a warp only when fx ≠ fy or skew ≠ 0)."""
    if camera.is_square_pixel:
        return RenderPlan(camera, camera, None)
    f0 = max(camera.fx, camera.fy)
    K0_unshifted = np.array([[f0, 0.0, 0.0], [0.0, f0, 0.0], [0.0, 0.0, 1.0]])
    A = K0_unshifted @ np.linalg.inv(camera.K)  # target pixel → source pixel (before shift)
    corners = np.array(
        [
            [-0.5, -0.5, 1],
            [camera.width - 0.5, -0.5, 1],
            [-0.5, camera.height - 0.5, 1],
            [camera.width - 0.5, camera.height - 0.5, 1],
        ]
    )
    src = corners @ A.T
    lo = np.floor(src[:, :2].min(axis=0)) - WARP_MARGIN_PX
    hi = np.ceil(src[:, :2].max(axis=0)) + WARP_MARGIN_PX
    width, height = (hi - lo).astype(int)
    # Source pixel (0, 0) centre sits at lo + ½ in unshifted coordinates.
    shift = lo + 0.5
    source = PinholeCamera(int(width), int(height), f0, f0, -shift[0], -shift[1], 0.0)
    M = (source.K @ np.linalg.inv(camera.K))[:2]
    return RenderPlan(source, camera, M)


def warp_to_target(image: NDArray[np.floating], plan: RenderPlan) -> NDArray[np.float32]:
    """Resample a source render onto the target camera's pixel grid (bilinear)."""
    if plan.target_to_source is None:
        return np.asarray(image, dtype=np.float32)
    import cv2

    return cv2.warpAffine(
        np.asarray(image, dtype=np.float32),
        plan.target_to_source,
        (plan.target.width, plan.target.height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
