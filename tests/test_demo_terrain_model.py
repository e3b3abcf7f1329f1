"""The demo terrain is a built-in model beside demo-sat: registered by workers, listed, not
deletable, and its form defaults look down at it (worker/jobs/models.py, service/pages)."""

from __future__ import annotations

from typing import Any

import redis
from fastapi.testclient import TestClient
from service_api_helpers import (
    KEYS,
    api_client,  # noqa: F401 (the client fixture)
    redis_db,  # noqa: F401 (the r fixture)
)

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
