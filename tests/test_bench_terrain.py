"""The terrain band of `proxpose bench` (worker/bench/terrain.py), end to end on the quick suite."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_bench import proxpose, run_bench


@pytest.mark.slow
def test_quick_bench_with_the_terrain_band(tmp_path: Path) -> None:
    """--terrain adds the terrain and the held-out ridged terrain beside the demo satellite's
    band: their cases in the terrain band, from the guess and from the truth, reported apart."""
    out = run_bench(
        tmp_path,
        *("--quick", "--terrain", "--methods", "default", "--sun-elevation", "30,40"),
        *("--altitude", "500,600", "--tilt", "0,10"),
    )
    data = json.loads((out / "bench.json").read_text())
    terrain = [r for r in data["cases"] if r["reference"] == "terrain"]
    assert {(r["model"], r["start"]) for r in terrain} == {
        (m, s) for m in ("terrain", "terrain-ridged") for s in ("offset", "truth")
    }
    assert all(2.0 < r["initial_rotation_deg"] <= 6.0 for r in terrain if r["start"] == "offset")
    assert [g["group"] for g in data["summary"]["by_band"]] == [3.0, 10.0, 20.0]  # demo only
    assert [g["group"] for g in data["summary"]["by_terrain"]] == ["terrain", "terrain-ridged"]
    md = (out / "bench.md").read_text()
    assert "### Terrain band" in md and "#### `terrain-ridged`" in md
    assert "sun 30–40° above the horizon" in md and data["config"]["sun_elevation_deg"] == [30, 40]
    assert "Camera 500–600 m above the ground, tilted 0–10° from the nadir" in md
    assert data["config"]["altitude_m"] == [500, 600] and data["config"]["tilt_deg"] == [0, 10]


def _elevation_deg(sun_camera: np.ndarray, R: np.ndarray) -> float:
    """Elevation of a camera-frame sun direction above the terrain's horizon (+y up)."""
    return float(np.degrees(np.arcsin((R.T @ sun_camera)[1])))


def test_terrain_case_puts_the_sun_at_the_asked_elevation(tmp_path: Path) -> None:
    """make_terrain_case draws the sun's elevation from the range it is given: the request's
    sun at it, the reference's true sun SUN_ERROR_DEG away from the request's."""
    from worker.bench.cases import bench_camera
    from worker.bench.synth import CaseSpec
    from worker.bench.terrain import (
        SUN_ERROR_DEG,
        TerrainView,
        make_terrain_case,
        terrain_model_path,
    )
    from worker.engine.meshes import load_model
    from worker.entry import init_renderer_backend

    init_renderer_backend()
    model = load_model(terrain_model_path("terrain", tmp_path))
    for elevation in (8.0, 40.0):
        case = make_terrain_case(
            model,
            bench_camera(48, 48),
            CaseSpec(3.0, 0.03),
            5,
            view=TerrainView(sun_elevation_deg=(elevation,) * 2),
        )
        asked = np.asarray(case.request.lighting.sun_direction)
        assert _elevation_deg(asked, case.R_true) == pytest.approx(elevation, abs=1e-6)
        off = np.degrees(np.arccos(np.clip(asked @ case.sun_true, -1.0, 1.0)))
        assert off == pytest.approx(SUN_ERROR_DEG, abs=0.01)


@pytest.mark.parametrize("value", ["50,40", "0,10", "10", "10,90"])
def test_bench_rejects_a_bad_sun_elevation(value: str) -> None:
    out = proxpose("bench", "--terrain", "--sun-elevation", value, "--output", "/nonexistent")
    assert out.returncode == 2
    assert "--sun-elevation" in out.stderr


def test_bench_rejects_a_sun_elevation_without_terrain() -> None:
    out = proxpose(
        "bench", "--models", "demo", "--sun-elevation", "5,15", "--output", "/nonexistent"
    )
    assert out.returncode == 2
    assert "--sun-elevation applies to the terrain band" in out.stderr


@pytest.mark.parametrize(("altitude", "tilt"), [(300.0, 0.0), (900.0, 40.0)])
def test_terrain_case_puts_the_camera_at_the_asked_height_and_tilt(
    tmp_path: Path, altitude: float, tilt: float
) -> None:
    """make_terrain_case draws the camera's height above the ground it looks at and its tilt
    from the nadir from the view's ranges (a tilt of 0 looks straight down)."""
    from worker.bench.cases import bench_camera
    from worker.bench.synth import CaseSpec
    from worker.bench.terrain import TerrainView, make_terrain_case, terrain_model_path
    from worker.engine.meshes import load_model
    from worker.entry import init_renderer_backend

    init_renderer_backend()
    model = load_model(terrain_model_path("terrain", tmp_path))
    view = TerrainView(altitude_m=(altitude,) * 2, tilt_deg=(tilt,) * 2)
    case = make_terrain_case(model, bench_camera(48, 48), CaseSpec(3.0, 0.03), 5, view=view)
    centre = -case.R_true.T @ case.t_true  # the camera's centre, model frame (+y up)
    axis = case.R_true.T @ np.array([0.0, 0.0, 1.0])  # where it looks
    assert centre[1] == pytest.approx(altitude, rel=1e-9)
    assert np.degrees(np.arccos(-axis[1])) == pytest.approx(tilt, abs=1e-6)
    assert case.reference.max() > 0  # it sees the lit ground


@pytest.mark.parametrize(
    ("option", "value"),
    [("--altitude", "0,100"), ("--altitude", "700,500"), ("--tilt", "-5,10"), ("--tilt", "10,80")],
)
def test_bench_rejects_a_bad_terrain_view(option: str, value: str) -> None:
    out = proxpose("bench", "--terrain", f"{option}={value}", "--output", "/nonexistent")
    assert out.returncode == 2
    assert f"{option} must be LO,HI" in out.stderr


@pytest.mark.parametrize("option", ["--altitude", "--tilt"])
def test_bench_rejects_a_terrain_view_without_terrain(option: str) -> None:
    out = proxpose("bench", "--models", "demo", option, "5,15", "--output", "/nonexistent")
    assert out.returncode == 2
    assert f"{option} applies to the terrain band" in out.stderr
