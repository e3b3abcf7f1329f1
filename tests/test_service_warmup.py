"""What the API readies as it starts, so that the first burst of submissions does not pay for
it: its Redis connections (real Redis, CLIENT LIST), PIL's image readers and FastAPI's routes;
and that it still starts, answering 503, when Redis is away."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import redis
from conftest import REPO, free_port, settings_on_redis
from fastapi.testclient import TestClient

from schemas.settings import get_settings
from service.main import API_CLIENT_NAME, WARM_CONNECTIONS, create_app

DB = 14


def api_connections(r: redis.Redis) -> int:
    return sum(1 for c in r.client_list() if c["name"] == API_CLIENT_NAME and c["db"] == str(DB))


def test_the_api_opens_its_redis_connections_as_it_starts(
    redis_server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch) as r:
        assert api_connections(r) == 0
        with TestClient(create_app()) as client:
            # the sync client's pool and the async client's, before any request
            assert api_connections(r) >= 2 * WARM_CONNECTIONS
            assert client.get("/readyz").status_code in (200, 503)  # no worker: 503 is fine
        assert api_connections(r) < WARM_CONNECTIONS  # closed with the app


def test_the_api_starts_without_redis_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("PROXPOSE_REDIS_URL", f"redis://127.0.0.1:{free_port()}/0")
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    try:
        with caplog.at_level(logging.WARNING, "service.main"):
            with TestClient(create_app()) as client:
                down = client.get("/readyz")
        assert down.status_code == 503
        assert any("not opened in advance" in m for m in caplog.messages), caplog.messages
    finally:
        get_settings.cache_clear()


def test_image_readers_load_without_scanning_every_pil_plugin() -> None:
    """In a fresh interpreter: PNG, JPEG and TIFF are registered and PIL's full plugin scan
    (Image.init, ~35 ms) has not run, so no upload sets it off either."""
    probe = (
        "from PIL import Image; from service.uploads import IMAGE_FORMATS, load_image_codecs; "
        "load_image_codecs(); "
        "assert all(f in Image.OPEN for f in IMAGE_FORMATS), Image.OPEN.keys(); "
        "assert Image._initialized == 1, Image._initialized; print('ok')"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert out.stdout.strip() == "ok", out.stderr


def test_fastapi_builds_the_routes_as_the_api_starts(
    redis_server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """FastAPI builds a route's dependencies and validators when a request first looks at it
    (~23 ms for all of ours); the API does it as it starts (service.main.warm_routes), so the
    first submission does not build anything."""
    import fastapi.routing

    built: list[str] = []
    real = fastapi.routing.get_dependant

    def counting(*args: Any, **kwargs: Any) -> Any:
        built.append(str(kwargs.get("path")))
        return real(*args, **kwargs)

    monkeypatch.setattr(fastapi.routing, "get_dependant", counting)
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch):
        with TestClient(create_app()) as client:
            at_start = len(built)
            assert "/v1/estimates" in built and "/v1/tracks/{job_id}" in built, built
            assert client.get("/v1/estimates/0").status_code == 404
            files = {"image": ("a.png", b"not a png", "image/png")}
            assert client.post("/v1/estimates", files=files).status_code == 422
            assert len(built) == at_start, built[at_start:]
