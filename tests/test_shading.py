"""Choosing the shading normals that explain the image (worker/align/shading.py), on tiny renders
of a coarse sphere: its smooth (file) and flat (faceted) renders differ visibly."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.options import EstimateOptions
from worker.align.renderers import get_renderer
from worker.align.session import Session
from worker.align.shading import choose_shading
from worker.engine.camera import PinholeCamera
from worker.engine.images import srgb_encode, to_grey
from worker.engine.meshes import LoadedModel, MeshPart
from worker.engine.posemath import axis_angle_to_matrix
from worker.engine.renderer import LightingSpec

CAMERA = PinholeCamera(96, 96, 110.0, 110.0, 47.5, 47.5)
LIGHT = LightingSpec((0.4, -0.5, -0.77), 3.0, 0.02)
R = axis_angle_to_matrix(np.array([0.3, 1.0, 0.2]), 0.7)
T = np.array([0.05, -0.02, 3.0])


def _sphere(normals: bool) -> LoadedModel:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    V = mesh.vertices.astype(np.float32)
    N = mesh.vertex_normals.astype(np.float32) if normals else None
    part = MeshPart(V, mesh.faces.astype(np.uint32), N, None, None, None)
    return LoadedModel(
        name="ico",
        sha256=f"ico-{normals}",
        parts=[part],
        bounds=np.stack([V.min(0), V.max(0)]).astype(np.float64),
        n_vertices=len(V),
        n_faces=len(mesh.faces),
        textured=False,
    )


def _session(model: LoadedModel, reference: np.ndarray, shading: str = "file") -> Session:
    renderer = get_renderer(model, CAMERA, LIGHT, (1.0,), 16, 0, shading)
    return Session(
        renderer=renderer,
        reference=reference,
        reference_grey=to_grey(reference),
        options=EstimateOptions().resolved(),
        R=R,
        t=T,
    )


def _reference(model: LoadedModel, shading: str) -> np.ndarray:
    linear = get_renderer(model, CAMERA, LIGHT, (1.0,), 64, 0, shading).render(R, T, spp=64)
    return srgb_encode(0.8 * linear)  # another exposure, as a camera would differ


def _renderer_for(model: LoadedModel):  # noqa: ANN202
    return lambda shading: get_renderer(model, CAMERA, LIGHT, (1.0,), 16, 0, shading)


@pytest.mark.parametrize("truth", ["file", "faceted"])
@pytest.mark.parametrize("start", ["file", "faceted"])
def test_the_shading_that_made_the_image_is_kept_or_chosen(
    variant: str, truth: str, start: str
) -> None:
    model = _sphere(normals=True)
    session = _session(model, _reference(model, truth), start)
    assert choose_shading(session, _renderer_for(model)) == truth
    assert session.renderer.shading == truth
    assert session.renders == 2  # the current pose rendered once each way
    view = session.current_view()  # the render kept is the chosen shading's
    assert session.renders == 2 and view is session.current


def test_a_model_without_vertex_normals_has_nothing_to_choose(variant: str) -> None:
    model = _sphere(normals=False)
    session = _session(model, _reference(model, "faceted"))
    assert choose_shading(session, _renderer_for(model)) == "file"
    assert session.renders == 0
