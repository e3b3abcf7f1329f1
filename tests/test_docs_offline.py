"""``/docs`` offline: Swagger UI from the vendored ``service/static/swagger/`` files, never a CDN.

Without a browser: the page references only local assets, carries a CSP allowing exactly its one
inline script (by hash), the assets are served with the right types, the docs stay public with
API keys configured, and ``/redoc`` points to ``/docs``. In headless Chromium (marked
``browser``; skipped without Chromium unless PROXPOSE_REQUIRE_BROWSER=1): the page renders
every operation of the OpenAPI document, with no console error and no request leaving the
service.
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest
import redis
from conftest import free_port, settings_on_redis, start_api
from fastapi.testclient import TestClient

from schemas.settings import get_settings
from service.main import create_app
from service.routes.docs import SWAGGER_CSS_URL, SWAGGER_FAVICON_URL, SWAGGER_JS_URL
from service.routes.pages import STATIC_DIR

#: Redis database of this module (the session's Redis is shared with other modules).
DB = 7
SWAGGER_DIR = STATIC_DIR / "swagger"
ASSET_TYPES = {
    SWAGGER_JS_URL: "text/javascript",
    SWAGGER_CSS_URL: "text/css",
    SWAGGER_FAVICON_URL: "image/png",
}
CHROMIUM = Path(os.environ.get("PROXPOSE_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]
HTTP_METHODS = ("get", "put", "post", "delete", "options", "head", "patch", "trace")


@pytest.fixture
def r(redis_server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[redis.Redis]:
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch) as client:
        yield client


@pytest.fixture
def client(r: redis.Redis) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c


def references(html: str) -> list[str]:
    """Every URL the page's markup loads (src and href attributes)."""
    return re.findall(r'\b(?:src|href)="([^"]*)"', html)


def inline_scripts(html: str) -> list[str]:
    return re.findall(r"<script>(.*?)</script>", html, re.DOTALL)


def sha256_source(script: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(script.encode()).digest()).decode() + "'"


def test_docs_page_references_only_local_assets(client: TestClient) -> None:
    response = client.get("/docs")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    html = response.text
    urls = references(html)
    assert sorted(urls) == sorted([SWAGGER_JS_URL, SWAGGER_CSS_URL, SWAGGER_FAVICON_URL])
    assert all(u.startswith("/static/swagger/") for u in urls)
    assert "cdn" not in html.lower() and "http://" not in html and "https://" not in html
    assert "url: '/openapi.json'" in html
    assert '"validatorUrl": null' in html  # no call to validator.swagger.io
    assert client.head("/docs").status_code == 200


def test_docs_csp_allows_exactly_its_inline_script(client: TestClient) -> None:
    response = client.get("/docs")
    scripts = inline_scripts(response.text)
    assert len(scripts) == 1
    policies = response.headers.get_list("content-security-policy")
    own = [p for p in policies if sha256_source(scripts[0]) in p]
    assert len(own) == 1, policies  # the page's own policy, beside the middleware's
    directives = dict(d.strip().split(" ", 1) for d in own[0].split(";"))
    assert directives["script-src"] == f"'self' {sha256_source(scripts[0])}"
    assert directives["default-src"] == "'none'" and directives["connect-src"] == "'self'"
    assert "unsafe-inline" not in directives["script-src"] and "http" not in own[0]
    assert response.headers["x-frame-options"] == "DENY"


@pytest.mark.parametrize("url", list(ASSET_TYPES))
def test_swagger_assets_are_served(client: TestClient, url: str) -> None:
    response = client.get(url)
    assert response.status_code == 200
    assert response.headers["content-type"].startswith(ASSET_TYPES[url])
    assert response.content == (STATIC_DIR / url.removeprefix("/static/")).read_bytes()


def test_vendored_version_and_license_are_recorded() -> None:
    notes = (SWAGGER_DIR / "README.md").read_text()
    assert re.search(r"`swagger-ui-dist`.*\*\*5\.\d+\.\d+\*\*", notes)
    assert "Apache License" in (SWAGGER_DIR / "LICENSE").read_text()
    for name in ("swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png"):
        digest = hashlib.sha256((SWAGGER_DIR / name).read_bytes()).hexdigest()
        assert f"| `{name}` | `{digest}` |" in notes, f"{name} differs from the recorded file"


def test_redoc_points_to_docs_and_openapi_is_served(client: TestClient) -> None:
    response = client.get("/redoc", follow_redirects=False)
    assert response.status_code == 307 and response.headers["location"] == "/docs"
    assert client.get("/openapi.json").status_code == 200


def test_docs_stay_public_with_api_keys(r: redis.Redis, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PROXPOSE_API_KEYS", "alice:docs-test-key-0123456789")
    get_settings.cache_clear()
    with TestClient(create_app()) as c:
        assert c.get("/v1/estimates").status_code == 401
        for url in ("/docs", "/openapi.json", *ASSET_TYPES):
            assert c.get(url).status_code == 200, url


# ----------------------------------------------------------------------------- in Chromium
@pytest.fixture
def api_url(redis_server: Any, tmp_path: Path) -> Iterator[str]:
    """A real uvicorn of the app (no worker: the docs need none)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PROXPOSE_")}
    env |= {"PROXPOSE_REDIS_URL": redis_server.url(DB), "PROXPOSE_DATA_DIR": str(tmp_path)}
    port = free_port()
    proc = start_api(env, tmp_path / "api.log", port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@pytest.mark.browser
def test_swagger_ui_renders_every_operation_offline(api_url: str) -> None:
    if not CHROMIUM.is_file():
        if os.environ.get("PROXPOSE_REQUIRE_BROWSER") == "1":
            pytest.fail(f"PROXPOSE_REQUIRE_BROWSER=1 but {CHROMIUM} is missing")
        pytest.skip(f"{CHROMIUM} is missing")
    from playwright.sync_api import sync_playwright

    spec = httpx.get(f"{api_url}/openapi.json").json()
    operations = sum(m in item for item in spec["paths"].values() for m in HTTP_METHODS)
    problems: list[str] = []
    elsewhere: list[str] = []
    origin = urlsplit(api_url).netloc
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page()
            page.on(
                "console",
                lambda m: m.type in ("error", "warning") and problems.append(f"{m.type}: {m.text}"),
            )
            page.on("pageerror", lambda e: problems.append(f"uncaught: {e}"))

            def only_local(route: Any) -> None:
                if urlsplit(route.request.url).netloc == origin:
                    route.continue_()
                else:  # this machine is offline: a request elsewhere would hang or fail
                    elsewhere.append(route.request.url)
                    route.abort()

            page.route("**/*", only_local)
            page.goto(f"{api_url}/docs")
            page.wait_for_selector(".opblock", timeout=30_000)
            rendered = page.locator(".opblock").count()
            title = page.locator(".info .title").inner_text()
            page.locator(".opblock-summary").first.click()  # expands: React renders details
            page.wait_for_selector(".opblock-body", timeout=10_000)
        finally:
            browser.close()
    assert rendered == operations
    assert title.startswith(spec["info"]["title"])
    assert elsewhere == []
    assert problems == []
