"""Access control against a real Redis (no workers): API keys, isolation between keys, admin
keys, rate limits and caps (429 + Retry-After), the browser cookie and its CSRF check, security
headers on HTML, CORS off unless configured, unguessable job ids.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from typing import Any

import pytest
import redis
from conftest import settings_on_redis
from fastapi.testclient import TestClient
from PIL import Image
from rq import Queue

from schemas.settings import Settings, get_settings
from service.auth import identify
from service.main import create_app
from service.store import Keys

#: Redis database of this module.
DB = 4
KEYS = Keys("proxpose")
ALICE, BOB, OPS = (
    "alice-key-0123456789abcdef",
    "bob-key-0123456789abcdef",
    "ops-key-0123456789abcdef",
)
SIDE_PX = 64
CUBE_OBJ = (
    "".join(f"v {i & 1} {i >> 1 & 1} {i >> 2 & 1}\n" for i in range(8))
    + "f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\n"
    + "f 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\nf 2 4 6\nf 4 8 6\n"
).encode()


def bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture
def r(redis_server: Any, tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> Iterator[redis.Redis]:
    keys = {
        "PROXPOSE_API_KEYS": f"alice:{ALICE}, bob:{BOB}",
        "PROXPOSE_ADMIN_API_KEYS": f"ops:{OPS}",
    }
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch, keys) as client:
        yield client


@pytest.fixture
def client(r: redis.Redis) -> Iterator[TestClient]:
    with TestClient(create_app(), follow_redirects=False) as c:
        yield c


def png() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (SIDE_PX, SIDE_PX), (90, 90, 90)).save(buf, format="PNG")
    return buf.getvalue()


def request_json(**changes: Any) -> str:
    request = {
        "model_id": "demo-sat",
        "camera": {"width": 64, "height": 64, "fx": 70.0, "fy": 70.0, "cx": 31.5, "cy": 31.5},
        "initial_pose": {"t": [0.0, 0.0, 14.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
    }
    return json.dumps(request | changes)


def submit(client: TestClient, key: str | None, **kwargs: Any) -> Any:
    headers = bearer(key) if key else {}
    headers |= kwargs.pop("headers", {})
    files = {"image": ("ref.png", png(), "image/png")}
    data = {"request": kwargs.pop("request", request_json())}
    return client.post("/v1/estimates", files=files, data=data, headers=headers, **kwargs)


def enqueued(r: redis.Redis) -> int:
    return Queue(KEYS.estimate_queue, connection=r).count


# ----------------------------------------------------------------------------- keys
@pytest.mark.parametrize(
    "method, path",
    [
        ("GET", "/v1/estimates"),
        ("POST", "/v1/estimates"),
        ("GET", "/v1/estimates/0123456789abcdef0123456789abcdef"),
        ("DELETE", "/v1/estimates/0123456789abcdef0123456789abcdef"),
        ("GET", "/v1/estimates/0123456789abcdef0123456789abcdef/events"),
        ("GET", "/v1/models"),
        ("POST", "/v1/models"),
        ("DELETE", "/v1/models/0123456789abcdef"),
        ("POST", "/v1/renders"),
        ("GET", "/v1/anything-else"),
        ("GET", "/models/demo-sat/request.json"),
    ],
)
def test_every_v1_route_needs_a_key(
    client: TestClient, r: redis.Redis, method: str, path: str
) -> None:
    for headers in ({}, bearer("not-the-key-0123456789"), {"Authorization": f"Basic {ALICE}"}):
        response = client.request(method, path, headers=headers)
        assert response.status_code == 401, (headers, response.text)
        assert response.headers["www-authenticate"].startswith("Bearer")
        assert "Bearer" in response.json()["detail"]
    assert enqueued(r) == 0


def test_probes_docs_and_static_files_stay_open(client: TestClient) -> None:
    for path in ("/healthz", "/readyz", "/metrics", "/openapi.json", "/docs", "/session"):
        assert client.get(path).status_code == 200, path
    assert client.get("/static/api.js").status_code == 200


def test_pages_need_a_key_and_a_browser_is_sent_to_the_key_form(client: TestClient) -> None:
    for path in ("/", "/models", "/estimates/0123456789abcdef0123456789abcdef"):
        navigation = client.get(path, headers={"accept": "text/html"})
        assert navigation.status_code == 303
        assert navigation.headers["location"] == f"/session?next={path}"
        assert client.get(path).status_code == 401  # not a browser: a plain 401
        assert client.get(path, headers=bearer(ALICE)).status_code in (200, 404)


def test_scheme_is_case_insensitive_and_keys_are_exact(client: TestClient) -> None:
    assert (
        client.get("/v1/models", headers={"Authorization": f"bearer  {ALICE}"}).status_code == 200
    )
    assert client.get("/v1/models", headers=bearer(ALICE[:-1])).status_code == 401
    assert client.get("/v1/models", headers=bearer(ALICE + "x")).status_code == 401
    assert client.get("/v1/models", headers=bearer(ALICE.upper())).status_code == 401


def test_identify_checks_every_key_and_names_the_principal() -> None:
    settings = Settings(api_keys={"alice": ALICE}, admin_api_keys={"ops": OPS})
    assert identify(settings, ALICE) is not None and identify(settings, ALICE).name == "alice"  # type: ignore[union-attr]
    ops = identify(settings, OPS)
    assert ops is not None and ops.admin
    assert identify(settings, "") is None and identify(settings, "x" * 10_000) is None


def test_settings_refuse_weak_or_shared_keys_without_echoing_them() -> None:
    with pytest.raises(ValueError) as weak:
        Settings(api_keys="alice:short-key")  # type: ignore[arg-type]
    assert "short-key" not in str(weak.value)
    with pytest.raises(ValueError, match="twice"):
        Settings(api_keys={"a": ALICE}, admin_api_keys={"b": ALICE})
    assert ALICE not in repr(Settings(api_keys={"alice": ALICE}))


# ----------------------------------------------------------------------------- isolation
def test_a_key_sees_only_its_own_jobs_and_an_admin_sees_all(
    client: TestClient, r: redis.Redis
) -> None:
    mine = submit(client, ALICE).json()["id"]
    theirs = submit(client, BOB).json()["id"]
    for job_id, owner, stranger in ((mine, ALICE, BOB), (theirs, BOB, ALICE)):
        assert client.get(f"/v1/estimates/{job_id}", headers=bearer(owner)).status_code == 200
        for method, suffix in (
            ("GET", ""),
            ("DELETE", ""),
            ("GET", "/events"),
            ("GET", "/artifacts/difference"),
        ):
            response = client.request(
                method, f"/v1/estimates/{job_id}{suffix}", headers=bearer(stranger)
            )
            assert response.status_code == 404, (method, suffix, response.text)
        assert client.get(f"/v1/estimates/{job_id}", headers=bearer(OPS)).status_code == 200

    def listing(key: str) -> list[str]:
        page = client.get("/v1/estimates", headers=bearer(key)).json()
        return [job["id"] for job in page["items"]]

    assert listing(ALICE) == [mine] and listing(BOB) == [theirs]
    assert listing(OPS) == [theirs, mine]
    assert client.delete(f"/v1/estimates/{mine}", headers=bearer(BOB)).status_code == 404
    assert client.get(f"/v1/estimates/{mine}", headers=bearer(ALICE)).json()["status"] == "queued"
    assert client.delete(f"/v1/estimates/{mine}", headers=bearer(OPS)).status_code == 200


def test_idempotency_keys_are_per_api_key(client: TestClient) -> None:
    header = {"Idempotency-Key": "same-key-for-both"}
    a = submit(client, ALICE, headers=header).json()["id"]
    b = submit(client, BOB, headers=header).json()["id"]
    assert a != b
    assert submit(client, ALICE, headers=header).json()["id"] == a


def test_models_are_private_to_their_owners(client: TestClient, r: redis.Redis) -> None:
    def upload(key: str, name: str) -> Any:
        files = {"file": ("cube.obj", CUBE_OBJ)}
        return client.post("/v1/models", files=files, data={"name": name}, headers=bearer(key))

    first = upload(ALICE, "alice's cube")
    assert first.status_code == 201
    model_id = first.json()["id"]
    assert client.get(f"/v1/models/{model_id}", headers=bearer(BOB)).status_code == 404
    assert client.get("/v1/models", headers=bearer(BOB)).json()["items"] == []
    bob_request = request_json(model_id=model_id)
    refused = submit(client, BOB, request=bob_request)
    assert refused.status_code == 422 and refused.json()["errors"][0]["type"] == "model_not_found"
    # the same bytes from bob: his own registration under his name, nothing revealed
    second = upload(BOB, "bob's cube")
    assert second.status_code == 201 and second.json()["id"] == model_id
    assert second.json()["name"] == "bob's cube"
    assert upload(BOB, "again").status_code == 200
    assert (
        client.get(f"/v1/models/{model_id}", headers=bearer(ALICE)).json()["name"] == "alice's cube"
    )
    assert submit(client, BOB, request=bob_request).status_code == 202
    # alice lets go: bob keeps it; bob lets go: it is gone
    assert client.delete(f"/v1/models/{model_id}", headers=bearer(ALICE)).status_code == 204
    assert client.get(f"/v1/models/{model_id}", headers=bearer(ALICE)).status_code == 404
    assert client.get(f"/v1/models/{model_id}", headers=bearer(BOB)).status_code == 200
    assert [m["id"] for m in client.get("/v1/models", headers=bearer(OPS)).json()["items"]] == [
        model_id
    ]
    assert client.delete(f"/v1/models/{model_id}", headers=bearer(BOB)).status_code == 204
    assert not r.exists(KEYS.model_data(model_id))


def test_model_quota_per_key(client: TestClient, r: redis.Redis, monkeypatch: Any) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_MODELS_PER_KEY", "1")
    get_settings.cache_clear()
    cube = {"file": ("cube.obj", CUBE_OBJ)}
    other = {"file": ("cube2.obj", CUBE_OBJ.replace(b"v 1 1 1", b"v 2 2 2"))}
    assert client.post("/v1/models", files=cube, headers=bearer(ALICE)).status_code == 201
    refused = client.post("/v1/models", files=other, headers=bearer(ALICE))
    assert refused.status_code == 403 and "max_models_per_key" in refused.json()["detail"]
    assert client.post("/v1/models", files=other, headers=bearer(BOB)).status_code == 201


# ----------------------------------------------------------------------------- limits
def test_submissions_over_the_rate_are_429_with_retry_after(
    client: TestClient, r: redis.Redis, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PROXPOSE_SUBMISSIONS_PER_MINUTE", "6")  # one per 10 s
    monkeypatch.setenv("PROXPOSE_SUBMISSION_BURST", "3")
    get_settings.cache_clear()
    assert [submit(client, ALICE).status_code for _ in range(3)] == [202, 202, 202]
    for attempt in (submit(client, ALICE), client.post("/v1/models", headers=bearer(ALICE))):
        assert attempt.status_code == 429, attempt.text
        assert 1 <= int(attempt.headers["retry-after"]) <= 10
        assert "per minute" in attempt.json()["detail"]
    assert enqueued(r) == 3
    assert submit(client, BOB).status_code == 202  # another key has its own budget
    assert client.get("/v1/estimates", headers=bearer(ALICE)).status_code == 200  # reads are free


def test_active_jobs_cap_is_429_until_one_ends(
    client: TestClient, r: redis.Redis, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_ACTIVE_JOBS_PER_KEY", "2")
    get_settings.cache_clear()
    first, _ = (submit(client, ALICE).json()["id"] for _ in range(2))
    refused = submit(client, ALICE, headers={"Idempotency-Key": "capped"})
    assert refused.status_code == 429 and int(refused.headers["retry-after"]) >= 1
    assert "max_active_jobs_per_key" in refused.json()["detail"]
    assert enqueued(r) == 2
    assert submit(client, BOB).status_code == 202
    assert client.delete(f"/v1/estimates/{first}", headers=bearer(ALICE)).status_code == 200
    again = submit(client, ALICE, headers={"Idempotency-Key": "capped"})  # the key was released
    assert again.status_code == 202, again.text


def test_job_ids_are_random_128_bit_hex(client: TestClient) -> None:
    ids = {submit(client, ALICE).json()["id"] for _ in range(20)}
    assert len(ids) == 20 and all(len(i) == 32 and int(i, 16) >= 0 for i in ids)


# ----------------------------------------------------------------------------- browsers
def test_session_cookie_signs_a_browser_in(client: TestClient, r: redis.Redis) -> None:
    wrong = client.post("/session", data={"api_key": "wrong-key-0123456789", "next": "/"})
    assert wrong.status_code == 401 and "not valid" in wrong.text
    signed = client.post("/session", data={"api_key": ALICE, "next": "/models"})
    assert signed.status_code == 303 and signed.headers["location"] == "/models"
    cookie = signed.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie.replace("Strict", "strict")
    assert client.get("/models").status_code == 200  # the client keeps the cookie
    assert client.get("/v1/models").status_code == 200
    same_site = {"origin": "http://testserver"}
    assert submit(client, None, headers=same_site).status_code == 202
    cross_site = submit(client, None, headers={"origin": "https://evil.example"})
    assert cross_site.status_code == 403
    assert enqueued(r) == 1
    client.post("/session/logout")
    assert client.get("/v1/models").status_code == 401


def test_session_never_redirects_off_site(client: TestClient) -> None:
    for target in ("https://evil.example/", "//evil.example/", "/\\evil.example"):
        response = client.post("/session", data={"api_key": ALICE, "next": target})
        assert response.headers["location"] == "/"


def test_html_gets_security_headers_and_json_gets_nosniff(client: TestClient) -> None:
    page = client.get("/", headers=bearer(ALICE))
    assert page.headers["content-type"].startswith("text/html")
    csp = page.headers["content-security-policy"]
    script_src = next(d for d in csp.split(";") if d.strip().startswith("script-src"))
    assert "'unsafe-inline'" not in script_src and "'self'" in script_src
    assert "frame-ancestors 'none'" in csp
    assert page.headers["x-frame-options"] == "DENY"
    assert page.headers["x-content-type-options"] == "nosniff"
    assert page.headers["referrer-policy"] == "no-referrer"
    form = client.get("/session")
    assert "content-security-policy" in form.headers
    docs = client.get("/docs")  # public; its route sets a policy of its own, kept alone
    policies = docs.headers.get_list("content-security-policy")
    assert len(policies) == 1 and "http" not in policies[0].split("script-src")[1]
    assert docs.headers["x-frame-options"] == "DENY"
    api = client.get("/v1/models", headers=bearer(ALICE))
    assert api.headers["x-content-type-options"] == "nosniff"
    assert "content-security-policy" not in api.headers


def test_cors_is_off_unless_origins_are_configured(client: TestClient, monkeypatch: Any) -> None:
    preflight = {
        "origin": "https://tools.example",
        "access-control-request-method": "POST",
        "access-control-request-headers": "authorization",
    }
    answer = client.options("/v1/estimates", headers=preflight)
    assert "access-control-allow-origin" not in answer.headers
    simple = client.get("/v1/models", headers={**bearer(ALICE), "origin": "https://tools.example"})
    assert "access-control-allow-origin" not in simple.headers
    monkeypatch.setenv("PROXPOSE_CORS_ORIGINS", "https://tools.example")
    get_settings.cache_clear()
    answer = client.options("/v1/estimates", headers=preflight)
    assert answer.status_code == 200
    assert answer.headers["access-control-allow-origin"] == "https://tools.example"
    other = client.options("/v1/estimates", headers={**preflight, "origin": "https://evil.example"})
    assert other.headers.get("access-control-allow-origin") != "https://evil.example"
