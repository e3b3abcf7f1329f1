"""Models, renders, probes and metrics, on a real Redis without workers (nothing here
renders): bad requests to the endpoints other than ``POST /v1/estimates`` (4xx naming the field,
nothing enqueued or stored), model uploads, renders without a worker, the probes, ``/metrics``,
the OpenAPI document, and Redis down."""

from __future__ import annotations

import json
import struct
from datetime import UTC, datetime
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from rq import Queue, Worker
from service_api_helpers import (
    KEYS,
    api_client,  # noqa: F401 (the client fixture)
    assert_field_error,
    base_request,
    png,
    queued,
    redis_db,  # noqa: F401 (the r fixture)
    submit,
)

from schemas.models import ModelPublic
from schemas.settings import get_settings
from service.main import create_app
from service.store import ModelStore
from service.store.blobs import model_file_name, open_blob_store

CUBE_OBJ = b"""# unit cube
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 2 3 7
f 2 7 6
f 3 4 8
f 3 8 7
f 4 1 5
f 4 5 8
"""
RENDER_BODY = {
    "model_id": "demo-sat",
    "camera": base_request()["camera"],
    "pose": base_request()["initial_pose"],
}
#: A PLY whose header declares two billion faces (the data is 100 bytes).
PLY_FACE_BOMB = (
    b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
    b"property float y\nproperty float z\nelement face 2000000000\n"
    b"property list uchar int vertex_indices\nend_header\n" + bytes(100)
)
#: A glTF whose buffer is a file of the server (it must never be read).
GLTF_EXTERNAL_URI = json.dumps(
    {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "file:///etc/passwd", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
).encode()


# ----------------------------------------------------------------------------- the battery
BAD_OTHERS: dict[str, tuple[str, str, dict[str, Any], int, tuple[str | int, ...]]] = {
    "render without pose": (
        "POST",
        "/v1/renders",
        {"json": {"model_id": "demo-sat", "camera": base_request()["camera"]}},
        422,
        ("body", "pose"),
    ),
    "render spp 0": (
        "POST",
        "/v1/renders",
        {
            "json": {
                "model_id": "demo-sat",
                "camera": base_request()["camera"],
                "pose": base_request()["initial_pose"],
                "spp": 0,
            }
        },
        422,
        ("body", "spp"),
    ),
    "render of an unknown model": (
        "POST",
        "/v1/renders",
        {
            "json": {
                "model_id": "feedfacefeedface",
                "camera": base_request()["camera"],
                "pose": base_request()["initial_pose"],
            }
        },
        422,
        ("body", "model_id"),
    ),
    "render body not JSON": (
        "POST",
        "/v1/renders",
        {"content": b"{oops", "headers": {"content-type": "application/json"}},
        422,
        ("body",),
    ),
    "model upload without file": (
        "POST",
        "/v1/models",
        {"files": {"name": (None, "x")}},  # multipart, but no file part
        422,
        ("body", "file"),
    ),
    "model upload .txt": (
        "POST",
        "/v1/models",
        {"files": {"file": ("cube.txt", CUBE_OBJ)}},
        422,
        ("body", "file"),
    ),
    "model upload garbage": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.ply", b"ply\nnonsense\n")}},
        422,
        ("body", "file"),
    ),
    "model upload empty": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.obj", b"")}},
        422,
        ("body", "file"),
    ),
    "model name too long": (
        "POST",
        "/v1/models",
        {"files": {"file": ("cube.obj", CUBE_OBJ)}, "data": {"name": "n" * 201}},
        422,
        ("body", "name"),
    ),
    "list limit 0": ("GET", "/v1/estimates?limit=0", {}, 422, ("query", "limit")),
    "list limit too large": ("GET", "/v1/estimates?limit=1000", {}, 422, ("query", "limit")),
    "list cursor not a cursor": ("GET", "/v1/estimates?cursor=abc", {}, 422, ("query", "cursor")),
    "render pose NaN": (
        "POST",
        "/v1/renders",
        {
            "content": json.dumps(
                {**RENDER_BODY, "pose": {"t": [0, 0, 14], "q": [0, float("nan"), 0]}}
            ),
            "headers": {"content-type": "application/json"},
        },
        422,
        ("body", "pose", "q", 1),
    ),
    "render unknown field": (
        "POST",
        "/v1/renders",
        {"json": {**RENDER_BODY, "exposure": 2}},
        422,
        ("body", "exposure"),
    ),
    "render body a list": (
        "POST",
        "/v1/renders",
        {"content": b"[]", "headers": {"content-type": "application/json"}},
        422,
        ("body",),
    ),
    "render behind the camera": (
        "POST",
        "/v1/renders",
        {"json": {**RENDER_BODY, "pose": {"t": [0, 0, -1], "quaternion": [1, 0, 0, 0]}}},
        422,
        ("body", "pose"),
    ),
    "model PLY declaring 2e9 faces": (
        "POST",
        "/v1/models",
        {"files": {"file": ("bomb.ply", PLY_FACE_BOMB)}},
        422,
        ("body", "file"),
    ),
    "model GLB with a broken header": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.glb", b"glTF" + struct.pack("<II", 2, 100) + bytes(88))}},
        422,
        ("body", "file"),
    ),
    "model OBJ with an index out of range": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999999\n")}},
        422,
        ("body", "file"),
    ),
    "model a PNG named .obj": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.obj", png())}},
        422,
        ("body", "file"),
    ),
    "model glTF pointing at a local file": (
        "POST",
        "/v1/models",
        {"files": {"file": ("x.gltf", GLTF_EXTERNAL_URI)}},
        422,
        ("body", "file"),
    ),
    "model without file name": (
        "POST",
        "/v1/models",
        {"files": {"file": ("", CUBE_OBJ)}},
        422,
        ("body", "file"),
    ),
}


