"""The terrain beside the spacecraft in the product: workers register demo-terrain, its form
defaults look down at it, and ``proxpose bench --terrain`` reports the terrain band apart."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from service_api_helpers import (
    KEYS,
    api_client,  # noqa: F401 (the client fixture)
    redis_db,  # noqa: F401 (the r fixture)
)
from test_bench import QUICK_TIMEOUT_S, proxpose

from schemas.settings import get_settings
from service.store.blobs import open_blob_store


def test_workers_register_the_demo_terrain_beside_demo_sat(
    client: TestClient, r: redis.Redis, tmp_path: Any
) -> None:
    """Both built-ins are registered (idempotently), cannot be deleted, and the terrain's form
    defaults look down at it from above (its +y is up) with the sun above the ground."""
    from worker.jobs.models import register_demo_model

    blobs = open_blob_store(get_settings())
    register_demo_model(r, KEYS, tmp_path, blobs)
    register_demo_model(r, KEYS, tmp_path, blobs)  # again: nothing changes
    terrain = client.get("/v1/models/demo-terrain").json()
    assert terrain["builtin"] is True and terrain["faces"] == 2 * 512 * 512
    assert client.get("/v1/models/demo-sat").json()["builtin"] is True
    assert client.delete("/v1/models/demo-terrain").status_code == 409
    request = client.get("/models/demo-terrain/request.json").json()
    w, x, y, z = request["initial_pose"]["quaternion"]
    # the camera's optical axis in the model frame (third row of R) points down (−y)
    axis_y = 2 * (y * z + w * x)
    assert axis_y < -0.85
    sun_camera = request["lighting"]["sun_direction"]
    up_camera = [2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)]
    assert sum(s * u for s, u in zip(sun_camera, up_camera, strict=True)) > 0.5  # sun above


@pytest.mark.slow
def test_quick_bench_with_the_terrain_band(tmp_path: Path) -> None:
    """--terrain adds the terrain and the held-out ridged terrain beside the demo satellite's
    band: their cases in the terrain band, from the guess and from the truth, reported apart."""
    out = proxpose(
        "bench",
        "--quick",
        "--terrain",
        "--methods",
        "default",
        "--output",
        str(tmp_path / "out"),
        env={"PROXPOSE_DATA_DIR": str(tmp_path / "data")},
        timeout=QUICK_TIMEOUT_S,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    data = json.loads((tmp_path / "out" / "bench.json").read_text())
    terrain = [r for r in data["cases"] if r["reference"] == "terrain"]
    assert {(r["model"], r["start"]) for r in terrain} == {
        (m, s) for m in ("terrain", "terrain-ridged") for s in ("offset", "truth")
    }
    assert all(2.0 < r["initial_rotation_deg"] <= 6.0 for r in terrain if r["start"] == "offset")
    assert [g["group"] for g in data["summary"]["by_band"]] == [3.0, 10.0, 20.0]  # demo only
    assert [g["group"] for g in data["summary"]["by_terrain"]] == ["terrain", "terrain-ridged"]
    md = (tmp_path / "out" / "bench.md").read_text()
    assert "### Terrain band" in md and "#### `terrain-ridged`" in md
