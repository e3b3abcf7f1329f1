"""Model loading (worker/engine/meshes.py): every format, node transforms, textures, vertex colours,
the cache, and the errors. Small models are written with trimesh (or by hand) into tmp_path."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import shared_model
from PIL import Image

from worker.engine.exceptions import ModelLoadError, ModelTooLargeError
from worker.engine.images import srgb_decode
from worker.engine.meshes import LoadedModel, load_model

#: A 2×2 texture (8 px per cell): red, green / blue, yellow — every orientation error shows.
CELLS = np.array([[(230, 20, 20), (20, 200, 40)], [(30, 40, 220), (240, 220, 30)]], np.uint8)
TEXTURE = np.kron(CELLS, np.ones((8, 8, 1), np.uint8))  # (16, 16, 3)


def _linear(rgb: tuple[int, ...] | np.ndarray) -> np.ndarray:
    return srgb_decode(np.asarray(rgb, np.float32) / 255.0)


def _node_transform() -> np.ndarray:
    """90° about z, then a translation far from the origin (100, 5, −3)."""
    T = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1])
    T[:3, 3] = [100.0, 5.0, -3.0]
    return T


def _textured_box_scene() -> tuple[trimesh.Scene, np.ndarray]:
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    uv = np.random.default_rng(0).uniform(size=(len(box.vertices), 2))
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(TEXTURE), baseColorFactor=[0.5, 1.0, 1.0, 1.0]
    )
    box.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="box_node", geom_name="box", transform=_node_transform())
    return scene, uv


def _write_gltf(scene: trimesh.Scene, directory: Path) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    for name, data in scene.export(file_type="gltf").items():
        (directory / name).write_bytes(data)
    return directory / "model.gltf"


@pytest.fixture
def gltf_files(tmp_path: Path) -> dict[str, Path]:
    scene, _ = _textured_box_scene()
    glb = tmp_path / "box.glb"
    glb.write_bytes(scene.export(file_type="glb"))
    return {"glb": glb, "gltf": _write_gltf(scene, tmp_path / "gltf")}


# -- formats ------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["glb", "gltf"])
def test_gltf_node_transform_texture_and_file_coordinates(
    gltf_files: dict[str, Path], fmt: str
) -> None:
    scene, uv = _textured_box_scene()
    model = load_model(gltf_files[fmt])
    assert (model.n_vertices, model.n_faces) == (8, 12)
    # The node's 90° turn swaps the x and y extents; its translation is kept: no recentring.
    np.testing.assert_allclose(model.bounds, [[99.5, 4.0, -3.25], [100.5, 6.0, -2.75]], atol=1e-6)
    np.testing.assert_allclose(model.centre, [100.0, 5.0, -3.0], atol=1e-6)
    assert model.textured
    (part,) = model.parts
    box = scene.geometry["box"]
    expected_vertices = trimesh.transform_points(box.vertices, _node_transform())
    order = [int(np.argmin(np.linalg.norm(expected_vertices - v, axis=1))) for v in part.vertices]
    np.testing.assert_allclose(part.vertices, expected_vertices[order], atol=1e-5)
    # UVs: v flipped for Mitsuba's top-left bitmap origin.
    np.testing.assert_allclose(part.uvs[:, 0], uv[order, 0], atol=1e-6)
    np.testing.assert_allclose(part.uvs[:, 1], 1.0 - uv[order, 1], atol=1e-6)
    # Texture: linear base colour in image row order, times the (linear) base colour factor.
    assert part.texture.shape == (16, 16, 3) and part.texture.dtype == np.float32
    factor = np.array([0.5, 1.0, 1.0])
    np.testing.assert_allclose(part.texture[0, 0], _linear(CELLS[0, 0]) * factor, atol=0.01)
    np.testing.assert_allclose(part.texture[15, 15], _linear(CELLS[1, 1]) * factor, atol=0.01)
    assert part.vertex_colors is None


def test_mirroring_node_keeps_faces_outward(tmp_path: Path) -> None:
    """A node with det < 0 mirrors the mesh; the winding must flip so normals stay outward."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="m", geom_name="box", transform=np.diag([-1.0, 1, 1, 1]))
    path = tmp_path / "mirror.glb"
    path.write_bytes(scene.export(file_type="glb"))
    (part,) = load_model(path).parts
    mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
    assert mesh.volume > 0  # outward winding: positive signed volume