@pytest.mark.parametrize("case", BAD_OTHERS.values(), ids=BAD_OTHERS.keys())
def test_bad_requests_to_other_endpoints(
    client: TestClient, r: redis.Redis, case: tuple[str, str, dict[str, Any], int, tuple[Any, ...]]
) -> None:
    method, path, kwargs, status, loc = case
    assert_field_error(client.request(method, path, **kwargs), status, loc)
    assert queued(r) == 0
    assert r.zcard(KEYS.models_index) == 0


# ----------------------------------------------------------------------------- good requests
def test_model_upload_is_content_addressed(client: TestClient, r: redis.Redis) -> None:
    first = client.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)}, data={"name": "Cube"})
    assert first.status_code == 201, first.text
    model = first.json()
    assert model["name"] == "Cube" and len(model["id"]) == 16
    assert (model["vertices"], model["faces"], model["textured"]) == (8, 12, False)
    assert model["bounds"] == [[0, 0, 0], [1, 1, 1]]
    assert first.headers["location"] == f"/v1/models/{model['id']}"
    again = client.post("/v1/models", files={"file": ("other.obj", CUBE_OBJ)})
    assert again.status_code == 200 and again.json()["id"] == model["id"]
    # workers fetch it from the blob store; Redis keeps the metadata only
    blobs = open_blob_store(get_settings())
    assert ModelStore(r, KEYS, blobs=blobs).data(model["id"]) == CUBE_OBJ
    assert not r.exists(KEYS.model_data(model["id"]))
    blob = model_file_name(model["id"], model["sha256"])
    assert blobs.get(blob) == CUBE_OBJ
    assert [m["id"] for m in client.get("/v1/models").json()["items"]] == [model["id"]]
    assert client.get(f"/v1/models/{model['id']}").json() == model
    assert client.delete(f"/v1/models/{model['id']}").status_code == 204
    assert client.get(f"/v1/models/{model['id']}").status_code == 404
    assert blobs.get(blob) is None  # the file went with its last owner


def test_builtin_model_cannot_be_deleted(client: TestClient, r: redis.Redis) -> None:
    demo = ModelPublic(
        id="demo-sat",
        name="Demo",
        vertices=3,
        faces=1,
        bounds=[[0, 0, 0], [1, 1, 0]],
        textured=False,
        format="glb",
        size_bytes=3,
        sha256="0" * 64,
        created_at=datetime.now(UTC),
        builtin=True,
    )
    ModelStore(r, KEYS, blobs=open_blob_store(get_settings())).put(demo, b"glb")
    assert client.get("/v1/models/demo-sat").json()["builtin"] is True
    assert client.delete("/v1/models/demo-sat").status_code == 409


