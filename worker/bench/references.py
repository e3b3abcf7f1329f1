"""Reference classes of the robustness suite: images made with physics unlike the estimator's.

The estimator renders with Mitsuba's direct integrator, a box pixel filter, a Lambertian BRDF,
the model's smooth normals, the request's sun and an sRGB encoding. Each class changes one of
those (or, ``combined``, several at once, as an image from another renderer or a real camera
would), so that ``proxpose bench --suite robustness`` shows which difference moves the estimate
and by how much, and above all how far the estimate drifts when it *starts at the truth*.

Classes marked ``tuned`` were looked at while the estimator was developed; the others were held
out of that loop, and the report lists them apart, so that a gain that holds only for the
differences the estimator was tuned on shows. The ``plain`` class is a control: the bench's
ray tracer with the estimator's own physics, so its drift is what another renderer alone (its
sampling, its pixel grid, its geometry code) moves the estimate; the report lists it on its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from worker.bench.raytrace import Physics, RayTracer
from worker.engine.camera import PinholeCamera
from worker.engine.images import srgb_encode
from worker.engine.meshes import LoadedModel
from worker.engine.renderer import LightingSpec, Renderer
from worker.engine.variant import one_render_thread

Array = NDArray[np.float64]
#: A class's group in the report: looked at while tuning, held out of that loop, or the control.
Group = Literal["tuned", "held out", "control"]
#: Sun irradiance and ambient radiance of the references (the request asks for the defaults).
IRRADIANCE, AMBIENT = 3.0, 0.02
#: Samples per pixel of the Mitsuba (path-traced) references.
MITSUBA_SPP = 128
#: Photon noise variance per unit of linear signal (with noise_sigma > 0).
SHOT_NOISE_GAIN = 1e-3


@dataclass(frozen=True)
class ReferenceClass:
    """How one class of references is made: the renderer and its physics, then the camera."""

    name: str
    description: str
    group: Group  # where the report lists it (see the module's docstring)
    renderer: str = "raytrace"  # raytrace (worker.bench.raytrace) | mitsuba (path tracing)
    physics: Physics = field(default_factory=Physics)
    faceted: bool = False  # mitsuba: flat shading normals
    sun_error_deg: float = 0.0
    exposure: float = 1.0
    gamma: float | None = None  # None: sRGB; else a plain power law 1/γ
    noise_sigma: float = 0.0  # read noise, fraction of full scale (and photon noise)
    blur_px: float = 0.0  # defocus, Gaussian σ
    motion_px: float = 0.0  # motion blur, length of a straight streak
    jpeg_quality: int = 0  # 0: no JPEG


_CLASSES = [
    ReferenceClass("plain", "the bench's ray tracer with the estimator's physics (a control)",
                   "control"),
    ReferenceClass("faceted", "flat shading normals (each triangle's own)", "tuned",
                   physics=Physics(normals="faceted")),
    ReferenceClass("glossy", "Blinn–Phong: 30 % specular, shininess 30", "tuned",
                   physics=Physics(brdf="phong")),
    ReferenceClass("regolith", "Lommel–Seeliger/Lambert mix (a small body's law)", "tuned",
                   physics=Physics(brdf="lommel")),
    ReferenceClass("path", "Mitsuba path tracing: inter-reflections, Gaussian filter", "tuned",
                   renderer="mitsuba"),
    ReferenceClass("defocus", "optical blur, Gaussian σ = 1 px", "tuned", blur_px=1.0),
    ReferenceClass("sun", "the request's sun 4° off", "tuned", sun_error_deg=4.0),
    ReferenceClass(
        "combined",
        "path tracing, flat normals, Gaussian filter, sun 3° off, exposure 0.7, gamma 2.2, noise",
        "tuned",
        renderer="mitsuba",
        faceted=True,
        sun_error_deg=3.0,
        exposure=0.7,
        gamma=2.2,
        noise_sigma=0.01,
    ),
    ReferenceClass("rough", "Oren–Nayar rough diffuse, σ = 25°", "held out",
                   physics=Physics(brdf="oren")),
    ReferenceClass("filter", "Gaussian pixel filter (σ = 0.5 px)", "held out",
                   physics=Physics(pixel_filter="gaussian")),
    # held out until 2026-12-06, when the streak of worker/align/blur.py was made looking at it
    ReferenceClass("motion", "motion blur, a 1.5 px streak", "tuned", motion_px=1.5),
    ReferenceClass("tone", "exposure 0.7, gamma 2.2 instead of sRGB", "held out", exposure=0.7,
                   gamma=2.2),
    ReferenceClass("bright", "exposure 3: the brighter parts clip", "held out", exposure=3.0),
    ReferenceClass("noise", "photon and read noise (σ = 1 % of full scale)", "held out",
                   noise_sigma=0.01),
    ReferenceClass("jpeg", "JPEG, quality 75", "held out", jpeg_quality=75),
]  # fmt: skip
REFERENCE_CLASSES: dict[str, ReferenceClass] = {c.name: c for c in _CLASSES}


def _streak(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    """A normalised straight-line kernel (motion blur) of ``length_px`` at ``angle_rad``."""
    n = 2 * int(np.ceil(length_px)) + 3
    k = np.zeros((n, n), np.float32)
    for s in np.linspace(-0.5 * length_px, 0.5 * length_px, 8 * n):
        x, y = n // 2 + s * np.cos(angle_rad), n // 2 + s * np.sin(angle_rad)
        k[int(round(y)), int(round(x))] += 1.0
    return k / k.sum()


def camera_response(
    linear: NDArray[np.float32], cls: ReferenceClass, rng: np.random.Generator
) -> NDArray[np.uint8]:
    """What the camera makes of the light: blur, exposure, noise, encoding, 8 bits, JPEG."""
    img = linear.astype(np.float32) * cls.exposure
    if cls.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cls.blur_px)
    if cls.motion_px > 0:
        img = cv2.filter2D(img, -1, _streak(cls.motion_px, rng.uniform(0.0, np.pi)))
    if cls.noise_sigma > 0:
        img = img + rng.normal(size=img.shape) * np.sqrt(np.clip(img, 0, None) * SHOT_NOISE_GAIN)
    img = np.clip(img, 0.0, 1.0)
    encoded = srgb_encode(img) if cls.gamma is None else np.power(img, 1.0 / cls.gamma)
    if cls.noise_sigma > 0:
        encoded = encoded + rng.normal(scale=cls.noise_sigma, size=encoded.shape)
    u8 = (np.clip(encoded, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if cls.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", u8[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, cls.jpeg_quality])
        u8 = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(u8)


_tracer_cache: dict[tuple[str, PinholeCamera], RayTracer] = {}


def _tracer(model: LoadedModel, camera: PinholeCamera) -> RayTracer:
    """The ray tracer of (model, camera), kept for the model's next case (one at a time)."""
    key = (model.sha256, camera)
    if key not in _tracer_cache:
        _tracer_cache.clear()
        _tracer_cache[key] = RayTracer(model, camera)
    return _tracer_cache[key]


def render_class_reference(
    model: LoadedModel,
    camera: PinholeCamera,
    R: Array,
    t: Array,
    sun: Array,
    cls: ReferenceClass,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """The 8-bit reference of class ``cls`` at the true pose, lit by the true ``sun``."""
    if cls.renderer == "mitsuba":
        renderer = Renderer(
            model,
            camera,
            LightingSpec(tuple(sun), IRRADIANCE, AMBIENT),  # type: ignore[arg-type]
            spp=MITSUBA_SPP,
            integrator="path",
            pixel_filter="gaussian",
            px_per_unit=None,
            shading="faceted" if cls.faceted else "file",
        )
        seed = int(rng.integers(1 << 30))
        with one_render_thread():
            linear = renderer.render(R, t, seed=seed)
    else:
        linear = _tracer(model, camera).render(R, t, sun, IRRADIANCE, AMBIENT, cls.physics, rng)
    return camera_response(linear, cls, rng)
