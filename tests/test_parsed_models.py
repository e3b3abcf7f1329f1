"""Parsed models kept on disk (worker/engine/parsed_models.py): a second process loads the same
model without trimesh and gets the same arrays; files that read other files are not kept; a bad
or outdated entry is parsed again; the face limit, eviction and an unwritable directory."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import REPO
from PIL import Image

from worker.engine import meshes, parsed_models
from worker.engine.exceptions import ModelTooLargeError
from worker.engine.meshes import LoadedModel, file_sha256, load_model

TEXTURE = np.random.default_rng(4).integers(0, 256, (24, 32, 3), dtype=np.uint8)


def _textured_glb(path: Path, factor: float = 1.0) -> Path:
    """Two boxes sharing one texture (one scaled by a colour factor) and a vertex-coloured one."""
    scene = trimesh.Scene()
    image = Image.fromarray(TEXTURE)
    for i, f in enumerate((1.0, factor)):
        box = trimesh.creation.box(extents=(1.0 + i, 1.0, 0.5))
        material = trimesh.visual.material.PBRMaterial(
            baseColorTexture=image, baseColorFactor=[f, 1.0, 1.0, 1.0]
        )
        uv = np.random.default_rng(i).uniform(size=(len(box.vertices), 2))
        box.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
        T = np.eye(4)
        T[:3, 3] = [3.0 * i, 0.0, 0.0]
        scene.add_geometry(box, geom_name=f"box{i}", transform=T)
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.visual.vertex_colors = [200, 30, 40, 255]
    scene.add_geometry(ball, geom_name="ball")
    path.write_bytes(scene.export(file_type="glb"))
    return path


def _assert_same(a: LoadedModel, b: LoadedModel) -> None:
    assert (a.n_faces, a.n_vertices, a.textured, a.sha256) == (
        b.n_faces,
        b.n_vertices,
        b.textured,
        b.sha256,
    )
    np.testing.assert_array_equal(a.bounds, b.bounds)
    assert len(a.parts) == len(b.parts)
    for p, q in zip(a.parts, b.parts, strict=True):
        for name in ("vertices", "faces", "normals", "uvs", "texture", "vertex_colors"):
            x, y = getattr(p, name), getattr(q, name)
            assert (x is None) == (y is None), name
            if x is not None:
                assert x.dtype == y.dtype, name
                np.testing.assert_array_equal(x, y, err_msg=name)
        assert p.albedo == q.albedo


@pytest.fixture(autouse=True)
def _fresh_process_cache() -> None:
    meshes._cache.clear()


def test_a_kept_parse_loads_the_same_model(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _textured_glb(tmp_path / "boxes.glb", factor=0.5)
    parsed = tmp_path / "parsed"
    first = load_model(path, parsed_dir=parsed)
    assert [p.name for p in parsed.iterdir()] == [f"{file_sha256(path)}.npz"]
    plain, scaled = sorted(  # box0 (factor 1) lies left of box1 (factor 0.5)
        (p for p in first.parts if p.texture is not None),
        key=lambda p: float(p.vertices[:, 0].max()),
    )
    assert plain.texture is not None and scaled.texture is not None
    assert scaled.albedo[0] == pytest.approx(0.5, abs=0.01)  # as the file stores it (8 bit)
    np.testing.assert_allclose(scaled.texture[..., 0], scaled.albedo[0] * plain.texture[..., 0])
    np.testing.assert_array_equal(scaled.texture[..., 1:], plain.texture[..., 1:])
    assert sum(p.vertex_colors is not None for p in first.parts) == 1

    meshes._cache.clear()

    def no_parse(*args: object) -> None:
        raise AssertionError("parsed again")

    monkeypatch.setattr(meshes, "_parse", no_parse)
    _assert_same(load_model(path, parsed_dir=parsed), first)


def test_a_second_process_loads_a_kept_model_without_trimesh(tmp_path: Path) -> None:
    path = _textured_glb(tmp_path / "boxes.glb")
    parsed = tmp_path / "parsed"
    first = load_model(path, parsed_dir=parsed)
    code = (
        "import sys; from pathlib import Path; import numpy as np\n"
        "from worker.engine.meshes import load_model\n"
        f"m = load_model({str(path)!r}, parsed_dir=Path({str(parsed)!r}))\n"
        "print('trimesh' in sys.modules, m.n_faces, float(sum(p.vertices.sum() for p in m.parts)),"
        " float(sum(p.texture.sum() for p in m.parts if p.texture is not None)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out[0] == "False"  # trimesh (and scipy, networkx) not imported
    assert int(out[1]) == first.n_faces
    assert float(out[2]) == float(sum(p.vertices.sum() for p in first.parts))
    textures = sum(p.texture.sum() for p in first.parts if p.texture is not None)
    assert float(out[3]) == float(textures)


def test_files_that_read_other_files_are_not_kept(tmp_path: Path) -> None:
    box = trimesh.creation.box()
    (tmp_path / "box.obj").write_text(box.export(file_type="obj"))
    parsed = tmp_path / "parsed"
    load_model(tmp_path / "box.obj", parsed_dir=parsed)
    assert not parsed.exists()


@pytest.mark.parametrize("damage", ["truncated", "other_format"])
def test_a_bad_or_outdated_entry_is_parsed_again(
    tmp_path: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    path = _textured_glb(tmp_path / "boxes.glb")
    parsed = tmp_path / "parsed"
    first = load_model(path, parsed_dir=parsed)
    entry = parsed / f"{file_sha256(path)}.npz"
    if damage == "truncated":
        entry.write_bytes(entry.read_bytes()[:1000])
    else:
        with np.load(entry) as z:
            arrays = dict(z)
        arrays["format"] = np.asarray(parsed_models.FORMAT + 1)
        np.savez(entry, **arrays)
    meshes._cache.clear()
    with caplog.at_level(logging.WARNING, logger="worker.engine.parsed_models"):
        _assert_same(load_model(path, parsed_dir=parsed), first)
    assert ("unreadable" in caplog.text) == (damage == "truncated")
    with np.load(entry) as z:  # written anew
        assert int(z["format"]) == parsed_models.FORMAT


def test_the_face_limit_applies_to_a_kept_parse(tmp_path: Path) -> None:
    path = _textured_glb(tmp_path / "boxes.glb")
    parsed = tmp_path / "parsed"
    n = load_model(path, parsed_dir=parsed).n_faces
    meshes._cache.clear()
    with pytest.raises(ModelTooLargeError, match=f"more than {n - 1} faces"):
        load_model(path, max_faces=n - 1, parsed_dir=parsed)


def test_the_least_recently_used_entries_are_evicted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(parsed_models, "MAX_ENTRIES", 2)
    parsed = tmp_path / "parsed"
    paths = []
    for i in range(3):
        paths.append(tmp_path / f"box{i}.stl")
        paths[-1].write_bytes(trimesh.creation.box(extents=(1 + i, 1, 1)).export(file_type="stl"))
    load_model(paths[0], parsed_dir=parsed)
    load_model(paths[1], parsed_dir=parsed)
    old = parsed / f"{file_sha256(paths[1])}.npz"
    os.utime(old, (1.0, 1.0))  # box1 is the least recently used
    load_model(paths[2], parsed_dir=parsed)
    kept = {p.name for p in parsed.iterdir()}
    assert kept == {f"{file_sha256(paths[i])}.npz" for i in (0, 2)}


def test_an_unwritable_directory_only_costs_time(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _textured_glb(tmp_path / "boxes.glb")
    blocked = tmp_path / "a-file"
    blocked.write_text("not a directory")
    with caplog.at_level(logging.WARNING, logger="worker.engine.parsed_models"):
        model = load_model(path, parsed_dir=blocked / "parsed")
    assert model.n_faces > 0
    assert "could not keep the parsed model" in caplog.text


def test_the_setting_names_the_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from schemas.settings import Settings

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert Settings(parsed_model_cache="auto").parsed_model_dir() == (
        tmp_path / "proxpose" / "parsed-models"
    )
    assert Settings(parsed_model_cache="off").parsed_model_dir() is None
    assert Settings(parsed_model_cache=str(tmp_path / "x")).parsed_model_dir() == tmp_path / "x"
