"""Rendering a loaded model at a pose with Mitsuba 3, and ray casting its surface.

The scene is built once per (model, camera, scales): the model stays in its own frame, which is
Mitsuba's world frame, and a pose b = R a + t moves the *camera* (and the sun with it) through
``mi.traverse`` updates — no scene reload, no recompilation. One sensor is built per resolution
scale (the full image and the cheaper perturbation renders), and optionally one per *window*
(ladder side and scale): a film of fixed size that sees a movable sub-rectangle of the scaled
image (a target covering a third of the frame should not pay for all of it). A window moves
through its sensor's principal point offset, which the render kernel reads as a parameter:
moving it recompiles nothing (changing a film's crop offset would).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from worker.engine.camera import PinholeCamera, RenderPlan, plan_render, warp_to_target
from worker.engine.exceptions import RenderError
from worker.engine.kernels import frozen_render, plain_render, use_frozen
from worker.engine.meshes import LoadedModel
from worker.engine.rays import intersect
from worker.engine.scene_meshes import scene_mesh

Array = NDArray[np.float64]

#: OpenCV camera axes (x right, y down) from Mitsuba's (x left, y up): p_cv = FLIP · p_mi.
CV_FROM_MI = np.diag([-1.0, -1.0, 1.0])
#: Clip planes in model radii (a target farther than FAR_CLIP_RADII is below a pixel anyway).
NEAR_CLIP_RADII = 1e-4
FAR_CLIP_RADII = 1e5
#: Shading normals a renderer can use: the model file's vertex normals (faceted where it has
#: none), or every triangle's own normal.
SHADINGS = ("file", "faceted")
#: Pixel sampler: multi-jittered samples cut the edge noise of a render about 2× against
#: independent ones at the same count, and render noise moves the cost minimum.
SAMPLER = "multijitter"
#: A sensor: its scale, and its window's ladder side (full-resolution px; 0: the whole image).
SensorKey = tuple[float, int]


@dataclass(frozen=True)
class Window:
    """A window of the image at one scale: the ladder side whose sensor renders it (full-
    resolution px) and its top-left pixel in the scaled image."""

    side: int
    origin: tuple[int, int]


@dataclass(frozen=True)
class LightingSpec:
    """Sun direction (camera frame, unit, target → sun), sun irradiance and ambient radiance."""

    sun_direction: tuple[float, float, float]
    sun_irradiance: float
    ambient: float


@dataclass
class RenderStats:
    """Counters for the result's render count and the profile."""

    renders: int = 0
    seconds: float = 0.0
    by_scale: dict[float, int] = field(default_factory=dict)


def _unit_tuple(v: Array) -> tuple[float, float, float]:
    u = np.asarray(v, dtype=np.float64) / max(float(np.linalg.norm(v)), 1e-12)
    return (float(u[0]), float(u[1]), float(u[2]))