def _write_textured_obj(directory: Path) -> Path:
    """A 2×2 quad in the z = 0 plane facing −z, with the texture's top-left at (−1, −1)."""
    directory.mkdir(parents=True, exist_ok=True)
    Image.fromarray(TEXTURE).save(directory / "tex.png")
    (directory / "quad.mtl").write_text("newmtl skin\nKd 0.8 0.8 0.8\nmap_Kd tex.png\n")
    (directory / "quad.obj").write_text(
        "mtllib quad.mtl\n"
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\n"
        # OBJ texture v grows upwards: the image's top-left is (0, 1).
        "vt 0 1\nvt 1 1\nvt 1 0\nvt 0 0\n"
        "usemtl skin\n"
        "f 1/1 4/4 3/3\nf 1/1 3/3 2/2\n"
    )
    return directory / "quad.obj"


def test_obj_with_mtl_texture_and_uvs(tmp_path: Path) -> None:
    model = load_model(_write_textured_obj(tmp_path / "obj"))
    assert (model.n_vertices, model.n_faces) == (4, 2)
    assert model.textured
    (part,) = model.parts
    assert part.texture.shape == (16, 16, 3)
    np.testing.assert_allclose(part.texture[0, 0], _linear(CELLS[0, 0]) * 0.8, atol=0.01)
    # The vertex at (−1, −1) has OBJ vt (0, 1): Mitsuba uv (0, 0), the bitmap's top-left.
    corner = int(np.argmin(np.linalg.norm(part.vertices - [-1, -1, 0], axis=1)))
    np.testing.assert_allclose(part.uvs[corner], [0.0, 0.0], atol=1e-6)


def test_obj_texture_renders_the_right_way_up(tmp_path: Path, variant: str) -> None:
    """End to end: in the camera (x right, y down) the quad's (−1, −1) corner is top-left, so
    the texture's top-left cell must appear top-left in the render."""
    from worker.engine.camera import PinholeCamera
    from worker.engine.renderer import LightingSpec, Renderer

    model = load_model(_write_textured_obj(tmp_path / "obj"))
    camera = PinholeCamera(64, 64, 60.0, 60.0, 31.5, 31.5)
    light = LightingSpec((0.0, 0.0, -1.0), sun_irradiance=1e-4, ambient=1.0)
    image = Renderer(model, camera, light, spp=16).render(np.eye(3), np.array([0, 0, 2.5]))
    # The quad spans ±24 px around the centre; sample the middle of each cell.
    for (row, col), (v, u) in {
        (0, 0): (19, 19),
        (0, 1): (19, 44),
        (1, 0): (44, 19),
        (1, 1): (44, 44),
    }.items():
        np.testing.assert_allclose(
            image[v, u], _linear(CELLS[row, col]) * 0.8, atol=0.03, err_msg=f"cell {row, col}"
        )


def test_ply_with_vertex_colours(tmp_path: Path) -> None:
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=2.0)
    mesh.vertices += [10.0, 0.0, 0.0]
    rng = np.random.default_rng(1)
    colours = rng.integers(0, 256, size=(len(mesh.vertices), 3), dtype=np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=colours)
    path = tmp_path / "ball.ply"
    path.write_bytes(mesh.export(file_type="ply"))
    model = load_model(path)
    assert (model.n_vertices, model.n_faces) == (len(mesh.vertices), len(mesh.faces))
    assert not model.textured
    (part,) = model.parts
    assert part.texture is None and part.uvs is None
    order = [int(np.argmin(np.linalg.norm(mesh.vertices - v, axis=1))) for v in part.vertices]
    np.testing.assert_allclose(part.vertex_colors, _linear(colours[order]), atol=1e-5)
    np.testing.assert_allclose(model.centre, [10.0, 0.0, 0.0], atol=1e-6)


