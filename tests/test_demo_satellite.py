"""Tests of the procedural demo satellite (worker/demo/satellite.py)."""

from __future__ import annotations

import hashlib
import os
import pathlib
import subprocess
import sys

import cv2
import numpy as np
import pytest
import trimesh

from schemas.names import DEMO_MODEL_ID
from worker.demo.satellite import (
    DEMO_MODEL_NAME,
    build_demo_satellite,
    demo_satellite_path,
    write_demo_satellite,
)

REPO = pathlib.Path(__file__).resolve().parents[1]


def _sha256(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def glb(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    return write_demo_satellite(tmp_path_factory.mktemp("demosat") / "a" / "demo.glb")


@pytest.fixture(scope="module")
def scene(glb: pathlib.Path) -> trimesh.Scene:
    return trimesh.load(glb, force="scene")


def test_constants() -> None:
    assert DEMO_MODEL_ID == "demo-sat"
    assert DEMO_MODEL_NAME == "Demo satellite (procedural)"


def test_glb_is_byte_identical_across_writes(glb: pathlib.Path, tmp_path: pathlib.Path) -> None:
    again = write_demo_satellite(tmp_path / "b.glb")
    assert _sha256(again) == _sha256(glb)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.glb"]  # no temp file left behind


def test_glb_is_byte_identical_across_processes(glb: pathlib.Path) -> None:
    # a fresh interpreter with another hash seed catches set/dict-order dependence in the export
    code = (
        "import hashlib, trimesh; from worker.demo.satellite import build_demo_satellite; "
        "data = trimesh.exchange.gltf.export_glb(build_demo_satellite(0), include_normals=True); "
        "print(hashlib.sha256(data).hexdigest())"
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    assert out.stdout.strip() == _sha256(glb)


def test_seed_changes_textures_not_geometry(scene: trimesh.Scene) -> None:
    other = build_demo_satellite(seed=1)
    assert sorted(other.geometry) == sorted(scene.geometry)
    np.testing.assert_allclose(other.bounds, scene.bounds, atol=1e-6)
    ta = np.asarray(scene.geometry["bus"].visual.material.baseColorTexture.convert("RGB"))
    tb = np.asarray(other.geometry["bus"].visual.material.baseColorTexture)
    assert ta.shape == tb.shape and not np.array_equal(ta, tb)


def test_scene_graph_structure(scene: trimesh.Scene) -> None:
    nodes = scene.graph.nodes_geometry
    assert len(scene.geometry) >= 15
    assert len(nodes) > len(scene.geometry)  # some meshes are instanced by several nodes
    non_identity = [n for n in nodes if not np.allclose(scene.graph[n][0], np.eye(4))]
    assert len(non_identity) >= 0.9 * len(nodes)
    parents = scene.graph.transforms.parents
    depth = {n: 0 for n in nodes}
    for n in nodes:
        p = n
        while p in parents:
            p, depth[n] = parents[p], depth[n] + 1
    assert max(depth.values()) >= 3  # nested transforms (bus -> boom -> dish -> feed)
    faces = sum(len(scene.geometry[scene.graph[n][1]].faces) for n in nodes)
    assert 5_000 <= faces <= 30_000


def test_every_mesh_is_textured_and_oriented(scene: trimesh.Scene) -> None:
    for name, mesh in scene.geometry.items():
        assert isinstance(mesh.visual, trimesh.visual.TextureVisuals), name
        assert mesh.visual.uv is not None and mesh.visual.uv.shape == (len(mesh.vertices), 2)
        assert np.isfinite(mesh.visual.uv).all()
        material = mesh.visual.material
        assert isinstance(material, trimesh.visual.material.PBRMaterial), name
        assert material.baseColorTexture is not None, name
        assert max(material.baseColorTexture.size) <= 1024
        assert material.metallicFactor is not None and material.metallicFactor <= 0.5
        assert mesh.volume > 0, name  # closed, outward winding
        vn = mesh.vertex_normals[mesh.faces].mean(axis=1)
        assert (np.einsum("ij,ij->i", vn, mesh.face_normals) > 0.9).all(), name


def test_bus_is_flat_shaded_and_centred(scene: trimesh.Scene) -> None:
    bus = scene.geometry["bus"]
    assert len(bus.vertices) == 24  # unshared vertices per face
    np.testing.assert_allclose(bus.vertex_normals[bus.faces[:, 0]], bus.face_normals, atol=1e-6)
    T, _ = scene.graph["bus"]
    np.testing.assert_allclose(
        trimesh.transform_points(bus.bounds, T), [[-1, -1, -1.5], [1, 1, 1.5]], atol=1e-6
    )


def test_bounding_box(scene: trimesh.Scene) -> None:
    lo, hi = scene.bounds
    assert np.abs(scene.bounds).max() < 12.0
    ext = hi - lo
    assert 2.0 < ext[0] < 5.0  # bus plus antenna along X
    assert 14.0 < ext[1] < 18.0  # solar array wings along Y
    assert 3.0 < ext[2] < 5.0  # bus long axis plus launch adapter, trackers
    assert abs(lo[1] + hi[1]) < 0.5  # wings are symmetric about the bus


def test_textures_are_rich_in_features(scene: trimesh.Scene) -> None:
    sift = cv2.SIFT_create()
    counts = {}
    for name, mesh in scene.geometry.items():
        rgb = np.asarray(mesh.visual.material.baseColorTexture.convert("RGB"))
        counts[name] = len(sift.detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None))
        assert rgb.std() > 20, name
        assert counts[name] >= max(12, rgb.shape[0] * rgb.shape[1] // 4000), (name, counts[name])
    assert counts["bus"] >= 3000
    assert min(counts[f"panel_{s}_{k}"] for s in ("py", "my") for k in range(3)) >= 3000
    assert counts["hga_dish"] >= 150


def test_solar_panels_are_not_periodic(scene: trimesh.Scene) -> None:
    # shift the cell field by one cell pitch: a periodic texture would match itself closely
    rgb = np.asarray(scene.geometry["panel_py_0"].visual.material.baseColorTexture).astype(float)
    cells = rgb[14:800, 14:1010]
    pitch_x, pitch_y = round((1024 - 28) / 16), round((820 - 28) / 20)
    for dy, dx in ((0, pitch_x), (pitch_y, 0)):
        shifted = cells[dy:, dx:]
        diff = np.abs(shifted - cells[: cells.shape[0] - dy, : cells.shape[1] - dx]).mean()
        assert diff > 20.0


def test_demo_satellite_path(tmp_path: pathlib.Path, glb: pathlib.Path) -> None:
    path = demo_satellite_path(tmp_path)
    assert path == tmp_path / "models" / "demo-sat-v1.glb"
    assert _sha256(path) == _sha256(glb)
    stamp = path.stat().st_mtime_ns
    assert demo_satellite_path(tmp_path) == path
    assert path.stat().st_mtime_ns == stamp  # not rewritten when present
