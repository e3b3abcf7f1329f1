"""Scenes that fill the frame: the demo terrain (camera inside the model's bounding sphere), a
target half out of frame, meshes wound the wrong way, and an unlit initial pose."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from schemas.camera import Camera
from schemas.estimate import EstimateRequest
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from worker.align.artifacts import make_artifacts
from worker.align.estimator import estimate
from worker.bench.synth import CaseSpec, _initial_guess, pose_json
from worker.bench.terrain import look_down_pose, make_terrain_case, sun_above_horizon
from worker.demo.terrain import heightfield, heightfield_mesh, write_demo_terrain
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import UnlitRenderError
from worker.engine.meshes import LoadedModel, load_model
from worker.engine.renderer import LightingSpec, Renderer

SIDE_PX = 160
#: A small DEM keeps the tests fast (129 posts: 15.6 m between them).
POSTS = 129


def _camera(side: int = SIDE_PX) -> Camera:
    f = 0.5 * side / np.tan(np.radians(20.0))
    return Camera(width=side, height=side, fx=f, fy=f, cx=(side - 1) / 2, cy=(side - 1) / 2)


@pytest.fixture(scope="module")
def terrain(tmp_path_factory: pytest.TempPathFactory, variant: str) -> LoadedModel:
    path = tmp_path_factory.mktemp("terrain") / "terrain.glb"
    return load_model(write_demo_terrain(path, seed=3, posts=POSTS))


def _flipped(tmp_path: Path, inconsistent: bool) -> LoadedModel:
    """The terrain with every face (or every other face) wound the other way and its normals
    pointing into the ground."""
    mesh = heightfield_mesh(heightfield(seed=3, posts=POSTS))
    F = np.asarray(mesh.faces).copy()
    sel = slice(None, None, 2) if inconsistent else slice(None)
    F[sel] = F[sel][:, ::-1]
    flipped = trimesh.Trimesh(mesh.vertices, F, process=False)
    flipped.visual = mesh.visual.copy()
    flipped.vertex_normals = -np.asarray(mesh.vertex_normals)
    path = tmp_path / ("mixed.glb" if inconsistent else "flipped.glb")
    path.write_bytes(trimesh.exchange.gltf.export_glb(trimesh.Scene(flipped)))
    return load_model(path)


def _view(model: LoadedModel, R: np.ndarray, t: np.ndarray, sun: np.ndarray) -> np.ndarray:
    light = LightingSpec(tuple(sun), 3.0, 0.02)  # type: ignore[arg-type]
    cam = PinholeCamera.from_schema(_camera())
    return Renderer(model, cam, light, spp=4).render(R, t)


def _oblique() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    R, t = look_down_pose(np.zeros(3), 600.0, 25.0, 0.7)
    return R, t, sun_above_horizon(R, 35.0, 2.0)


def test_camera_inside_bounding_sphere_renders_the_frame_full(terrain: LoadedModel) -> None:
    R, t, sun = _oblique()
    assert np.linalg.norm(R @ terrain.centre + t) < 0.6 * terrain.radius  # inside the sphere
    img = _view(terrain, R, t, sun)
    lit = img.mean(axis=2) > 0.02
    assert lit.mean() > 0.8  # ground everywhere, a little of it in shadow
    cam = PinholeCamera.from_schema(_camera())
    renderer = Renderer(terrain, cam, LightingSpec(tuple(sun), 3.0, 0.02), spp=1)  # type: ignore[arg-type]
    assert renderer.coverage(R, t, grid=16) == 1.0


@pytest.mark.parametrize("inconsistent", [False, True])
def test_flipped_winding_renders_lit(
    terrain: LoadedModel, tmp_path: Path, inconsistent: bool
) -> None:
    R, t, sun = _oblique()
    good = _view(terrain, R, t, sun).mean(axis=2)
    flipped = _view(_flipped(tmp_path, inconsistent), R, t, sun).mean(axis=2)
    assert flipped.mean() > 0.8 * good.mean()
    assert np.corrcoef(good.ravel(), flipped.ravel())[0, 1] > 0.9


def _terrain_case(terrain: LoadedModel, seed: int) -> tuple[np.ndarray, EstimateRequest]:
    case = make_terrain_case(terrain, _camera(), CaseSpec(3.0, 0.02), seed=seed)
    return case.reference.astype(np.float32) / 255.0, case.request


def test_full_frame_terrain_estimate_converges(terrain: LoadedModel) -> None:
    ref, request = _terrain_case(terrain, seed=7)
    est = estimate(terrain, ref, request)
    result = est.result
    assert result.errors is not None and result.initial_errors is not None
    assert result.initial_errors.rotation_deg > 2.0
    assert result.converged, result.reason
    assert result.errors.rotation_deg < 0.3
    assert result.errors.translation_pct_of_range < 0.3
    assert result.alignment_score > 0.9
    # the overlay stretches the ground, not a sky there is none of: half the frame is not black
    png = make_artifacts(result, est.reference, est.views)["overlay_final"]
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64) / 255.0
    assert (rgb[..., 0] > 0.1).mean() > 0.8 and (rgb[..., 2] > 0.1).mean() > 0.8


def test_target_half_out_of_frame(terrain: LoadedModel) -> None:
    """A camera aimed at the patch's edge: half the frame is empty sky, the target is cut."""
    edge = np.array([1000.0, 0.0, 0.0])  # the middle of the +x edge of the patch
    R, t = look_down_pose(edge, 600.0, 20.0, 0.0)
    sun = sun_above_horizon(R, 35.0, 2.5)
    ref = np.clip(_view(terrain, R, t, sun), 0, 1) ** (1 / 2.2)
    lit = ref.mean(axis=2) > 0.05
    assert 0.25 < lit.mean() < 0.75  # about half the frame shows the ground
    R0, t0 = _initial_guess(R, t, CaseSpec(2.0, 0.02), np.random.default_rng(1))
    request = EstimateRequest(
        camera=_camera(),
        initial_pose=pose_json(R0, t0),
        lighting=Lighting(sun_direction=list(map(float, sun))),
        options=EstimateOptions(),
        ground_truth=pose_json(R, t),
    )
    result = estimate(terrain, ref.astype(np.float32), request).result
    assert result.errors is not None
    assert result.converged, result.reason
    assert result.errors.rotation_deg < 0.3
    assert result.errors.translation_pct_of_range < 0.3


