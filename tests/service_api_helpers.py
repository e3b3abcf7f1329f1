"""Shared by the ``test_service_api_*`` modules (the API on a real Redis, without workers):
their Redis database, the ``r`` and ``client`` fixtures, a valid estimate request and its image,
and the checks of a rejected request."""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import redis
from conftest import settings_on_redis
from fastapi.routing import APIRoute, APIRouter
from fastapi.testclient import TestClient
from PIL import Image
from pydantic import BaseModel
from rq import Queue

from service.main import create_app
from service.store import Keys

#: Redis database of these modules (the session's Redis is shared with other modules).
DB = 1
KEYS = Keys("proxpose")
SIDE_PX = 64


# ----------------------------------------------------------------------------- fixtures
# Each module imports them as redis_db and api_client (a test argument named like an import
# would shadow it); its tests ask for r and client.
@pytest.fixture(name="r")
def redis_db(
    redis_server: Any, tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> Iterator[redis.Redis]:
    """Settings pointing at the ``DB`` Redis database, emptied before and after."""
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch) as client:
        yield client


@pytest.fixture(name="client")
def api_client(r: redis.Redis) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c


def png(width: int = SIDE_PX, height: int = SIDE_PX) -> bytes:
    img = Image.new("RGB", (width, height))
    img.paste((200, 180, 40), (width // 4, height // 4, width // 2, height // 2))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def base_request(**changes: Any) -> dict[str, Any]:
    request: dict[str, Any] = {
        "model_id": "demo-sat",
        "camera": {
            "width": SIDE_PX,
            "height": SIDE_PX,
            "fx": 70.0,
            "fy": 70.0,
            "cx": 31.5,
            "cy": 31.5,
        },
        "initial_pose": {"t": [0.0, 0.0, 14.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
    }
    request.update(changes)
    return request


def submit(
    client: TestClient,
    request: dict[str, Any] | str | None = None,
    image: bytes | None = None,
    headers: dict[str, str] | None = None,
) -> Any:
    request = base_request() if request is None else request
    files = {"image": ("ref.png", png() if image is None else image, "image/png")}
    text = request if isinstance(request, str) else json.dumps(request)
    return client.post("/v1/estimates", files=files, data={"request": text}, headers=headers)


def queued(r: redis.Redis) -> int:
    """Jobs waiting in either queue, plus job records: what a rejected request must not add."""
    waiting = sum(
        Queue(name, connection=r).count for name in (KEYS.estimate_queue, KEYS.render_queue)
    )
    return waiting + int(r.zcard(KEYS.jobs_index))  # type: ignore[arg-type]


def assert_field_error(response: Any, status: int, loc: tuple[str | int, ...]) -> dict[str, Any]:
    assert response.status_code == status, response.text
    assert "Traceback" not in response.text
    body = assert_problem(response, status)
    errors = body["errors"]
    assert isinstance(errors, list) and errors, body
    locs = [tuple(e["loc"]) for e in errors]
    hit = [e for e in errors if tuple(e["loc"][: len(loc)]) == loc]
    assert hit, f"no error at {loc}; got {locs}"
    assert all(e["msg"] and e["type"] for e in errors)
    return hit[0]  # type: ignore[no-any-return]


def assert_problem(response: Any, status: int, code: str | None = None) -> dict[str, Any]:
    """``response`` is RFC 9457 problem details with ``status`` (and ``code``); its body."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json"), response.headers
    body = response.json()
    assert body["status"] == status and body["type"].startswith("urn:proxpose:problem:"), body
    assert body["title"] and isinstance(body["detail"], str) and body["detail"], body
    assert body["type"] == "urn:proxpose:problem:" + body["code"], body
    if code is not None:
        assert body["code"] == code, body
    return body  # type: ignore[no-any-return]


def response_model_bytes(
    router: APIRouter, endpoint: Callable[..., Any], resource: BaseModel
) -> bytes:
    """What FastAPI's pass over ``endpoint``'s 202 response_model makes of ``resource`` (the
    bytes a route answering through ``submissions.accepted`` must give)."""
    route = next(rt for rt in router.routes if isinstance(rt, APIRoute) and rt.endpoint is endpoint)
    assert route.response_field is not None and route.status_code == 202
    value, errors = route.response_field.validate(resource, {}, loc=("response",))
    assert not errors
    return route.response_field.serialize_json(value, by_alias=True)