def test_stl(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation([-5.0, 1.0, 2.0])
    path = tmp_path / "box.stl"
    path.write_bytes(box.export(file_type="stl"))
    model = load_model(path)
    assert model.n_faces == 12
    assert model.n_vertices in (8, 36)  # merged or one triple per facet: both render the same
    np.testing.assert_allclose(model.bounds, box.bounds, atol=1e-6)
    assert not model.textured and model.parts[0].vertex_colors is None


def test_uppercase_extension_is_accepted(tmp_path: Path) -> None:
    path = tmp_path / "BOX.STL"
    path.write_bytes(trimesh.creation.box().export(file_type="stl"))
    assert load_model(path).n_faces == 12


# -- cache --------------------------------------------------------------------------------
def test_cache_is_keyed_by_content(tmp_path: Path, gltf_files: dict[str, Path]) -> None:
    first = load_model(gltf_files["glb"])
    assert load_model(gltf_files["glb"]) is first
    copy = tmp_path / "copy" / "same.glb"
    copy.parent.mkdir()
    shutil.copy(gltf_files["glb"], copy)
    assert load_model(copy) is first
    other = tmp_path / "other.glb"
    other.write_bytes(trimesh.Scene(trimesh.creation.box()).export(file_type="glb"))
    assert load_model(other) is not first


def test_face_limit_applies_to_cached_models_too(gltf_files: dict[str, Path]) -> None:
    assert load_model(gltf_files["glb"], max_faces=12).n_faces == 12
    with pytest.raises(ModelTooLargeError, match="11"):
        load_model(gltf_files["glb"], max_faces=11)


def test_too_many_faces(tmp_path: Path) -> None:
    path = tmp_path / "ball.stl"
    path.write_bytes(trimesh.creation.icosphere(subdivisions=2).export(file_type="stl"))
    with pytest.raises(ModelTooLargeError, match="more than 100 faces"):
        load_model(path, max_faces=100)


# -- errors -------------------------------------------------------------------------------
GARBAGE = np.random.default_rng(2).integers(0, 256, 3000, dtype=np.uint8).tobytes()


@pytest.mark.parametrize("ext", [".obj", ".ply", ".stl", ".glb", ".gltf"])
@pytest.mark.parametrize("content", [b"", GARBAGE], ids=["empty", "garbage"])
def test_unreadable_files_raise_model_load_error(tmp_path: Path, ext: str, content: bytes) -> None:
    # A valid glTF named model.gltf sits next to the bad file: trimesh's glTF reader falls back
    # to that name when the file given is not JSON, which must not load another model.
    scene, _ = _textured_box_scene()
    _write_gltf(scene, tmp_path)
    path = tmp_path / f"bad{ext}"
    path.write_bytes(content)
    with pytest.raises(ModelLoadError):
        load_model(path)


def test_unsupported_extension(tmp_path: Path) -> None:
    path = tmp_path / "model.fbx"
    path.write_bytes(trimesh.creation.box().export(file_type="stl"))
    with pytest.raises(ModelLoadError, match="unsupported model format '.fbx'"):
        load_model(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ModelLoadError, match="not found"):
        load_model(tmp_path / "nope.glb")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),  # points only
        ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "non-finite"),
        ("v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n", "degenerate"),
    ],
)
def test_models_without_usable_triangles(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ModelLoadError, match=message):
        load_model(path)


# -- real models --------------------------------------------------------------------------
def _pose_in_front(model: LoadedModel, distance_radii: float = 2.5) -> tuple:
    R = np.eye(3)
    return R, np.array([0.0, 0.0, distance_radii * model.radius]) - R @ model.centre


def test_demo_satellite_loads_and_renders(tmp_path: Path, variant: str) -> None:
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.camera import PinholeCamera
    from worker.engine.renderer import LightingSpec, Renderer

    model = load_model(demo_satellite_path(tmp_path))
    assert model.textured and 5_000 <= model.n_faces <= 30_000
    assert len(model.parts) >= 15
    camera = PinholeCamera(96, 96, 110.0, 110.0, 47.5, 47.5)
    light = LightingSpec((0.0, -0.6, -0.8), 3.0, 0.02)
    renderer = Renderer(model, camera, light, spp=4)
    R, t = _pose_in_front(model)
    image = renderer.render(R, t)
    assert image.shape == (96, 96, 3) and np.isfinite(image).all()
    lit = image.mean(axis=2) > 0.01
    assert 0.02 < lit.mean() < 0.9
    assert renderer.coverage(R, t) > 0.02


# Facts from ../shared/models/*/SOURCE.md: faces, vertices, bbox min/max, bounding radius,
# texture side (None: untextured).
SHARED_FACTS = {
    "iss": (172_200, 101_363, (-2.83, -4.17, -22.86), (3.29, 25.77, 22.68), 27.29, None),
    "aura": (6_135, 18_405, (-3.52, -0.23, -43.95), (5.47, 18.75, 6.88), 27.06, 1024),
    "phobos": (32_040, 16_449, (-12.32, -9.98, -14.24), (12.05, 10.54, 12.80), 14.59, 2048),
}


@pytest.mark.shared
@pytest.mark.parametrize("name", list(SHARED_FACTS))
def test_shared_model_facts(name: str) -> None:
    faces, vertices, lo, hi, radius, texture_side = SHARED_FACTS[name]
    model = load_model(shared_model(name))
    assert model.n_faces == faces
    assert model.n_vertices == vertices
    np.testing.assert_allclose(model.bounds, [lo, hi], atol=0.006)
    assert model.radius == pytest.approx(radius, abs=0.006)
    assert model.textured == (texture_side is not None)
    if texture_side is not None:
        for part in model.parts:
            assert part.texture.shape == (texture_side, texture_side, 3)
            assert part.uvs is not None and np.isfinite(part.uvs).all()