def frame_with_z(d: ArrayLike) -> Array:
    """A rotation matrix whose third column is the unit vector d (columns = local axes)."""
    z = np.asarray(d, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def scalar_transform(M: Array) -> object:
    import mitsuba as mi

    return mi.ScalarTransform4f(np.asarray(M, dtype=np.float64).tolist())


class Renderer:
    """Renders one model through one camera at any pose; see the module docstring."""

    def __init__(
        self,
        model: LoadedModel,
        camera: PinholeCamera,
        lighting: LightingSpec,
        scales: tuple[float, ...] = (1.0,),
        spp: int = 8,
        integrator: str = "direct",
        pixel_filter: str = "box",
        px_per_unit: float | None = None,
        shading: str = "file",
        window_sizes: dict[tuple[int, float], tuple[int, int]] | None = None,
    ) -> None:
        import mitsuba as mi

        self.model = model
        self.camera = camera
        self.spp = spp
        # 'direct' (sun + ambient, one bounce) is what the estimator renders with; 'path' and
        # a Gaussian filter give test references a renderer setup of their own.
        self._integrator = integrator
        self._pixel_filter = pixel_filter
        # Textures are prefiltered to about one texel per pixel at the working range: Mitsuba's
        # bitmap has no mip-mapping, and a texture much finer than the pixels aliases into
        # sampling noise that no feature tracker can see through.
        self.px_per_unit = px_per_unit
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        self.shading = shading
        self.plans: dict[float, RenderPlan] = {s: plan_render(self._scaled(s)) for s in scales}
        # Windows need a square-pixel camera: a warped source film would change its size with
        # the window's position.
        #: Film size (w, h) of the window sensor of each (ladder side, scale).
        self.window_sizes = dict(window_sizes or {}) if camera.is_square_pixel else {}
        self._sensors: list[tuple[SensorKey, RenderPlan]] = [
            ((s, 0), plan) for s, plan in self.plans.items()
        ] + [
            ((s, side), plan_render(self.window_camera(s, Window(side, (0, 0)))))
            for side, s in self.window_sizes
        ]
        self._origins = dict.fromkeys(self.window_sizes, (0, 0))
        self.stats = RenderStats()
        self._lighting = lighting
        self._R = np.eye(3)  # the attitude of the last pose: the sun turns with the camera
        self._held_sun: Array | None = None  # towards the sun, model frame (see hold_sun)
        try:
            self.scene = mi.load_dict(self.scene_dict())
        except Exception as exc:
            raise RenderError(f"cannot build the Mitsuba scene: {exc}") from exc
        self.params = mi.traverse(self.scene)
        frozen = use_frozen(mi.variant())
        self._render_fn = frozen_render(len(self._sensors)) if frozen else plain_render
        self._sensor_index = {key: i for i, (key, _) in enumerate(self._sensors)}
        self.set_lighting(lighting)

    def _scaled(self, scale: float) -> PinholeCamera:
        return self.camera if scale == 1.0 else self.camera.scaled(scale)

    @property
    def window_sides(self) -> list[int]:
        """The ladder sides (full-resolution px) this renderer has window sensors for."""
        return sorted({side for side, _ in self.window_sizes})

    def window_camera(self, scale: float, window: Window) -> PinholeCamera:
        """The camera of ``window`` at ``scale`` (its origin in the scaled image's pixels)."""
        w, h = self.window_sizes[(window.side, scale)]
        return self._scaled(scale).cropped(window.origin[0], window.origin[1], w, h)

    def window_at(self, scale: float, side: int, centre: tuple[float, float]) -> Window | None:
        """The window of ladder ``side`` at ``scale`` centred as near ``centre`` (full-
        resolution px) as the image's edges allow; None without a sensor for it."""
        if (side, scale) not in self.window_sizes:
            return None
        w, h = self.window_sizes[(side, scale)]
        cam = self._scaled(scale)
        sx, sy = cam.width / self.camera.width, cam.height / self.camera.height
        x = round((centre[0] + 0.5) * sx - 0.5 - 0.5 * (w - 1))
        y = round((centre[1] + 0.5) * sy - 0.5 - 0.5 * (h - 1))
        return Window(side, (min(max(x, 0), cam.width - w), min(max(y, 0), cam.height - h)))

    # -- scene construction -------------------------------------------------------------
    def scene_dict(self) -> dict[str, object]:
        """The Mitsuba scene description this renderer loads (sensors, lights, meshes)."""
        scene: dict[str, object] = {
            "type": "scene",
            "integrator": (
                {"type": "path", "max_depth": 4, "hide_emitters": True}
                if self._integrator == "path"
                else {"type": "direct", "hide_emitters": True}
            ),
            # Emitter sampling picks one light per sample in proportion to sampling_weight:
            # the sun takes every pick, and the ambient term comes from BSDF samples alone.
            # (Equal weights made half the sun samples miss: heavy binary noise.)
            "sun": {
                "type": "directional",
                "direction": [0.0, 0.0, 1.0],
                "irradiance": 1.0,
                "sampling_weight": 1.0,
            },
            "ambient": {"type": "constant", "radiance": 0.0, "sampling_weight": 0.0},
        }
        r = self.model.radius
        for i, (_, plan) in enumerate(self._sensors):
            px, py = plan.principal_point_offset
            scene[f"sensor{i}"] = {
                "type": "perspective",
                "fov_axis": "x",
                "fov": plan.x_fov_deg,
                # Mitsuba shifts the image opposite to its principal point offset (checked
                # against K[R|t] projection in tests/test_projection.py).
                "principal_point_offset_x": -px,
                "principal_point_offset_y": -py,
                # Fixed clip planes: changing them recompiles the render kernel.
                "near_clip": NEAR_CLIP_RADII * r,
                "far_clip": FAR_CLIP_RADII * r,
                # Distinct start poses: identical sensors would be merged by Mitsuba.
                "to_world": scalar_transform(np.eye(4) + np.eye(4, k=3) * i),
                "film": {
                    "type": "hdrfilm",
                    "width": plan.source.width,
                    "height": plan.source.height,
                    "rfilter": {"type": self._pixel_filter},
                    "pixel_format": "rgb",
                },
                "sampler": {"type": SAMPLER, "sample_count": self.spp},
            }
        for i, part in enumerate(self.model.parts):
            scene[f"part{i}"] = scene_mesh(part, f"part{i}", self.px_per_unit, self.shading)
        return scene

    # -- pose and lighting --------------------------------------------------------------
    def set_pose(self, R: ArrayLike, t: ArrayLike, sensor: int | None = None) -> None:
        """Place the camera (of every sensor, or of the one about to render) so that the model
        appears at pose b = R a + t."""
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        cam2model = np.eye(4)
        cam2model[:3, :3] = R.T @ CV_FROM_MI
        cam2model[:3, 3] = -R.T @ t
        for i in range(len(self._sensors)) if sensor is None else (sensor,):
            self._put_transform(f"sensor{i}.to_world", cam2model)
        self._R = R
        if self._held_sun is not None:
            self._sun_held_at(R)
        self._update_sun()
        self.params.update()

    def hold_sun(self, sun_model: ArrayLike) -> None:
        """Keep the sun fixed in the model frame (``sun_model``, towards the sun) whatever the
        pose, the lighting's camera-frame direction following each pose (until release_sun or
        set_lighting)."""
        self._held_sun = np.asarray(sun_model, dtype=np.float64)
        self._sun_held_at(self._R)
        self._update_sun()
        self.params.update()

    def release_sun(self, R: ArrayLike) -> None:
        """Let a held sun turn with the camera again, from the direction it has at attitude
        ``R``; nothing when no sun is held."""
        if self._held_sun is None:
            return
        self._sun_held_at(np.asarray(R, dtype=np.float64))
        self.set_lighting(self._lighting)

    def _sun_held_at(self, R: Array) -> None:
        """The lighting's camera-frame sun that keeps the held one at attitude ``R``."""
        assert self._held_sun is not None
        self._lighting = replace(self._lighting, sun_direction=_unit_tuple(R @ self._held_sun))

    @property
    def lighting(self) -> LightingSpec:
        """The lighting renders use now."""
        return self._lighting

    def set_lighting(self, lighting: LightingSpec) -> None:
        """Render with ``lighting`` from now on (its sun in the camera frame; a held sun is
        let go)."""
        self._held_sun = None
        self._lighting = lighting
        self.params["sun.irradiance.value"] = lighting.sun_irradiance
        self.params["ambient.radiance.value"] = lighting.ambient
        self._update_sun()
        self.params.update()

    def _update_sun(self) -> None:
        # Light travels from the sun towards the target: −sun_direction, camera frame → model.
        d_model = self._R.T @ -np.asarray(self._lighting.sun_direction, dtype=np.float64)
        M = np.eye(4)
        M[:3, :3] = frame_with_z(d_model)
        self._put_transform("sun.to_world", M)

    def _put_transform(self, key: str, M: Array) -> None:
        self.params[key] = type(self.params[key])(M.tolist())

    # -- rendering ----------------------------------------------------------------------
    def render(
        self,
        R: ArrayLike,
        t: ArrayLike,
        scale: float = 1.0,
        spp: int | None = None,
        seed: int = 0,
        window: Window | None = None,
    ) -> NDArray[np.float32]:
        """Linear RGB render (H, W, 3) float32 at pose (R, t), on the scaled camera's grid, or
        of ``window`` of it."""
        start = time.perf_counter()
        sensor = self._sensor_index[(scale, 0 if window is None else window.side)]
        if window is None:
            plan = self.plans[scale]
        else:
            plan = self._move_window(scale, window, sensor)
        self.set_pose(R, t, sensor)
        try:
            img = self._render_fn(self.scene, sensor, spp or self.spp, seed)
        except Exception as exc:
            raise RenderError(f"render failed: {exc}") from exc
        out = warp_to_target(np.asarray(img, dtype=np.float32)[..., :3], plan)
        self.stats.renders += 1
        self.stats.seconds += time.perf_counter() - start
        self.stats.by_scale[scale] = self.stats.by_scale.get(scale, 0) + 1
        return out

    def _move_window(self, scale: float, window: Window, sensor: int) -> RenderPlan:
        """Point ``sensor``, the sensor of ``window``, at its origin (the principal point
        offset; the caller's set_pose applies the update) and return its plan there."""
        plan = plan_render(self.window_camera(scale, window))
        key = (window.side, scale)
        if self._origins[key] != window.origin:
            px, py = plan.principal_point_offset
            self.params[f"sensor{sensor}.principal_point_offset_x"] = -px
            self.params[f"sensor{sensor}.principal_point_offset_y"] = -py
            self._origins[key] = window.origin
        return plan

    def camera_at(self, scale: float, window: Window | None = None) -> PinholeCamera:
        """The target camera of the render at ``scale`` (of ``window`` of it)."""
        return self.plans[scale].target if window is None else self.window_camera(scale, window)

    # -- ray casting --------------------------------------------------------------------
    def raycast(
        self,
        R: ArrayLike,
        t: ArrayLike,
        uv: ArrayLike,
        scale: float = 1.0,
        window: Window | None = None,
    ) -> tuple[Array, NDArray[np.bool_]]:
        """Surface points (N, 3, model frame) seen through pixels uv (N, 2) at pose (R, t), in
        the image at ``scale`` (in ``window`` of it).

        Returns the points and a mask of the rays that hit the model.
        """
        hit, points, _ = self._cast(R, t, uv, scale, window)
        return points, hit

    def surface_normals(
        self,
        R: ArrayLike,
        t: ArrayLike,
        uv: ArrayLike,
        scale: float = 1.0,
        window: Window | None = None,
        geometric: bool = False,
    ) -> tuple[Array, NDArray[np.bool_]]:
        """Shading normals (N, 3, camera frame) of the surface seen through pixels uv (N, 2)
        at pose (R, t) in the image at ``scale`` (in ``window`` of it), and which rays hit
        the model; with ``geometric`` the normals of the triangles hit."""
        hit, _, normals = self._cast(R, t, uv, scale, window, geometric)
        return normals @ np.asarray(R, dtype=np.float64).T, hit

    def _cast(
        self,
        R: ArrayLike,
        t: ArrayLike,
        uv: ArrayLike,
        scale: float,
        window: Window | None,
        geometric: bool = False,
    ) -> tuple[NDArray[np.bool_], Array, Array]:
        """The rays through pixels uv at pose (R, t), cast in the model frame: hits, points
        and shading (or ``geometric``) normals (model frame), one per pixel."""
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        uv = np.atleast_2d(np.asarray(uv, dtype=np.float64))
        n = len(uv)
        if n == 0:
            return np.zeros(0, dtype=bool), np.zeros((0, 3)), np.zeros((0, 3))
        d_model = self.camera_at(scale, window).rays(uv) @ R  # (Rᵀ d)ᵀ
        hit, points, normals = intersect(self.scene, -R.T @ t, d_model, geometric)
        return hit[:n], points[:n], normals[:n]

    def coverage(self, R: ArrayLike, t: ArrayLike, grid: int = 64) -> float:
        """Fraction of the image the model covers at (R, t), from a grid of rays."""
        cam = self.camera
        us, vs = np.linspace(0, cam.width - 1, grid), np.linspace(0, cam.height - 1, grid)
        uv = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
        return float(self.raycast(R, t, uv)[1].mean())
