"""Synthetic test cases: references rendered independently of the estimator's own renders.

A case draws a true pose, a sun, and an initial guess offset from the truth by a rotation angle
and a fraction of the range; the reference is rendered with a *different* renderer setup
(path tracing with inter-reflections, Gaussian pixel filter, many samples, gamma 2.2 instead of
sRGB), a different exposure, a sun a few degrees off the one in the request, and sensor noise,
then quantised to 8 bits. Tests and ``proxpose bench`` use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.camera import Camera
from schemas.estimate import EstimateRequest
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from schemas.pose import Pose
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_quaternion
from worker.engine.renderer import LightingSpec, Renderer
from worker.engine.variant import one_render_thread

Array = NDArray[np.float64]


@dataclass
class CaseSpec:
    """How to draw one case."""

    offset_deg: float  # rotation of the initial guess from the truth
    offset_frac: float  # translation offset as a fraction of the range
    sun_error_deg: float = 3.0
    exposure: float = 0.7  # reference brightness relative to the request's lighting
    noise_sigma: float = 0.01  # Gaussian noise on the encoded image, fraction of full scale
    fill: float = 0.6  # target diameter as a fraction of the smaller image side
    blur_px: float = 0.0  # extra optical blur (Gaussian σ, px), applied to the light


@dataclass
class Case:
    reference: NDArray[np.uint8]  # (H, W, 3) 8-bit, as a camera file would hold it
    request: EstimateRequest
    R_true: Array
    t_true: Array
    sun_true: Array  # the sun the reference was rendered with (the request's is off by sun_error)


def from_truth(case: Case) -> Case:
    """The case with its initial guess replaced by the true pose."""
    truth = case.request.ground_truth
    request = case.request.model_copy(update={"initial_pose": truth})
    return Case(case.reference, request, case.R_true, case.t_true, case.sun_true)


def random_rotation(rng: np.random.Generator) -> Array:
    q = rng.normal(size=4)
    from worker.engine.posemath import quaternion_to_matrix

    return quaternion_to_matrix(q / np.linalg.norm(q))


def random_unit(rng: np.random.Generator) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def perturb_direction(d: Array, angle_deg: float, rng: np.random.Generator) -> Array:
    """``d`` rotated by ``angle_deg`` about a random axis perpendicular to it."""
    axis = np.cross(d, random_unit(rng))
    return axis_angle_to_matrix(axis, np.radians(angle_deg)) @ d


def pose_json(R: Array, t: Array) -> Pose:
    return Pose(t=list(map(float, t)), quaternion=list(map(float, matrix_to_quaternion(R))))


def draw_truth(
    model: LoadedModel, camera: PinholeCamera, spec: CaseSpec, rng: np.random.Generator
) -> tuple[Array, Array]:
    """A random attitude with the target's centre near the optical axis, filling ``fill``."""
    R = random_rotation(rng)
    f = min(camera.fx, camera.fy)
    side = min(camera.width, camera.height)
    d = model.radius * f / (0.5 * spec.fill * side)
    lateral = rng.uniform(-0.1, 0.1, 2) * d * side / f
    centre_cam = np.array([lateral[0], lateral[1], d])
    return R, centre_cam - R @ model.centre


def draw_sun(rng: np.random.Generator) -> Array:
    """Sun direction (camera frame) at a phase angle of 20–70° (lit side towards the camera)."""
    phase = np.radians(rng.uniform(20.0, 70.0))
    az = rng.uniform(0.0, 2 * np.pi)
    return np.array([np.sin(phase) * np.cos(az), np.sin(phase) * np.sin(az), -np.cos(phase)])


def render_reference(
    model: LoadedModel,
    camera: PinholeCamera,
    R: Array,
    t: Array,
    sun: Array,
    spec: CaseSpec,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """The reference image: a different renderer setup, exposure, gamma, noise, 8 bits."""
    light = LightingSpec(tuple(sun), 3.0 * spec.exposure, 0.02 * spec.exposure)
    d = float(np.linalg.norm(R @ model.centre + t))
    r = Renderer(
        model,
        camera,
        light,
        spp=64,
        integrator="path",
        pixel_filter="gaussian",
        px_per_unit=0.5 * (camera.fx + camera.fy) / d,
    )
    seed = int(rng.integers(1 << 30))
    with one_render_thread():
        linear = r.render(R, t, seed=seed)
    if spec.blur_px > 0:
        import cv2

        linear = cv2.GaussianBlur(linear, (0, 0), spec.blur_px)
    # Photon noise on the linear signal, then read noise on the encoded 8-bit values.
    shot = rng.normal(size=linear.shape) * np.sqrt(np.clip(linear, 0, None) * 1e-3)
    encoded = np.power(np.clip(linear + shot, 0, 1), 1 / 2.2)
    noisy = encoded + rng.normal(scale=spec.noise_sigma, size=linear.shape)
    return (np.clip(noisy, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def make_case(
    model: LoadedModel,
    camera: Camera,
    spec: CaseSpec,
    seed: int,
    options: EstimateOptions | None = None,
    reference: str = "standard",
) -> Case:
    """One seeded case: reference image, request (with ground truth) and the true pose.

    ``reference`` is "standard" (the default suite's renderer setup, :func:`render_reference`)
    or a class of :mod:`worker.bench.references`; for those the truth, the sun and the initial
    guess depend on the seed alone, so every class of one seed poses the same problem.
    """
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.from_schema(camera)
    R, t = draw_truth(model, cam, spec, rng)
    sun = draw_sun(rng)
    if reference == "standard":
        sun_true = perturb_direction(sun, spec.sun_error_deg, rng)
        image = render_reference(model, cam, R, t, sun_true, spec, rng)
        R0, t0 = _initial_guess(R, t, spec, rng)
    else:
        from worker.bench.references import REFERENCE_CLASSES, render_class_reference

        cls = REFERENCE_CLASSES[reference]
        sun_true = perturb_direction(sun, cls.sun_error_deg, rng)
        R0, t0 = _initial_guess(R, t, spec, rng)
        render_rng = np.random.default_rng([seed, 1])
        image = render_class_reference(model, cam, R, t, sun_true, cls, render_rng)
    request = EstimateRequest(
        camera=camera,
        initial_pose=pose_json(R0, t0),
        lighting=Lighting(sun_direction=list(map(float, sun))),
        options=options or EstimateOptions(),
        ground_truth=pose_json(R, t),
    )
    return Case(image, request, R, t, sun_true)


def _initial_guess(
    R: Array, t: Array, spec: CaseSpec, rng: np.random.Generator
) -> tuple[Array, Array]:
    """The truth rotated by spec.offset_deg about a random axis and moved by spec.offset_frac of
    the range in a random direction."""
    R0 = R @ axis_angle_to_matrix(random_unit(rng), np.radians(spec.offset_deg))
    return R0, t + random_unit(rng) * spec.offset_frac * float(np.linalg.norm(t))
