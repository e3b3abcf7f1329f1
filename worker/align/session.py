"""State of one estimate: the current pose, the renderer, counters, history and callbacks.

The stages (``worker.align.coarse``, ``worker.align.refine``) read and move the pose through a
Session; it records every iteration in the result's history and calls the progress callback.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from schemas.estimate import IterationRecord, Stage
from schemas.options import EstimateOptions
from worker.align.features import Described, describe
from worker.align.lm import MIN_SCALE_PX
from worker.align.pyramid import ladder_side
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import EstimationCancelled
from worker.engine.images import Box, FloatImage, on_sky
from worker.engine.metrics import rotation_error_deg, translation_error
from worker.engine.photometry import render_to_grey, to_u8
from worker.engine.posemath import pose_to_schema
from worker.engine.renderer import LightingSpec, Renderer, Window

Array = NDArray[np.float64]
#: A pixel belongs to the target's lit part above this fraction of the render's brightest.
LIT_FRACTION = 0.05
ProgressCallback = Callable[[IterationRecord, int], None]
CancelCheck = Callable[[], bool]


@dataclass
class RenderedView:
    """A render at a pose and a pyramid level: linear RGB and display-encoded grey, of the
    level's whole image or of a window of it."""

    R: Array
    t: Array
    linear: FloatImage
    grey: FloatImage
    level: float = 1.0  # image scale relative to the reference (1 = full resolution)
    spp: int = 0  # samples per pixel it was rendered with
    window: Window | None = None  # the window of the level's image it shows (None: all)
    frame: tuple[int, int] | None = None  # (w, h) of the level's whole image, for a window
    #: On the whole image: where the window's render was pasted (the sky is all around it).
    sky_box: Box | None = None

    def in_frame(self) -> RenderedView:
        """This view on the level's whole image: a window's render pasted onto the sky."""
        if self.window is None or self.frame is None:
            return self
        o, f = self.window.origin, self.frame
        box = Box.at(o, (self.grey.shape[1], self.grey.shape[0]))
        linear, grey = on_sky(self.linear, o, f), on_sky(self.grey, o, f)
        return RenderedView(self.R, self.t, linear, grey, self.level, self.spp, sky_box=box)


@dataclass(frozen=True)
class LinearFit:
    """The learned linear model r ≈ J δp at the current pose, as the covariance reads it:
    ``J`` (2k, n) and ``r`` (2k,) are the whitened Jacobian rows and residuals of the k features
    used (n = 6, or 8 with the sun's tilt), ``w`` (k,) their weights and ``x`` (k, 2) their
    positions in the image, px."""

    J: Array
    r: Array
    w: Array
    x: Array

    @property
    def features(self) -> int:
        """How many features the fit rests on."""
        return len(self.w)


