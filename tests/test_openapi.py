"""The OpenAPI document as a client generator reads it: every operation has a stable id, a
summary and its error answers as problem details; the estimate's multipart body carries the
typed request. And the errors themselves: every kind the API answers is RFC 9457 problem details
(no Redis needed for these: the app is built but not started, or started on a dead port)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from fastapi.testclient import TestClient
from service_api_helpers import (
    api_client,  # noqa: F401 (the client fixture)
    assert_field_error,
    assert_problem,
    base_request,
    png,
    queued,
    redis_db,  # noqa: F401 (the r fixture)
    submit,
)

from schemas.camera import Camera
from schemas.jobs import EstimateCreate
from schemas.lighting import Lighting
from schemas.options import EstimateOptions
from schemas.track_jobs import TrackCreate
from service.main import create_app

METHODS = {"get", "post", "put", "patch", "delete"}


@pytest.fixture(scope="module")
def document() -> dict[str, Any]:
    return create_app().openapi()


def operations(document: dict[str, Any]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    for path, item in document["paths"].items():
        for method, operation in item.items():
            if method in METHODS:
                yield method, path, operation


def test_every_operation_has_a_stable_id_a_summary_and_its_errors(document: dict[str, Any]) -> None:
    ids = []
    for method, path, op in operations(document):
        where = f"{method.upper()} {path}"
        op_id = op.get("operationId", "")
        assert op_id.isidentifier() and "_v1_" not in op_id and not op_id.endswith(f"_{method}"), (
            where,
            op_id,
        )
        ids.append(op_id)
        assert op.get("summary"), where
        responses = op["responses"]
        assert any(s.startswith("2") for s in responses), where
        if op.get("parameters") or op.get("requestBody"):
            assert "422" in responses, where
        if path.startswith("/v1/"):
            assert {"401", "500", "503"} <= set(responses), (where, sorted(responses))
        for status, response in responses.items():
            if status[0] in "45":
                content = response["content"]
                assert list(content) == ["application/problem+json"], (where, status)
                schema = content["application/problem+json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/Problem"}, (where, status)
            if status in ("202", "429", "503"):
                assert "Retry-After" in response.get("headers", {}), (where, status)
    assert len(ids) == len(set(ids)), "operation ids are not unique"
    assert {"create_estimate", "get_estimate", "list_estimates", "cancel_estimate"} <= set(ids)


def test_the_track_routes_are_documented_with_their_body_and_problems(
    document: dict[str, Any],
) -> None:
    post = document["paths"]["/v1/tracks"]["post"]
    multipart = post["requestBody"]["content"]["multipart/form-data"]
    assert multipart["schema"]["required"] == ["frames", "request"]
    props = multipart["schema"]["properties"]
    assert props["request"] == {"$ref": "#/components/schemas/TrackCreate"}
    assert props["frames"]["type"] == "array" and props["frames"]["items"]["format"] == "binary"
    assert multipart["encoding"]["request"]["contentType"] == "application/json"
    assert {"202", "409", "413", "415", "422", "429"} <= set(post["responses"])
    assert "max_track_frames" in post["responses"]["413"]["description"]
    components = document["components"]["schemas"]
    assert "TrackCreate" in components and "TrackPublic" in components
    assert "ground_truth" in components["TrackCreate"]["properties"]
    ops = {
        (method, path): op
        for method, path, op in operations(document)
        if path.startswith("/v1/tracks")
    }
    expected = {
        ("post", "/v1/tracks"): "create_track",
        ("get", "/v1/tracks/{job_id}"): "get_track",
        ("delete", "/v1/tracks/{job_id}"): "cancel_track",
        ("get", "/v1/tracks/{job_id}/events"): "stream_track_events",
        ("get", "/v1/tracks/{job_id}/track.json"): "get_track_json",
        ("get", "/v1/tracks/{job_id}/artifacts/{name}"): "get_track_artifact",
    }
    assert {key: op["operationId"] for key, op in ops.items()} == expected
    for key, op in ops.items():
        assert "404" in op["responses"] or key[0] == "post", key


def test_the_estimate_body_describes_the_request_part(document: dict[str, Any]) -> None:
    body = document["paths"]["/v1/estimates"]["post"]["requestBody"]
    multipart = body["content"]["multipart/form-data"]
    props = multipart["schema"]["properties"]
    assert multipart["schema"]["required"] == ["image", "request"]
    assert props["request"] == {"$ref": "#/components/schemas/EstimateCreate"}
    assert props["image"]["format"] == "binary"
    assert multipart["encoding"]["request"]["contentType"] == "application/json"
    components = document["components"]["schemas"]
    for name in ("EstimateCreate", "Camera", "Pose", "Lighting", "EstimateOptions", "Problem"):
        assert name in components, name
    create = components["EstimateCreate"]
    assert create["properties"]["camera"] == {"$ref": "#/components/schemas/Camera"}
    assert create["properties"]["model_id"]["examples"] == ["demo-sat"]
    assert components["Camera"]["properties"]["fx"].get("description")
    # every part of the request documents itself with an example that validates
    models = {
        "Camera": Camera,
        "Lighting": Lighting,
        "EstimateOptions": EstimateOptions,
        "EstimateCreate": EstimateCreate,
        "TrackCreate": TrackCreate,
    }
    for name, model in models.items():
        assert components[name]["examples"], name
        for example in components[name]["examples"]:
            model.model_validate(example)
    # no dangling references anywhere
    text = str(document)
    for ref in {part.split("'")[0] for part in text.split("#/components/schemas/")[1:]}:
        assert ref in components, ref
    assert "HTTPValidationError" not in components


def test_problem_schema_lists_the_field_errors(document: dict[str, Any]) -> None:
    problem = document["components"]["schemas"]["Problem"]
    assert {"type", "title", "status", "detail", "code"} <= set(problem["required"])
    assert "errors" in problem["properties"]


# ----------------------------------------------------------------------------- problem details
def test_validation_errors_are_problems_naming_each_bad_field(client: TestClient, r: Any) -> None:
    bad = base_request(camera={"width": 64, "height": 64, "fx": -1, "fy": 0, "cx": 1, "cy": 1})
    response = submit(client, bad)
    body = assert_problem(response, 422, "validation_error")
    locs = {tuple(e["loc"]) for e in body["errors"]}
    assert ("body", "request", "camera", "fx") in locs and (
        "body",
        "request",
        "camera",
        "fy",
    ) in locs
    assert body["instance"] == "/v1/estimates"
    assert "camera.fx" in body["detail"]
    assert queued(r) == 0
    # FastAPI's own validation (a query parameter) has the same shape
    body = assert_problem(client.get("/v1/estimates?limit=0"), 422, "validation_error")
    assert body["errors"][0]["loc"] == ["query", "limit"]


def test_a_field_error_carries_its_type_as_the_code(client: TestClient, r: Any) -> None:
    response = submit(client, image=png(32, 32))
    error = assert_field_error(response, 422, ("body", "image"))
    assert response.json()["code"] == error["type"] == "image_size_mismatch"


@pytest.mark.parametrize(
    ("method", "path", "status", "code"),
    [
        ("get", "/v1/estimates/" + "0" * 32, 404, "not_found"),
        ("get", "/v1/models/abcdef0123456789", 404, "not_found"),
        ("get", "/no/such/path", 404, "not_found"),
        ("put", "/v1/estimates", 405, "method_not_allowed"),
        ("delete", "/v1/models/demo-sat", 404, "not_found"),
    ],
)
def test_http_errors_are_problems(
    client: TestClient, r: Any, method: str, path: str, status: int, code: str
) -> None:
    assert_problem(client.request(method, path), status, code)


def test_a_body_that_is_not_multipart_is_415(client: TestClient, r: Any) -> None:
    response = client.post("/v1/estimates", json=base_request())
    body = assert_problem(response, 415, "unsupported_media_type")
    assert "multipart/form-data" in body["detail"] and "application/json" in body["detail"]
    assert_problem(client.post("/v1/models", content=b"x"), 415, "unsupported_media_type")
    assert queued(r) == 0


def test_a_job_that_ended_cannot_be_cancelled_409(client: TestClient, r: Any) -> None:
    job_id = submit(client).json()["id"]
    assert client.delete(f"/v1/estimates/{job_id}").status_code == 200  # queued: cancelled
    body = assert_problem(client.delete(f"/v1/estimates/{job_id}"), 409, "job_ended")
    assert job_id in body["detail"]


def test_an_oversized_body_is_a_413_problem(client: TestClient, r: Any, monkeypatch: Any) -> None:
    from schemas.settings import get_settings

    monkeypatch.setenv("PROXPOSE_MAX_IMAGE_BYTES", "2048")
    monkeypatch.setenv("PROXPOSE_MAX_MODEL_BYTES", "2048")
    get_settings.cache_clear()
    big = b"\0" * (2 * 1024 * 1024)
    response = client.post("/v1/estimates", files={"image": ("a.png", big)}, data={"request": "{}"})
    body = assert_problem(response, 413, "too_large")
    assert body["errors"][0]["loc"] == ["body"]


def test_redis_down_is_a_503_problem_with_retry_after(monkeypatch: Any, tmp_path: Any) -> None:
    from conftest import free_port

    from schemas.settings import get_settings

    monkeypatch.setenv("PROXPOSE_REDIS_URL", f"redis://127.0.0.1:{free_port()}/0")
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    try:
        with TestClient(create_app()) as client:
            response = client.get("/v1/estimates/" + "0" * 32)
            assert_problem(response, 503, "unavailable")
            assert int(response.headers["Retry-After"]) > 0
    finally:
        get_settings.cache_clear()
