"""The renderer cache keeps one model's renderers: another model's lets them go."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator

import numpy as np
import pytest

from worker.align import renderers
from worker.align.renderers import get_renderer
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel, MeshPart
from worker.engine.renderer import LightingSpec

CAMERA = PinholeCamera(48, 48, 60.0, 60.0, 23.5, 23.5)
LIGHT = LightingSpec((0.4, -0.5, -0.77), 3.0, 0.02)
R, T = np.eye(3), np.array([0.0, 0.0, 4.0])


@pytest.fixture(autouse=True)
def _no_scenes_left() -> Iterator[None]:
    """Leave no renderer behind: a live scene changes what other tests' renders record."""
    yield
    renderers._renderers.clear()
    gc.collect()


def _quad(name: str, size: float) -> LoadedModel:
    """A square of side 2·size facing the camera (its sha256 field is ``name``)."""
    V = size * np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    return LoadedModel(
        name=name,
        sha256=name,
        parts=[MeshPart(V, F, None, None, None, None)],
        bounds=np.stack([V.min(0), V.max(0)]).astype(np.float64),
        n_vertices=4,
        n_faces=2,
        textured=False,
    )


def _models_cached() -> set[str]:
    return {str(key[0]) for key in renderers._renderers}


def test_another_model_lets_the_kept_renderers_go(variant: str) -> None:
    renderers._renderers.clear()
    small, large = _quad("cache-small", 0.5), _quad("cache-large", 1.0)
    first = get_renderer(small, CAMERA, LIGHT, (1.0,), 4)
    second = get_renderer(small, CAMERA, LIGHT, (1.0, 0.5), 4)  # same model, another key
    assert second is not first and _models_cached() == {"cache-small"}
    assert len(renderers._renderers) == 2
    assert get_renderer(small, CAMERA, LIGHT, (1.0,), 4) is first  # reused
    gone = weakref.ref(second)
    del second
    held = first.render(R, T)  # a caller holding a renderer keeps it working
    other = get_renderer(large, CAMERA, LIGHT, (1.0,), 4)
    gc.collect()
    assert _models_cached() == {"cache-large"} and len(renderers._renderers) == 1
    assert gone() is None  # freed: its scene no longer takes part in other kernels' tracing
    np.testing.assert_array_equal(first.render(R, T), held)
    # the larger square covers more of the frame: each renderer draws its own model
    assert (other.render(R, T).sum(axis=2) > 0).sum() > (held.sum(axis=2) > 0).sum()


def test_the_same_model_keeps_its_renderers_up_to_the_cache_size(variant: str) -> None:
    renderers._renderers.clear()
    model = _quad("cache-one", 0.5)
    built = [
        get_renderer(model, CAMERA, LIGHT, (1.0,), 4, level)
        for level in range(renderers.RENDERER_CACHE_SIZE + 1)
    ]
    assert len({id(r) for r in built}) == len(built)
    assert len(renderers._renderers) == renderers.RENDERER_CACHE_SIZE  # the oldest went
    assert get_renderer(model, CAMERA, LIGHT, (1.0,), 4, len(built) - 1) is built[-1]
