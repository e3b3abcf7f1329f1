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

import numpy as np
from numpy.typing import NDArray

from schemas.estimate import IterationRecord, Stage
from schemas.options import EstimateOptions
from worker.align.features import Described, describe
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import EstimationCancelled
from worker.engine.images import FloatImage
from worker.engine.metrics import rotation_error_deg, translation_error
from worker.engine.photometry import render_to_grey, to_u8
from worker.engine.posemath import pose_to_schema
from worker.engine.renderer import LightingSpec, Renderer

Array = NDArray[np.float64]
ProgressCallback = Callable[[IterationRecord, int], None]
CancelCheck = Callable[[], bool]


@dataclass
class RenderedView:
    """A full-resolution render at a pose: linear RGB and display-encoded grey."""

    R: Array
    t: Array
    linear: FloatImage
    grey: FloatImage


@dataclass(frozen=True)
class LinearFit:
    """The learned linear model r ≈ J δp at the current pose, as the covariance reads it.

    ``J`` (2k, n) and ``r`` (2k,) are the whitened Jacobian rows and residuals of the k features
    used (n = 6, or 8 with the sun's tilt), ``w`` (k,) their weights and ``x`` (k, 2) their
    positions in the image, px.
    """

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
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    #: The request's lighting (a fitted sun changes the renderer's, see worker.align.sunfit).
    requested_lighting: LightingSpec = field(init=False)
    #: Renders made by this session (the renderer may be shared, or swapped mid-estimate).
    renders: int = 0
    _renders_at_last_record: int = 0
    _ref_u8: NDArray[np.uint8] | None = None
    _described: dict[tuple[str, int], Described] = field(default_factory=dict)
    _time_at_last_record: float = field(default_factory=time.perf_counter)

    def __post_init__(self) -> None:
        self.requested_lighting = self.renderer.lighting

    @property
    def camera(self) -> PinholeCamera:
        return self.renderer.camera

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
        """The reference's keypoints and descriptors per detector, computed once.

        Described on the reference stretched to 8 bits by its own levels: SIFT and ORB are
        indifferent to a monotonic tone change, so no render is needed to normalise it.
        """
        kinds = ("sift", "orb") if detector == "both" else (detector,)
        if self._ref_u8 is None:
            g = self.reference_grey
            lo, hi = np.percentile(g, [1.0, 99.9])
            self._ref_u8 = to_u8(np.clip(g - lo, 0.0, None), max(float(hi - lo), 1e-6))
        out = {}
        for kind in kinds:
            key = (kind, max_features)
            if key not in self._described:
                self._described[key] = describe(self._ref_u8, kind, max_features)
            out[kind] = self._described[key]
        return out

    def check_cancel(self) -> None:
        if self.should_cancel is not None and self.should_cancel():
            raise EstimationCancelled("the estimate was cancelled")

    # -- rendering -----------------------------------------------------------------------
    def render_view(self, R: Array, t: Array) -> RenderedView:
        """Full-resolution render at (R, t) with the main spp and the session's fixed seed.

        One seed for every main render keeps render noise from changing between nearby poses,
        so cost comparisons see the pose and not the sampler.
        """
        linear = self._render(R, t, 1.0, self.options.spp, self.options.seed)
        view = RenderedView(np.asarray(R), np.asarray(t), linear, render_to_grey(linear))
        self.views.setdefault("first", view)
        return view

    def current_view(self) -> RenderedView:
        """The render at the current pose (rendered once and kept)."""
        if self.current is None or not (
            np.array_equal(self.current.R, self.R) and np.array_equal(self.current.t, self.t)
        ):
            self.current = self.render_view(self.R, self.t)
        return self.current

    def render_perturbed(self, R: Array, t: Array, scale: float, seed: int) -> FloatImage:
        """Display-encoded grey render for Jacobian learning (perturbation scale and spp)."""
        return render_to_grey(self._render(R, t, scale, self.options.perturbation_spp, seed))

    def _render(self, R: Array, t: Array, scale: float, spp: int, seed: int) -> FloatImage:
        self.check_cancel()
        start = self.renderer.stats.seconds
        linear = self.renderer.render(R, t, scale=scale, spp=spp, seed=seed)
        self.timings_s["render"] += self.renderer.stats.seconds - start
        self.renders += 1
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
        self,
        stage: Stage,
        cost: float,
        step_norm: float,
        lam: float,
        accepted: bool,
        features: int,
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
