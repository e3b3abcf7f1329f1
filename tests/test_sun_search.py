"""The sun searched by the pattern of what it lights (worker.align.sunsearch).

Over terrain at a low sun the request's sun, 3° off, lights other ground than the reference
shows lit; the search, run between the coarse stage and the refinement of a scene that fills the
frame, should bring the renderer's sun close to the one the reference was made with. Real
renders of a small DEM; the reference from the bench's ray tracer (another reflectance law,
exposure, gamma, noise). A spy records the sun before and after the search.
"""

from __future__ import annotations

import numpy as np
import pytest

from worker.align import sunsearch
from worker.align.session import Session
from worker.align.sunsearch import lit_mask, pattern_score
from worker.bench.cases import bench_camera
from worker.bench.synth import Case, CaseSpec, pose_json
from worker.bench.terrain import make_terrain_case
from worker.demo.terrain import write_demo_terrain
from worker.engine.meshes import LoadedModel, load_model

SIDE_PX = 192


@pytest.fixture(scope="module")
def terrain(tmp_path_factory: pytest.TempPathFactory, variant: str) -> LoadedModel:
    path = tmp_path_factory.mktemp("terrain") / "terrain.glb"
    return load_model(write_demo_terrain(path, seed=3, posts=257))


class _Searched(Exception):
    """Raised by the spy once the search has run."""


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _searched_suns(
    model: LoadedModel, case: Case, monkeypatch: pytest.MonkeyPatch
) -> list[tuple[float, float, bool, int]]:
    """(° off the true sun before, after, moved, renders made) of the search an estimate runs
    (the estimate is stopped there: the refinement after it is not under test)."""
    from worker.align.estimator import estimate

    found: list[tuple[float, float, bool, int]] = []
    search = sunsearch.search_sun

    def spy(session: Session) -> bool:
        before = _angle_deg(np.array(session.renderer.lighting.sun_direction), case.sun_true)
        renders = session.renders
        moved = search(session)
        after = _angle_deg(np.array(session.renderer.lighting.sun_direction), case.sun_true)
        found.append((before, after, moved, session.renders - renders))
        raise _Searched

    monkeypatch.setattr(sunsearch, "search_sun", spy)
    request = case.request.model_copy(update={"initial_pose": pose_json(case.R_true, case.t_true)})
    with pytest.raises(_Searched):
        estimate(model, case.reference.astype(np.float32) / 255.0, request)
    return found


def test_a_low_sun_is_found_from_the_lit_pattern(
    terrain: LoadedModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = make_terrain_case(
        terrain, bench_camera(SIDE_PX), CaseSpec(0.0, 0.0), 11, sun_elevation_deg=(6, 9)
    )
    found = _searched_suns(terrain, case, monkeypatch)
    before, after, moved, renders = found[0]
    assert before == pytest.approx(3.0, abs=0.01)  # the bench's request is 3° off
    assert moved and after < 1.0
    assert renders <= sunsearch.MAX_RENDERS + 4


def test_a_target_on_the_sky_is_left_to_the_features(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, variant: str
) -> None:
    """A spacecraft does not fill the frame: the search returns at once, without a render (the
    refinement's feature-based sun fit is what moves its sun)."""
    from worker.bench.synth import make_case
    from worker.demo.satellite import demo_satellite_path

    model = load_model(demo_satellite_path(tmp_path_factory.mktemp("demo")))
    case = make_case(model, bench_camera(256), CaseSpec(0.0, 0.0), seed=0, reference="sun")
    found = _searched_suns(model, case, monkeypatch)
    assert [(moved, renders) for _, _, moved, renders in found] == [(False, 0)]


def test_the_pattern_score_ignores_tone_and_sees_the_pattern() -> None:
    rng = np.random.default_rng(0)
    render = np.full((96, 96), 0.05)
    render[20:60, 10:50] = 0.8  # a lit block on shadowed ground
    render[70:90, 60:90] = 0.6
    mask, lit = lit_mask(render)
    assert mask[30, 30] and not mask[5, 5] and 0.2 < lit < 0.3
    # the same pattern under another tone curve and with noise scores high ...
    reference = (0.7 * render) ** (1 / 2.2) + rng.normal(0, 0.01, render.shape)
    assert pattern_score(render, reference) > 0.9
    # ... the pattern moved by 15 px far lower
    moved = np.roll(reference, 15, axis=1)
    assert pattern_score(render, moved) < pattern_score(render, reference) - 0.3
    # a render with nothing lit, or all of it, gives no score
    assert pattern_score(np.full((96, 96), 0.5), reference) == -1.0
