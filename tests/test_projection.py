"""The renderer images a point where K [R | t] says (worker/engine/renderer.py and camera.py).

Small spheres at known model points, lit by ambient light only, render as uniform discs; each
disc's intensity centroid is compared with the exact centre of the sphere's image (an ellipse
whose centre lies up to ~0.04 px from the projected sphere centre here: perspective bias).
Cameras: an off-centre principal point, non-square pixels (fx ≠ fy, rendered through a warp)
and a skew.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel, MeshPart
from worker.engine.posemath import axis_angle_to_matrix
from worker.engine.renderer import LightingSpec, Renderer

REPO = Path(__file__).resolve().parents[1]
#: Centroid agreement required, px.
TOLERANCE_PX = 0.1
#: Sphere radius over its distance: a disc of ~3 px radius at f ≈ 150.
R_OVER_D = 0.02
SPP = 64
AMBIENT_ONLY = LightingSpec((0.0, 0.0, -1.0), sun_irradiance=1e-4, ambient=1.0)
#: The pose of the "model" (the set of spheres): anything but the identity.
R_MODEL = axis_angle_to_matrix(np.array([0.2, -0.7, 0.4]), 0.6)
T_MODEL = np.array([0.3, -0.2, 9.0])

CAMERAS = {
    "offcentre": PinholeCamera(160, 120, 150.0, 150.0, 90.3, 52.6),
    "nonsquare": PinholeCamera(160, 120, 140.0, 165.0, 81.2, 57.9),
    "skewed": PinholeCamera(160, 120, 150.0, 150.0, 77.4, 61.7, skew=9.0),
}


def sphere_centres_cam(camera: PinholeCamera) -> np.ndarray:
    """Camera-frame centres (N, 3): a grid over the image (to its corners), depths 7–11."""
    us = np.linspace(0.1, 0.9, 4) * camera.width
    vs = np.linspace(0.13, 0.87, 3) * camera.height
    uv = np.array([(u, v) for v in vs for u in us])
    depth = 7.0 + 4.0 * np.random.default_rng(0).uniform(size=len(uv))
    rays = np.linalg.solve(camera.K, np.column_stack([uv, np.ones(len(uv))]).T).T
    return rays * depth[:, None]


def spheres_model(centres_cam: np.ndarray) -> LoadedModel:
    """Icospheres of radius R_OVER_D·d at the model points a = Rᵀ(b − t)."""
    import trimesh

    parts = []
    for b in centres_cam:
        a = R_MODEL.T @ (b - T_MODEL)
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=R_OVER_D * np.linalg.norm(b))
        V = (mesh.vertices + a).astype(np.float32)
        N = mesh.vertex_normals.astype(np.float32)
        parts.append(MeshPart(V, mesh.faces.astype(np.uint32), N, None, None, None))
    verts = np.concatenate([p.vertices for p in parts])
    return LoadedModel(
        name="spheres",
        sha256="spheres",
        parts=parts,
        bounds=np.stack([verts.min(0), verts.max(0)]).astype(np.float64),
        n_vertices=len(verts),
        n_faces=sum(len(p.faces) for p in parts),
        textured=False,
    )


def ellipse_centre(camera: PinholeCamera, centre: np.ndarray, radius: float) -> np.ndarray:
    """Exact centre (u, v) of the image of a sphere: the centre of the conic of its tangent cone.

    Rays x (normalised coordinates, x = K⁻¹ u) touch the sphere where (xᵀc)² = |x|²(|c|² − r²);
    the cone's section by the image plane is an ellipse, and K maps its centre affinely.
    """
    Q = np.outer(centre, centre) - (centre @ centre - radius**2) * np.eye(3)
    K_inv = np.linalg.inv(camera.K)
    A = K_inv.T @ Q @ K_inv
    return np.linalg.solve(A[:2, :2], -A[:2, 2])


def disc_centroids(image: np.ndarray, predicted: np.ndarray, window_px: float) -> np.ndarray:
    """Intensity centroids (N, 2) of the discs near ``predicted``, OpenCV pixel coordinates."""
    grey = image.mean(axis=2) if image.ndim == 3 else image
    h, w = grey.shape
    vv, uu = np.mgrid[0:h, 0:w]
    out = []
    for u0, v0 in predicted:
        inside = (uu - u0) ** 2 + (vv - v0) ** 2 <= window_px**2
        m = grey * inside
        out.append([(m * uu).sum() / m.sum(), (m * vv).sum() / m.sum()])
    return np.array(out)


def render_spheres(camera: PinholeCamera, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(render at ``scale``, exact disc centres in that render's pixels)."""
    centres = sphere_centres_cam(camera)
    scales = (1.0,) if scale == 1.0 else (1.0, scale)
    renderer = Renderer(spheres_model(centres), camera, AMBIENT_ONLY, scales=scales, spp=SPP)
    image = renderer.render(R_MODEL, T_MODEL, scale=scale)
    cam = renderer.camera_at(scale)
    expected = np.array([ellipse_centre(cam, c, R_OVER_D * np.linalg.norm(c)) for c in centres])
    return image, expected