def test_unlit_initial_pose_is_a_specific_error(terrain: LoadedModel) -> None:
    R, t, _ = _oblique()
    below = -sun_above_horizon(R, 40.0, 1.0)  # the sun under the ground
    ref = np.full((SIDE_PX, SIDE_PX, 3), 0.1, np.float32)
    request = EstimateRequest(
        camera=_camera(),
        initial_pose=pose_json(R, t),
        lighting=Lighting(sun_direction=list(map(float, below))),
    )
    with pytest.raises(UnlitRenderError, match="sun lights none"):
        estimate(terrain, ref, request)


def test_suggested_request_looks_down_at_a_terrain(terrain: LoadedModel) -> None:
    """GET /models/<id>/request.json's framing for a flat model: from above, lit, the frame
    full of ground (the spacecraft framing would put the camera kilometres away, edge-on)."""
    from schemas.models import ModelPublic
    from service.pages import suggested_request
    from worker.engine.posemath import pose_from_schema

    meta = ModelPublic(
        id="demo-terrain", name="t", vertices=terrain.n_vertices, faces=terrain.n_faces,
        bounds=terrain.bounds.tolist(), textured=False, format="glb", size_bytes=1,
        sha256="0" * 64, created_at="2026-01-01T00:00:00Z",
    )  # fmt: skip
    request = EstimateRequest.model_validate(
        {k: v for k, v in suggested_request(meta, SIDE_PX, SIDE_PX).items() if k != "model_id"}
    )
    R, t = pose_from_schema(request.initial_pose)
    C = -R.T @ t
    assert 400.0 < C[1] < 800.0  # above the ground (+y up), at 0.3 of the 2 km side
    tilt = np.degrees(np.arccos(R[2] @ np.array([0.0, -1.0, 0.0])))  # optical axis vs nadir
    assert 20.0 < tilt < 30.0
    sun = np.asarray(request.lighting.sun_direction)
    cam = PinholeCamera.from_schema(request.camera)
    renderer = Renderer(terrain, cam, LightingSpec(tuple(sun), 3.0, 0.02), spp=2)  # type: ignore[arg-type]
    assert renderer.coverage(R, t, grid=16) == 1.0
    img = renderer.render(R, t).mean(axis=2)
    assert (img > 0.05).mean() > 0.7
