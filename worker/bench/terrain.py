"""Terrain cases: a camera above a heightfield that fills the frame (terrain-relative navigation).

The truth puts the camera ``ALTITUDE_M`` above a point near the patch centre, tilted
``TILT_DEG`` from the nadir at a random azimuth; the sun stands ``SUN_ELEVATION_DEG`` above the
horizon at a random azimuth (by default: ``proxpose bench --altitude``, ``--tilt`` and
``--sun-elevation`` change the ranges, see TerrainView). The reference
is made with physics unlike the estimator's (the robustness suite's ray tracer: a
Lommel–Seeliger/Lambert regolith law, flat shading normals, a shadow ray, jittered
supersampling), the request's sun ``SUN_ERROR_DEG`` off, exposure 0.7, gamma 2.2 and noise.
The initial guess is the truth rotated and moved by the band's offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.camera import Camera
from schemas.estimate import EstimateRequest
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from worker.bench.raytrace import Physics
from worker.bench.references import (
    AMBIENT,
    IRRADIANCE,
    ReferenceClass,
    _tracer,
    camera_response,
)
from worker.bench.synth import Case, CaseSpec, _initial_guess, perturb_direction, pose_json
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel

Array = NDArray[np.float64]
#: Camera height above the aim point, m, its tilt from the nadir, deg, the sun's elevation, deg.
ALTITUDE_M = (550.0, 700.0)
TILT_DEG = (15.0, 30.0)
SUN_ELEVATION_DEG = (25.0, 45.0)
#: How far the aim point lies from the patch centre, m (each axis).
AIM_SPREAD_M = 100.0
SUN_ERROR_DEG = 3.0
#: The reference physics (see the module docstring).
TERRAIN_REFERENCE = ReferenceClass(
    "terrain",
    "ray traced regolith (Lommel–Seeliger), shadow rays, supersampling, sun 3° off, "
    "exposure 0.7, gamma 2.2, noise",
    False,
    physics=Physics(normals="smooth", brdf="lommel"),
    sun_error_deg=SUN_ERROR_DEG,
    exposure=0.7,
    gamma=2.2,
    noise_sigma=0.01,
)
UP = np.array([0.0, 1.0, 0.0])  # glTF: +y up
#: The bench's terrain models: the demo terrain's generator (tuned on) and a held-out one.
TERRAIN_MODELS = {
    "terrain": "fractal relief and power-law craters (the demo terrain; tuned on)",
    "terrain-ridged": "ridged multifractal relief and power-law craters (held out)",
}


@dataclass(frozen=True)
class TerrainView:
    """The ranges a terrain case's view is drawn from, uniformly (``proxpose bench
    --sun-elevation``, ``--altitude``, ``--tilt``): the sun's elevation above the horizon, deg,
    the camera's height above the aim point, m, and its tilt from the nadir, deg."""

    sun_elevation_deg: tuple[float, float] = SUN_ELEVATION_DEG
    altitude_m: tuple[float, float] = ALTITUDE_M
    tilt_deg: tuple[float, float] = TILT_DEG


def terrain_model_path(name: str, data_dir: Path) -> Path:
    """The GLB of bench terrain model ``name`` under ``data_dir/models`` (written if missing)."""
    from worker.demo.terrain import demo_terrain_path, write_demo_terrain

    if name == "terrain":
        return demo_terrain_path(data_dir)
    path = Path(data_dir) / "models" / "bench-terrain-ridged-v1.glb"
    return path if path.is_file() else write_demo_terrain(path, generator="ridged")


def look_down_pose(
    aim: Array, altitude_m: float, tilt_deg: float, azimuth_rad: float
) -> tuple[Array, Array]:
    """(R, t) of a camera ``altitude_m`` above ``aim`` (model frame, +y up) looking at it,
    tilted ``tilt_deg`` from the nadir towards azimuth ``azimuth_rad`` (OpenCV camera axes)."""
    toward = np.array([np.cos(azimuth_rad), 0.0, np.sin(azimuth_rad)])
    C = aim + altitude_m * UP - altitude_m * np.tan(np.radians(tilt_deg)) * toward
    z = (aim - C) / np.linalg.norm(aim - C)
    x = np.cross(z, UP)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.cross(z, toward)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ C


def sun_above_horizon(R: Array, elevation_deg: float, azimuth_rad: float) -> Array:
    """Unit vector towards a sun ``elevation_deg`` above the horizon, camera frame."""
    e = np.radians(elevation_deg)
    s = np.array([np.cos(e) * np.cos(azimuth_rad), np.sin(e), np.cos(e) * np.sin(azimuth_rad)])
    return R @ s


def make_terrain_case(
    model: LoadedModel,
    camera: Camera,
    spec: CaseSpec,
    seed: int,
    options: EstimateOptions | None = None,
    view: TerrainView | None = None,
) -> Case:
    """One seeded terrain case (reference, request with ground truth, true pose and sun), its
    view drawn from the ranges of ``view`` (None: the defaults, TerrainView())."""
    view = view or TerrainView()
    rng = np.random.default_rng(seed)
    cam = PinholeCamera.from_schema(camera)
    aim = np.array([rng.uniform(-1, 1) * AIM_SPREAD_M, 0.0, rng.uniform(-1, 1) * AIM_SPREAD_M])
    R, t = look_down_pose(
        aim, rng.uniform(*view.altitude_m), rng.uniform(*view.tilt_deg), rng.uniform(0, 2 * np.pi)
    )
    elevation = rng.uniform(*view.sun_elevation_deg)
    sun = sun_above_horizon(R, elevation, rng.uniform(0, 2 * np.pi))
    cls = TERRAIN_REFERENCE
    sun_true = perturb_direction(sun, cls.sun_error_deg, rng)
    R0, t0 = _initial_guess(R, t, spec, rng)
    render_rng = np.random.default_rng([seed, 1])
    tracer = _tracer(model, cam)
    linear = tracer.render(R, t, sun_true, IRRADIANCE, AMBIENT, cls.physics, render_rng)
    image = camera_response(linear, cls, render_rng)
    request = EstimateRequest(
        camera=camera,
        initial_pose=pose_json(R0, t0),
        lighting=Lighting(sun_direction=list(map(float, sun))),
        options=options or EstimateOptions(),
        ground_truth=pose_json(R, t),
    )
    return Case(image, request, R, t, sun_true)