def _window(camera: PinholeCamera) -> float:
    return 3.0 * R_OVER_D * max(camera.fx, camera.fy) + 2.0


@pytest.mark.parametrize("name", list(CAMERAS))
def test_disc_centroids_match_the_pinhole_projection(variant: str, name: str) -> None:
    camera = CAMERAS[name]
    image, expected = render_spheres(camera)
    assert image.shape == (camera.height, camera.width, 3)
    # The discs are what ambient light on a diffuse white-ish sphere gives: flat, no shading.
    centroids = disc_centroids(image, expected, _window(camera))
    err = np.linalg.norm(centroids - expected, axis=1)
    assert err.max() < TOLERANCE_PX, f"{variant}: centroid errors {np.round(err, 3)} px"
    # The projected sphere centre differs from the ellipse centre by the perspective bias,
    # which grows ∝ (r/d)² with the distance from the principal point: small but not zero.
    projected = camera.project(sphere_centres_cam(camera))
    assert 0.005 < np.abs(projected - expected).max() < 0.06


def test_disc_centroids_match_the_projection_of_the_scaled_camera(variant: str) -> None:
    """A perturbation-scale render (0.5) images points where camera.scaled(0.5) projects."""
    camera = CAMERAS["nonsquare"]
    image, expected = render_spheres(camera, scale=0.5)
    scaled = camera.scaled(0.5)
    assert image.shape == (scaled.height, scaled.width, 3) == (60, 80, 3)
    centroids = disc_centroids(image, expected, _window(scaled))
    err = np.linalg.norm(centroids - expected, axis=1)
    assert err.max() < TOLERANCE_PX, f"{variant}: centroid errors {np.round(err, 3)} px"
    # Sanity of the scaled intrinsics themselves: half the full-size projection, pixel centres
    # mapping as (u + ½)·s − ½.
    full = camera.project(sphere_centres_cam(camera))
    np.testing.assert_allclose(scaled.project(sphere_centres_cam(camera)), (full + 0.5) / 2 - 0.5)


def test_discs_are_uniform(variant: str) -> None:
    """Ambient light only: every disc has the same flat radiance (albedo 0.5 × ambient 1)."""
    camera = CAMERAS["offcentre"]
    image, expected = render_spheres(camera)
    grey = image.mean(axis=2)
    for u, v in np.round(expected).astype(int):
        assert grey[v, u] == pytest.approx(0.5, abs=0.02)
    assert grey[grey < 1e-6].size > 0.8 * grey.size  # black background


SCALAR_SCRIPT = """
import json, sys
import numpy as np
sys.path.insert(0, {tests!r})
from worker.engine.variant import choose_variant
variant = choose_variant("scalar_rgb")
import test_projection as tp
image, expected = tp.render_spheres(tp.CAMERAS["offcentre"])
np.save({out!r}, image)
print(json.dumps({{"variant": variant}}))
"""


@pytest.mark.slow
def test_scalar_fallback_renders_the_same_image(variant: str, tmp_path: Path) -> None:
    """The scalar_rgb fallback (a variant is fixed per process, hence the subprocess) images
    the spheres where the session's variant does, within the centroid tolerance."""
    out = tmp_path / "scalar.npy"
    code = SCALAR_SCRIPT.format(tests=str(REPO / "tests"), out=str(out))
    env = {**os.environ, "PROXPOSE_VARIANT": "scalar_rgb"}
    proc = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["variant"] == "scalar_rgb"
    scalar = np.load(out)
    camera = CAMERAS["offcentre"]
    image, expected = render_spheres(camera)
    assert scalar.shape == image.shape
    c_scalar = disc_centroids(scalar, expected, _window(camera))
    c_session = disc_centroids(image, expected, _window(camera))
    assert np.abs(c_scalar - expected).max() < TOLERANCE_PX
    assert np.abs(c_scalar - c_session).max() < TOLERANCE_PX
    # Same scene, same spp: the images differ by sampling noise only, on edge pixels.
    assert np.abs(scalar - image).mean() < 0.01
    assert abs(float(scalar.sum() - image.sum())) < 0.01 * float(image.sum())