def test_probes_without_workers(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok", "workers": 0}
    ready = client.get("/readyz")  # ready: it accepts jobs, which queue until a worker starts
    assert ready.status_code == 200
    assert ready.json()["ready"] is True and ready.json()["workers"] == 0
    assert ready.json()["redis"] is True and "no worker" in ready.json()["reason"]


def test_readyz_is_a_503_problem_while_redis_is_away(monkeypatch: Any) -> None:
    from conftest import free_port

    monkeypatch.setenv("PROXPOSE_REDIS_URL", f"redis://127.0.0.1:{free_port()}/0")
    get_settings.cache_clear()
    with TestClient(create_app()) as c:
        ready = c.get("/readyz")
        assert c.get("/healthz").json() == {"status": "ok", "workers": None}
    assert ready.status_code == 503 and int(ready.headers["Retry-After"]) > 0
    assert ready.headers["content-type"].startswith("application/problem+json")
    body = ready.json()
    assert body["ready"] is False and body["redis"] is False and body["code"] == "unavailable"


def test_render_without_workers_is_503(client: TestClient, r: redis.Redis) -> None:
    body = {
        "model_id": "demo-sat",
        "camera": base_request()["camera"],
        "pose": base_request()["initial_pose"],
    }
    response = client.post("/v1/renders", json=body)
    assert response.status_code == 503 and "worker" in response.json()["detail"]
    assert queued(r) == 0


def test_render_wait_times_out_with_504_and_leaves_nothing_queued(
    client: TestClient, r: redis.Redis, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PROXPOSE_RENDER_TIMEOUT_S", "0.5")
    get_settings.cache_clear()
    idle = Worker([Queue(KEYS.estimate_queue, connection=r)], connection=r, name="idle")
    idle.register_birth()  # registered, alive, but never takes the job
    try:
        body = {
            "model_id": "demo-sat",
            "camera": base_request()["camera"],
            "pose": base_request()["initial_pose"],
        }
        response = client.post("/v1/renders", json=body)
    finally:
        idle.register_death()
    assert response.status_code == 504, response.text
    assert "0.5 s" in response.json()["detail"]
    assert queued(r) == 0


def test_model_with_too_many_faces_is_rejected(
    client: TestClient, r: redis.Redis, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_MODEL_FACES", "10")
    get_settings.cache_clear()
    response = client.post("/v1/models", files={"file": ("cube.obj", CUBE_OBJ)})
    assert assert_field_error(response, 422, ("body", "file"))["type"] == "model_too_large"
    assert r.zcard(KEYS.models_index) == 0


def test_metrics_expose_requests_queue_and_workers(client: TestClient) -> None:
    submit(client)
    client.get("/v1/estimates/nope")
    text = client.get("/metrics").text
    assert (
        'proxpose_http_requests_total{method="POST",route="/v1/estimates",status="202"} 1.0' in text
    )
    assert 'route="/v1/estimates/{job_id}",status="404"' in text
    assert 'proxpose_queue_depth{queue="estimates"} 1.0' in text
    assert "proxpose_workers 0.0" in text
    assert "proxpose_redis_up 1.0" in text


def test_openapi_documents_every_route(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    for path in (
        "/v1/models",
        "/v1/models/{model_id}",
        "/v1/estimates",
        "/v1/estimates/{job_id}",
        "/v1/estimates/{job_id}/events",
        "/v1/estimates/{job_id}/artifacts/{name}",
        "/v1/renders",
        "/healthz",
        "/readyz",
        "/metrics",
    ):
        assert path in paths
    assert client.get("/docs").status_code == 200


def test_redis_down_is_503_not_500(r: redis.Redis, monkeypatch: Any) -> None:
    from conftest import free_port

    monkeypatch.setenv("PROXPOSE_REDIS_URL", f"redis://127.0.0.1:{free_port()}/0")
    get_settings.cache_clear()
    with TestClient(create_app()) as c:
        response = c.get("/v1/estimates")
    assert response.status_code == 503
    assert "Redis" in response.json()["detail"]