@dataclass
class Session:
    """One estimate's state. The stages work at a pyramid ``level`` (an image scale: 1 = the
    reference's resolution); ``camera``, ``ref_image``, ``ref_grey`` and every render are at
    that level, so feature positions and residuals are in the level's pixels, while the pose
    is the same at every level."""

    renderer: Renderer
    reference: FloatImage  # as given: [0, 1], grey (H, W) or colour (H, W, 3)
    reference_grey: FloatImage  # its channel mean, [0, 1]
    options: EstimateOptions
    R: Array
    t: Array
    truth: tuple[Array, Array] | None = None
    on_iteration: ProgressCallback | None = None
    should_cancel: CancelCheck | None = None
    history: list[IterationRecord] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    views: dict[str, RenderedView] = field(default_factory=dict)  # "first", "second", "final"
    current: RenderedView | None = None
    #: The learned linear model at the current pose (for the covariance and the result).
    fit: LinearFit | None = None
    #: The last LM stage's state (worker.align.refine.StageState), for a tracker to go on from.
    last_stage: Any = None
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    #: The request's lighting (a fitted sun changes the renderer's, see worker.align.sunfit).
    requested_lighting: LightingSpec = field(init=False)
    #: Renders made by this session (the renderer may be shared, or swapped mid-estimate), and
    #: what they cost in full-resolution renders at the main spp (pixels × samples).
    renders: int = 0
    render_cost: float = 0.0
    #: The working level, and the scale of the perturbation renders at each level (the
    #: renderer has a sensor for every one of them).
    level: float = 1.0
    perturbation_scales: dict[float, float] = field(default_factory=dict)
    #: Floor of the LM's robust residual scale, whitened px (tracker.TRACK_ROBUST_FLOOR_PX).
    robust_floor_px: float = MIN_SCALE_PX
    #: Samples per pixel of the main renders of the stage in progress (None: options.spp).
    stage_spp: int | None = None
    #: The window's ladder side and centre (full-resolution px; None: the whole image): the
    #: levels the renderer has that window for then work on it instead of the whole image
    #: (worker.align.pyramid), and the centre's offset from the image of the model's centre.
    window_side: int | None = None
    window_centre: tuple[float, float] = (0.0, 0.0)
    window_offset: tuple[float, float] = (0.0, 0.0)
    #: (ladder side, centre px) of a window that holds the whole target (a tracked frame's):
    #: whole-image renders render only it, pasted onto the sky. None: render the whole image.
    sky_window: tuple[int, tuple[float, float]] | None = None
    #: Whether the target is a smooth body (options.reflectance "auto"; None: not yet seen),
    #: and the law its first fit found: (w, c) (worker.align.reflectance.Law).
    smooth_body: bool | None = None
    law: tuple[float, float] | None = None
    _pyramid: dict[float, tuple[FloatImage, FloatImage]] = field(default_factory=dict)
    _renders_at_last_record: int = 0
    _described: dict[tuple[str, int, float, Window | None], Described] = field(default_factory=dict)
    _time_at_last_record: float = field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        self.requested_lighting = self.renderer.lighting

    @property
    def camera(self) -> PinholeCamera:
        """The camera at the working level (of its window, if it has one)."""
        return self.renderer.camera_at(self.level, self.window)

    @property
    def window(self) -> Window | None:
        """The window at the working level (None: the whole image)."""
        return self._window_at(self.level)

    def _window_at(self, scale: float) -> Window | None:
        if self.window_side is None:
            return None
        return self.renderer.window_at(scale, self.window_side, self.window_centre)

    def place_window(self, view: RenderedView) -> None:
        """Window the refinement around the target's lit part in ``view`` (a render of the
        whole image, at any level): the smallest ladder side that holds it with a margin, or
        the whole image when none does (a target that fills the frame)."""
        lit = view.grey > LIT_FRACTION * float(view.grey.max())
        if not self.renderer.window_sizes or view.window is not None or not lit.any():
            return
        ys, xs = np.nonzero(lit)
        sx = self.renderer.camera.width / view.grey.shape[1]
        sy = self.renderer.camera.height / view.grey.shape[0]
        extent = max((xs.max() - xs.min() + 1) * sx, (ys.max() - ys.min() + 1) * sy)
        self.window_side = ladder_side(self.renderer.window_sides, extent)
        centre = (
            (xs.min() + xs.max() + 1) / 2 * sx - 0.5,
            (ys.min() + ys.max() + 1) / 2 * sy - 0.5,
        )
        u, v = self._model_centre_px(view.R, view.t)
        self.window_offset = (centre[0] - u, centre[1] - v)
        self.centre_window()

    def centre_window(self) -> None:
        """Move the window with the target: its centre keeps its offset from the image of the
        model's centre at the current pose. The current view is rendered again if it moved."""
        if self.window_side is None:
            return
        before = self.window
        u, v = self._model_centre_px(self.R, self.t)
        self.window_centre = (u + self.window_offset[0], v + self.window_offset[1])
        if self.window != before:
            self.current, self.fit = None, None

    def _model_centre_px(self, R: Array, t: Array) -> tuple[float, float]:
        """Where the model's centre is imaged at pose (R, t), full-resolution px."""
        u, v = self.renderer.camera.project(R @ self.renderer.model.centre + t)[0]
        return float(u), float(v)

    @property
    def ref_image(self) -> FloatImage:
        """The reference at the working level (area-averaged to the level's camera)."""
        return self._at_level()[0]

    @property
    def ref_grey(self) -> FloatImage:
        """The reference's grey at the working level."""
        return self._at_level()[1]

    def _at_level(self) -> tuple[FloatImage, FloatImage]:
        if self.level == 1.0:
            image, grey = self.reference, self.reference_grey
        else:
            if self.level not in self._pyramid:
                cam = self.renderer.camera_at(self.level)
                size = (cam.width, cam.height)
                image = cv2.resize(self.reference, size, interpolation=cv2.INTER_AREA)
                grey = cv2.resize(self.reference_grey, size, interpolation=cv2.INTER_AREA)
                self._pyramid[self.level] = (image, grey)
            image, grey = self._pyramid[self.level]
        if (window := self.window) is None:
            return image, grey
        (x, y), cam = window.origin, self.camera
        return image[y : y + cam.height, x : x + cam.width], grey[
            y : y + cam.height, x : x + cam.width
        ]

    @property
    def perturbation_scale(self) -> float:
        """The scale of the perturbation renders at the working level."""
        default = min(s for s in self.renderer.plans if s <= self.level)
        return self.perturbation_scales.get(self.level, default)

    def set_level(self, level: float) -> None:
        """Work at ``level`` from now on (the renderer must have a sensor for it)."""
        if level not in self.renderer.plans:
            raise ValueError(f"the renderer has no sensor at scale {level}")
        if level != self.level:
            self.level, self.current, self.fit = level, None, None

    @property
    def range_(self) -> float:
        """Distance to the target origin, ‖t‖, scene units."""
        return float(np.linalg.norm(self.t))

    @property
    def iterations(self) -> int:
        return len(self.history)

    @property
    def iterations_left(self) -> int:
        return self.options.max_iterations - len(self.history)

    @contextmanager
    def timed(self, part: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings_s[part] += time.perf_counter() - start

    def reference_described(self, detector: str, max_features: int) -> dict[str, Described]:
        """The reference's keypoints and descriptors per detector at the working level, computed
        once per level.

        Described on the reference stretched to 8 bits by its own levels: SIFT and ORB are
        indifferent to a monotonic tone change, so no render is needed to normalise it.
        """
        kinds = ("sift", "orb") if detector == "both" else (detector,)
        out = {}
        for kind in kinds:
            key = (kind, max_features, self.level, self.window)
            if key not in self._described:
                self._described[key] = describe(self._reference_u8(), kind, max_features)
            out[kind] = self._described[key]
        return out

    def _reference_u8(self) -> NDArray[np.uint8]:
        g = self.ref_grey
        lo, hi = np.percentile(g, [1.0, 99.9])
        return to_u8(np.clip(g - lo, 0.0, None), max(float(hi - lo), 1e-6))

    def check_cancel(self) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise EstimationCancelled("the estimate was cancelled")

    # -- rendering -----------------------------------------------------------------------
    def render_view(self, R: Array, t: Array) -> RenderedView:
        """Render at (R, t) at the working level with the main spp and the session's seed.

        One seed for every main render keeps render noise from changing between nearby poses,
        so cost comparisons see the pose and not the sampler.
        """
        window, spp = self.window, self.main_spp
        sky = self._sky_window(self.level) if window is None else None
        linear = self._render(R, t, self.level, spp, self.options.seed, window or sky)
        at, whole = window or sky, self.renderer.camera_at(self.level)
        frame = None if at is None else (whole.width, whole.height)
        grey = render_to_grey(linear)
        view = RenderedView(np.asarray(R), np.asarray(t), linear, grey, self.level, spp, at, frame)
        if sky is not None:
            view = view.in_frame()  # a sky window's render on the whole image
        self.views.setdefault("first", view)
        return view

    def _sky_window(self, scale: float) -> Window | None:
        """The sky window at ``scale`` (None without one or a sensor for it)."""
        return None if self.sky_window is None else self.renderer.window_at(scale, *self.sky_window)

    @property
    def main_spp(self) -> int:
        """Samples per pixel of the main renders now."""
        return self.stage_spp or self.options.spp

    def current_view(self) -> RenderedView:
        """The render at the current pose, level, window and spp (rendered once and kept)."""
        if (
            self.current is None
            or self.current.level != self.level
            or self.current.spp != self.main_spp
            or self.current.window != self.window
            or not (
                np.array_equal(self.current.R, self.R) and np.array_equal(self.current.t, self.t)
            )
        ):
            self.current = self.render_view(self.R, self.t)
        return self.current

    @property
    def perturbation_camera(self) -> PinholeCamera:
        """The camera of the perturbation renders at the working level (and window)."""
        scale = self.perturbation_scale
        return self.renderer.camera_at(scale, self._window_at(scale))

    def render_perturbed(self, R: Array, t: Array, seed: int) -> FloatImage:
        """Display-encoded grey render for Jacobian learning (at the level's perturbation
        scale, with the perturbation spp; of the window at that scale, if any; a sky window's
        render pasted onto the whole image)."""
        spp, scale = self.options.perturbation_spp, self.perturbation_scale
        window = self._window_at(scale)
        sky = self._sky_window(scale) if window is None else None
        grey = render_to_grey(self._render(R, t, scale, spp, seed, window or sky))
        whole = self.renderer.camera_at(scale)
        return grey if sky is None else on_sky(grey, sky.origin, (whole.width, whole.height))

    def raycast(self, R: Array, t: Array, uv: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Surface points (N, 3, model frame) seen through the working level's pixels uv
        (N, 2) at pose (R, t), and which rays hit (see Renderer.raycast)."""
        return self.renderer.raycast(R, t, uv, self.level, self.window)

    def _render(
        self, R: Array, t: Array, scale: float, spp: int, seed: int, window: Window | None = None
    ) -> FloatImage:
        self.check_cancel()
        start = self.renderer.stats.seconds
        linear = self.renderer.render(R, t, scale=scale, spp=spp, seed=seed, window=window)
        self.timings_s["render"] += self.renderer.stats.seconds - start
        self.renders += 1
        full = self.renderer.camera_at(1.0)
        self.render_cost += (
            linear.shape[0] * linear.shape[1] * spp / (full.width * full.height * self.options.spp)
        )
        return linear

    def use_renderer(self, renderer: Renderer) -> None:
        """Render from now on with ``renderer`` (same model and camera, other physics), lit
        as the current one is; the current view is rendered again on demand."""
        renderer.set_lighting(self.renderer.lighting)
        self.renderer, self.current = renderer, None

    def accept(self, view: RenderedView) -> None:
        """Move to the pose of ``view`` (its render becomes the current one)."""
        self.R, self.t, self.current = view.R, view.t, view
        self.views.setdefault("second", view)

    # -- history -------------------------------------------------------------------------
    def record(
        self, stage: Stage, cost: float, step_norm: float, lam: float, accepted: bool, features: int
    ) -> IterationRecord:
        now = time.perf_counter()
        renders = self.renders
        rot_err = trans_err = None
        if self.truth is not None:
            rot_err = rotation_error_deg(self.truth[0], self.R)
            trans_err = translation_error(self.truth[1], self.t)
        rec = IterationRecord(
            iteration=len(self.history) + 1,
            stage=stage,
            pose=pose_to_schema(self.R, self.t),
            cost=float(cost),
            step_norm=float(step_norm),
            lambda_=float(lam),
            accepted=accepted,
            features=int(features),
            renders=renders - self._renders_at_last_record,
            seconds=now - self._time_at_last_record,
            rotation_error_deg=rot_err,
            translation_error=trans_err,
        )
        self._renders_at_last_record, self._time_at_last_record = renders, now
        self.history.append(rec)
        if self.on_iteration is not None:
            self.on_iteration(rec, self.options.max_iterations)
        return rec
