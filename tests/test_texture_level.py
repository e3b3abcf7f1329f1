"""The renderer cache's texture level: ranges that build the same scene share one renderer."""

from __future__ import annotations

import numpy as np

from worker.align.renderers import get_renderer, texture_level
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel, MeshPart
from worker.engine.renderer import LightingSpec
from worker.engine.scene_meshes import TEXELS_PER_PIXEL

CAMERA = PinholeCamera(64, 64, 80.0, 80.0, 31.5, 31.5)
LIGHT = LightingSpec((0.4, -0.5, -0.77), 3.0, 0.02)
R = np.eye(3)


def _quad(texture_px: int | None) -> LoadedModel:
    """A 2×2 unit square facing the camera, with a texture of texture_px² or none."""
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    uvs = texture = None
    if texture_px is not None:
        uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        texture = np.full((texture_px, texture_px, 3), 0.5, np.float32)
    return LoadedModel(
        name="quad",
        sha256=f"quad-{texture_px}",
        parts=[MeshPart(V, F, None, uvs, texture, None)],
        bounds=np.stack([V.min(0), V.max(0)]).astype(np.float64),
        n_vertices=4,
        n_faces=2,
        textured=texture is not None,
    )


def test_untextured_model_has_one_level_at_every_range() -> None:
    model = _quad(None)
    levels = {texture_level(model, CAMERA, R, np.array([0.0, 0.0, z])) for z in (2, 8, 40, 300)}
    assert levels == {0}


def test_textured_levels_stop_where_no_texture_is_reduced() -> None:
    model = _quad(256)  # 128 texels per unit
    cap = int(np.ceil(2 * np.log2(128 / TEXELS_PER_PIXEL)))
    near = [texture_level(model, CAMERA, R, np.array([0.0, 0.0, z])) for z in (0.05, 0.2)]
    far = [texture_level(model, CAMERA, R, np.array([0.0, 0.0, z])) for z in (5.0, 20.0)]
    assert near == [cap, cap]  # the texture is used as it is at both: one scene
    assert far[0] > far[1] and far[0] < cap  # reduced ever more with range: a level each
    # at the cap the prefilter keeps every texel (≤ TEXELS_PER_PIXEL texels per pixel)
    assert 128 / 2 ** (cap / 2) <= TEXELS_PER_PIXEL


def test_untextured_model_shares_its_renderer_across_ranges(variant: str) -> None:
    model = _quad(None)
    renderers = {
        id(get_renderer(model, CAMERA, LIGHT, (1.0,), 4, texture_level(model, CAMERA, R, t)))
        for t in (np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, 30.0]))
    }
    assert len(renderers) == 1
