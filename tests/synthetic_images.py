"""Small synthetic images for the feature, edge, tracking and photometry tests: shapes with
smooth (band-limited) edges on a dark sky, evaluated analytically so that a sub-pixel shift of
the whole image is exact, and a stub renderer for sessions that need renders but no Mitsuba."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from worker.engine.camera import PinholeCamera
from worker.engine.renderer import LightingSpec, Renderer, RenderStats, Window

Image = NDArray[np.float32]
#: Rectangles (x0, y0, x1, y1, brightness) of the default scene, px of a 128-px image.
RECTANGLES = (
    (20.0, 18.0, 60.0, 50.0, 0.8),
    (70.0, 24.0, 104.0, 46.0, 0.45),
    (30.0, 64.0, 54.0, 104.0, 0.6),
    (64.0, 60.0, 110.0, 90.0, 0.3),
    (78.0, 66.0, 96.0, 80.0, 0.9),
)


def _step(x: NDArray[np.float64], width_px: float) -> NDArray[np.float64]:
    """A smooth 0 → 1 step at x = 0 (logistic, ~``width_px`` wide)."""
    return 1.0 / (1.0 + np.exp(-x / width_px))


def rectangles(
    side: int = 128,
    shift: tuple[float, float] = (0.0, 0.0),
    rects: tuple[tuple[float, float, float, float, float], ...] = RECTANGLES,
    width_px: float = 0.7,
) -> Image:
    """Grey image (side, side) of bright rectangles with smooth edges on black, every shape
    moved by ``shift`` = (dx, dy) px (exactly: the image is evaluated at x − dx, y − dy)."""
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    x, y = x - shift[0], y - shift[1]
    img = np.zeros((side, side))
    for x0, y0, x1, y1, value in rects:
        img = np.maximum(
            img,
            value
            * _step(x - x0, width_px)
            * _step(x1 - x, width_px)
            * _step(y - y0, width_px)
            * _step(y1 - y, width_px),
        )
    return img.astype(np.float32)


def blobs(side: int = 128, shift: tuple[float, float] = (0.0, 0.0), seed: int = 0) -> Image:
    """Grey texture (side, side) of 60 Gaussian blobs of 2–5 px, moved by ``shift`` exactly."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    img = np.zeros((side, side))
    for cx, cy, s, a in zip(
        rng.uniform(10, side - 10, 60),
        rng.uniform(10, side - 10, 60),
        rng.uniform(2.0, 5.0, 60),
        rng.uniform(0.2, 1.0, 60),
        strict=True,
    ):
        img += a * np.exp(-((x - shift[0] - cx) ** 2 + (y - shift[1] - cy) ** 2) / (2 * s * s))
    return (img / img.max()).astype(np.float32)


def discs(side: int = 192, seed: int = 0, width_px: float = 0.3) -> Image:
    """Grey image (side, side) of 7 bright discs of 10–25 px radius with smooth edges on black:
    edges in every direction."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:side, 0:side].astype(np.float64)
    img = np.zeros((side, side))
    for _ in range(7):
        cx, cy = rng.uniform(30, side - 30, 2)
        radius, value = rng.uniform(10, 25), rng.uniform(0.3, 1.0)
        img = np.maximum(img, value * _step(radius - np.hypot(x - cx, y - cy), width_px))
    return img.astype(np.float32)


def u8(img: Image) -> NDArray[np.uint8]:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class StubModel:
    """What the stages read of a loaded model: its centre and bounding radius."""

    centre: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    radius: float = 1.0
    sha256: str = "stub"


class StubRenderer:
    """Renders ``draw(R, t, scale)`` (linear grey, float32) and counts the renders like the
    real renderer; no Mitsuba. The default draws a blank sky."""

    def __init__(  # type: ignore[no-untyped-def]
        self,
        camera: PinholeCamera,
        draw=None,
        model: StubModel | None = None,
        scales: tuple[float, ...] = (1.0,),
        window_sizes: dict[tuple[int, float], tuple[int, int]] | None = None,
    ) -> None:
        self.camera = camera
        self.model = model or StubModel()
        self.stats = RenderStats()
        self.lighting = LightingSpec((0.0, -0.6, -0.8), 3.0, 0.02)
        self.plans = {s: None for s in scales}
        self.window_sizes = dict(window_sizes or {})
        self._draw = draw or (lambda R, t, scale: np.zeros((camera.height, camera.width)))

    # the real renderer's window geometry (it needs only camera and window_sizes)
    _scaled = Renderer._scaled
    window_camera = Renderer.window_camera
    window_at = Renderer.window_at
    window_sides = Renderer.window_sides

    def camera_at(self, scale: float, window: Window | None = None) -> PinholeCamera:
        return self._scaled(scale) if window is None else self.window_camera(scale, window)

    def set_lighting(self, lighting: LightingSpec) -> None:
        self.lighting = lighting

    def render(
        self,
        R: NDArray,
        t: NDArray,
        scale: float = 1.0,
        spp: int = 1,
        seed: int = 0,
        window: Window | None = None,
    ) -> Image:
        """``draw`` at ``scale``; of ``window``, the whole image cropped to it."""
        self.stats.renders += 1
        image = np.asarray(self._draw(R, t, scale), dtype=np.float32)
        if window is None:
            return image
        (x, y), (w, h) = window.origin, self.window_sizes[(window.side, scale)]
        return image[y : y + h, x : x + w]
