"""HTTP tests of the API against a real Redis, without workers (nothing here renders).

Covers the validation battery (every bad request answered 4xx naming the field, nothing
enqueued), job submission, idempotency, listing and paging, cancelling queued jobs, models,
limits, probes and metrics. The end-to-end tests with workers are in test_service_e2e.py.
"""

from __future__ import annotations

import copy
import io
import json
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from PIL import Image
from rq import Queue, Worker

from schemas.models import ModelPublic
from schemas.settings import get_settings
from service.main import create_app
from service.store import JobStore, Keys, Leases, ModelStore, Reaper

#: Redis database of this module (the session's Redis is shared with other modules).
DB = 1
KEYS = Keys("proxpose")
SIDE_PX = 64
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


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture
def r(redis_server: Any, tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> Iterator[redis.Redis]:
    """Settings pointing at this module's Redis database, emptied before and after."""
    url = redis_server.url(DB)
    monkeypatch.setenv("PROXPOSE_REDIS_URL", url)
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(tmp_path))
    get_settings.cache_clear()
    client = redis.Redis.from_url(url)
    client.flushdb()
    yield client
    client.flushdb()
    get_settings.cache_clear()


@pytest.fixture
def client(r: redis.Redis) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c


def png(width: int = SIDE_PX, height: int = SIDE_PX) -> bytes:
    img = Image.new("RGB", (width, height))
    img.paste((200, 180, 40), (width // 4, height // 4, width // 2, height // 2))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


def png_header_only(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width``×``height`` (the pixel data would not match)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


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
    detail = response.json()["detail"]
    assert isinstance(detail, list), detail
    locs = [tuple(e["loc"]) for e in detail]
    hit = [e for e in detail if tuple(e["loc"][: len(loc)]) == loc]
    assert hit, f"no error at {loc}; got {locs}"
    assert all(e["msg"] for e in detail)
    return hit[0]  # type: ignore[no-any-return]


# ----------------------------------------------------------------------------- the battery
def edit(path: str, value: Any = ..., drop: bool = False) -> Callable[[dict[str, Any]], Any]:
    """A change to the valid request: set (or drop) the field at a dotted path."""

    def apply(request: dict[str, Any]) -> dict[str, Any]:
        out = copy.deepcopy(request)
        *parents, last = path.split(".")
        node = out
        for p in parents:
            node = node[p]
        if drop:
            del node[last]
        else:
            node[last] = value
        return out

    return apply


@dataclass(frozen=True)
class Bad:
    """A bad POST /v1/estimates: how it differs from a valid one, and the expected answer."""

    loc: tuple[str | int, ...]
    request: Callable[[dict[str, Any]], Any] = lambda req: req  # None: omit the field
    image: Callable[[bytes], bytes | None] = lambda img: img  # None: omit the file
    headers: dict[str, str] = field(default_factory=dict)
    status: int = 422
    type_: str | None = None


REQ = ("body", "request")
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
BAD_ESTIMATES = {
    "image missing": Bad(("body", "image"), image=lambda _: None),
    "request missing": Bad(REQ, request=lambda _: None),
    "request not JSON": Bad(REQ, request=lambda _: "{not json", type_="json_invalid"),
    "request is a list": Bad(REQ, request=lambda _: "[]"),
    "request file not UTF-8": Bad(REQ, request=lambda _: b"\xff\xfe{}", type_="unicode_error"),
    "camera missing": Bad((*REQ, "camera"), request=edit("camera", drop=True)),
    "camera width 0": Bad((*REQ, "camera", "width"), request=edit("camera.width", 0)),
    "camera fx negative": Bad((*REQ, "camera", "fx"), request=edit("camera.fx", -5.0)),
    "camera cx far outside": Bad((*REQ, "camera"), request=edit("camera.cx", 1000.0)),
    "unknown top-level field": Bad((*REQ, "optons"), request=edit("optons", {})),
    "two attitudes": Bad((*REQ, "initial_pose"), request=edit("initial_pose.q", [0, 0, 0])),
    "target behind camera": Bad((*REQ, "initial_pose"), request=edit("initial_pose.t", [0, 0, -5])),
    "quaternion not unit": Bad(
        (*REQ, "initial_pose"), request=edit("initial_pose.quaternion", [1, 1, 0, 0])
    ),
    "t with 2 components": Bad((*REQ, "initial_pose", "t"), request=edit("initial_pose.t", [0, 1])),
    "t not finite": Bad(
        (*REQ, "initial_pose", "t", 2), request=edit("initial_pose.t", [0, 0, float("inf")])
    ),
    "max_iterations 0": Bad(
        (*REQ, "options", "max_iterations"), request=edit("options", {"max_iterations": 0})
    ),
    "unknown method": Bad((*REQ, "options", "method"), request=edit("options", {"method": "x"})),
    "sun not a unit vector": Bad(
        (*REQ, "lighting", "sun_direction"), request=edit("lighting", {"sun_direction": [0, 0, 2]})
    ),
    "ground_truth not a pose": Bad((*REQ, "ground_truth"), request=edit("ground_truth", "yes")),
    "model_id missing": Bad((*REQ, "model_id"), request=edit("model_id", drop=True)),
    "model_id malformed": Bad((*REQ, "model_id"), request=edit("model_id", "../../etc/passwd")),
    "model unknown": Bad(
        (*REQ, "model_id"), request=edit("model_id", "0123456789abcdef"), type_="model_not_found"
    ),
    "image is text": Bad(("body", "image"), image=lambda _: b"hello", type_="invalid_image"),
    "image empty": Bad(("body", "image"), image=lambda _: b"", type_="invalid_image"),
    "image is a GIF": Bad(("body", "image"), image=lambda _: b"GIF89a" + b"\0" * 64),
    "image truncated": Bad(("body", "image"), image=lambda img: img[:70], type_="invalid_image"),
    "image size differs from camera": Bad(
        ("body", "image"), image=lambda _: png(32, 48), type_="image_size_mismatch"
    ),
    "image header claims 5000x5000": Bad(
        ("body", "image"), image=lambda _: png_header_only(5000, 5000), type_="image_too_large"
    ),
    "Idempotency-Key with spaces": Bad(
        ("header", "Idempotency-Key"), headers={"Idempotency-Key": "not a key"}
    ),
    # non-finite, zero and degenerate numbers
    "camera fx NaN": Bad((*REQ, "camera", "fx"), request=edit("camera.fx", float("nan"))),
    "camera fx zero": Bad((*REQ, "camera", "fx"), request=edit("camera.fx", 0.0)),
    "camera cy infinite": Bad((*REQ, "camera", "cy"), request=edit("camera.cy", float("-inf"))),
    "camera fx 1e400 (inf)": Bad(
        (*REQ, "camera", "fx"), request=lambda r: json.dumps(r).replace("70.0", "1e400", 1)
    ),
    "camera width 10^40": Bad((*REQ, "camera", "width"), request=edit("camera.width", 10**40)),
    "camera width a string": Bad((*REQ, "camera", "width"), request=edit("camera.width", "wide")),
    "camera unknown field": Bad((*REQ, "camera", "k1"), request=edit("camera.k1", 0.1)),
    "t NaN": Bad(
        (*REQ, "initial_pose", "t", 0), request=edit("initial_pose.t", [float("nan"), 0, 14])
    ),
    "t on the image plane": Bad((*REQ, "initial_pose"), request=edit("initial_pose.t", [0, 0, 0])),
    "quaternion zero": Bad(
        (*REQ, "initial_pose"), request=edit("initial_pose.quaternion", [0, 0, 0, 0])
    ),
    "no attitude": Bad((*REQ, "initial_pose"), request=edit("initial_pose.quaternion", drop=True)),
    "R not orthonormal": Bad(
        (*REQ, "initial_pose"),
        request=lambda r: edit(
            "initial_pose", {"t": [0, 0, 14], "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}
        )(r),
    ),
    "R a reflection": Bad(
        (*REQ, "initial_pose"),
        request=lambda r: edit(
            "initial_pose", {"t": [0, 0, 14], "R": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]}
        )(r),
    ),
    "sun direction zero": Bad(
        (*REQ, "lighting", "sun_direction"), request=edit("lighting", {"sun_direction": [0, 0, 0]})
    ),
    "sun irradiance negative": Bad(
        (*REQ, "lighting", "sun_irradiance"), request=edit("lighting", {"sun_irradiance": -1.0})
    ),
    "ground truth behind camera": Bad(
        (*REQ, "ground_truth"),
        request=edit("ground_truth", {"t": [0, 0, -3], "quaternion": [1, 0, 0, 0]}),
    ),
    # options out of range
    "spp 0": Bad((*REQ, "options", "spp"), request=edit("options", {"spp": 0})),
    "n_samples 10000": Bad(
        (*REQ, "options", "n_samples"), request=edit("options", {"n_samples": 10**4})
    ),
    "epsilon negative": Bad((*REQ, "options", "epsilon"), request=edit("options", {"epsilon": -1})),
    "unknown option": Bad((*REQ, "options", "turbo"), request=edit("options", {"turbo": True})),
    # malformed JSON and sizes
    "request JSON nested 5000 deep": Bad(REQ, request=lambda _: '{"a":' * 5000 + "1" + "}" * 5000),
    "request is null": Bad(REQ, request=lambda _: "null"),
    "request file over 1 MiB": Bad(
        REQ, request=lambda r: json.dumps({**r, "pad": "x" * 1_100_000}).encode(), status=413
    ),
    "request field over 1 MiB": Bad(
        ("body",), request=lambda r: json.dumps({**r, "pad": "x" * 1_100_000}), status=413
    ),
    # images
    "image is a JSON file": Bad(("body", "image"), image=lambda _: b'{"not": "an image"}'),
    "image bytes flipped": Bad(
        ("body", "image"), image=lambda img: img[:40] + bytes(b ^ 0xFF for b in img[40:])
    ),
    "image 1 px": Bad(("body", "image"), image=lambda _: png(1, 1), type_="image_size_mismatch"),
    "image header claims 2^31 px wide": Bad(
        ("body", "image"), image=lambda _: png_header_only(2**31 - 1, 8), type_="image_too_large"
    ),
}


@pytest.mark.parametrize("case", BAD_ESTIMATES.values(), ids=BAD_ESTIMATES.keys())
def test_bad_estimate_requests_are_rejected_and_nothing_is_enqueued(
    client: TestClient, r: redis.Redis, case: Bad
) -> None:
    request = case.request(base_request())
    image = case.image(png())
    files: dict[str, Any] = {} if image is None else {"image": ("ref.png", image, "image/png")}
    data = {}
    if isinstance(request, bytes):  # a file part, as curl -F request=@request.json sends it
        files["request"] = ("request.json", request, "application/json")
    elif request is not None:
        data["request"] = request if isinstance(request, str) else json.dumps(request)
    response = client.post("/v1/estimates", files=files or None, data=data, headers=case.headers)
    error = assert_field_error(response, case.status, case.loc)
    if case.type_ is not None:
        assert error["type"] == case.type_, error
    assert queued(r) == 0


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
        {"data": {"name": "x"}},
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


@pytest.mark.parametrize(
    "method, path",
    [
        ("GET", "/v1/estimates/0123456789abcdef0123456789abcdef"),
        ("GET", "/v1/estimates/not-a-job"),
        ("GET", "/v1/estimates/a:b:c"),
        ("DELETE", "/v1/estimates/0123456789abcdef0123456789abcdef"),
        ("GET", "/v1/estimates/0123456789abcdef0123456789abcdef/events"),
        ("GET", "/v1/estimates/0123456789abcdef0123456789abcdef/artifacts/difference"),
        ("GET", "/v1/models/0123456789abcdef"),
        ("GET", "/v1/models/demo-sat"),
        ("DELETE", "/v1/models/0123456789abcdef"),
        ("GET", "/v1/nothing-here"),
    ],
)
def test_unknown_ids_are_404(client: TestClient, method: str, path: str) -> None:
    response = client.request(method, path)
    assert response.status_code == 404, response.text
    assert "Traceback" not in response.text


def test_oversized_image_is_413(client: TestClient, r: redis.Redis, monkeypatch: Any) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_IMAGE_BYTES", "1024")
    get_settings.cache_clear()
    big = png_header_only(SIDE_PX, SIDE_PX) + b"\0" * 2048
    assert_field_error(submit(client, image=big), 413, ("body", "image"))
    assert queued(r) == 0


def test_oversized_body_is_413_before_parsing(
    client: TestClient, r: redis.Redis, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PROXPOSE_MAX_IMAGE_BYTES", "1024")
    monkeypatch.setenv("PROXPOSE_MAX_MODEL_BYTES", "1024")
    get_settings.cache_clear()
    body = b"x" * (3 * 1024 * 1024)  # limit: 1024 + 1 MiB of framing
    response = client.post("/v1/models", content=body, headers={"content-type": "text/plain"})
    assert_field_error(response, 413, ("body",))

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted while it streams in
        yield b'--x\r\nContent-Disposition: form-data; name="image"; filename="a.png"\r\n\r\n'
        for _ in range(48):
            yield b"y" * 65536

    headers = {"content-type": "multipart/form-data; boundary=x"}
    response = client.post("/v1/estimates", content=chunks(), headers=headers)
    assert_field_error(response, 413, ("body",))
    assert queued(r) == 0


# ----------------------------------------------------------------------------- good requests
def test_submit_answers_202_with_location_and_the_job(client: TestClient, r: redis.Redis) -> None:
    response = submit(client)
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/v1/estimates/{job['id']}"
    assert len(job["id"]) == 32
    assert job["status"] == "queued"
    assert job["model_id"] == "demo-sat"
    assert job["progress"] == {"iteration": 0, "max_iterations": 15, "cost": None, "stage": None}
    assert job["result"] is None and job["error"] is None and job["artifacts"] == {}
    assert Queue(KEYS.estimate_queue, connection=r).job_ids == [f"{job['id']}-1"]
    assert client.get(response.headers["location"]).json() == job


def test_request_may_come_as_a_file_part(client: TestClient) -> None:
    files = {
        "image": ("ref.png", png(), "image/png"),
        "request": ("request.json", json.dumps(base_request()).encode(), "application/json"),
    }
    response = client.post("/v1/estimates", files=files)
    assert response.status_code == 202, response.text


def test_method_preset_is_kept_for_the_worker(client: TestClient, r: redis.Redis) -> None:
    job = submit(client, base_request(options={"method": "paper"})).json()
    assert job["progress"]["max_iterations"] == 10  # the paper preset's cap
    stored = JobStore(r, KEYS, 60).get(job["id"])
    assert stored is not None and json.loads(stored.request)["options"] == {"method": "paper"}


def test_idempotency_key_returns_the_same_job(client: TestClient, r: redis.Redis) -> None:
    key = {"Idempotency-Key": "c0ffee-1"}
    first = submit(client, headers=key)
    again = submit(client, headers=key)
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["idempotent-replayed"] == "true"
    assert again.headers["location"] == first.headers["location"]
    assert Queue(KEYS.estimate_queue, connection=r).count == 1
    other = submit(client, base_request(options={"max_iterations": 3}), headers=key)
    assert_field_error(other, 422, ("header", "Idempotency-Key"))
    fresh = submit(client, headers={"Idempotency-Key": "c0ffee-2"})
    assert fresh.json()["id"] != first.json()["id"]
    assert Queue(KEYS.estimate_queue, connection=r).count == 2


def test_listing_is_newest_first_and_paged(client: TestClient) -> None:
    ids = [submit(client).json()["id"] for _ in range(5)]
    assert [j["id"] for j in client.get("/v1/estimates").json()["items"]] == ids[::-1]
    seen, cursor, pages = [], None, 0
    while True:
        params = {"limit": 2} | ({"cursor": cursor} if cursor else {})
        page = client.get("/v1/estimates", params=params).json()
        seen += [j["id"] for j in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1] and pages == 3
    assert "result" not in page["items"][0]  # listings stay small


def test_cancel_queued_job(client: TestClient, r: redis.Redis) -> None:
    job = submit(client).json()
    response = client.delete(f"/v1/estimates/{job['id']}")
    assert response.status_code == 200, response.text
    cancelled = response.json()
    assert cancelled["status"] == "cancelled" and cancelled["finished_at"] is not None
    assert Queue(KEYS.estimate_queue, connection=r).count == 0
    assert r.ttl(KEYS.job(job["id"])) > 0  # kept for the retention, then gone
    assert client.delete(f"/v1/estimates/{job['id']}").status_code == 409
    events = client.get(f"/v1/estimates/{job['id']}/events")
    assert events.headers["content-type"].startswith("text/event-stream")
    assert "event: status" in events.text and "event: end" in events.text


def test_running_job_of_a_dead_worker_is_requeued_then_failed(
    client: TestClient, r: redis.Redis
) -> None:
    """A lapsed lease (the worker died) sends the job back to the queue, at the front, until
    it has been started job_max_attempts (3) times; then it fails with worker_lost."""
    job_id = submit(client).json()["id"]
    other_id = submit(client).json()["id"]
    leases = Leases(JobStore(r, KEYS, 60), lease_s=30.0)
    queue = Queue(KEYS.estimate_queue, connection=r)
    for attempt in (1, 2, 3):
        rq_id = f"{job_id}-{attempt}"
        assert queue.job_ids[0] == rq_id  # a requeued job goes first
        queue.remove(rq_id)
        assert leases.start(job_id, f"w{attempt}", rq_id) is not None
        assert leases.start(job_id, "again", rq_id) is None  # started once only
        assert client.get(f"/v1/estimates/{job_id}").json()["status"] == "running"
        r.delete(KEYS.job_lease(job_id))  # the lease lapses: the worker is gone
        job = client.get(f"/v1/estimates/{job_id}").json()
        assert job["attempts"] == attempt
        assert job["status"] == ("queued" if attempt < 3 else "failed")
    assert job["error"]["code"] == "worker_lost" and "3 attempts" in job["error"]["message"]
    stored = JobStore(r, KEYS, 60).get(job_id)
    assert stored is not None and [e["worker"] for e in stored.lost] == ["w1", "w2", "w3"]
    assert "lost" not in job and "traceback" not in job
    assert queue.job_ids == [f"{other_id}-1"]  # the other job is untouched
    assert not r.sismember(KEYS.jobs_running, job_id)


def test_a_queued_job_that_rq_lost_is_enqueued_again(client: TestClient, r: redis.Redis) -> None:
    """A worker killed between popping a job from the queue and starting it: the orphan sweep
    enqueues it again once it was missing at two sweeps in a row."""
    job_id = submit(client).json()["id"]
    queue = Queue(KEYS.estimate_queue, connection=r)
    assert r.lpop(queue.key) == f"{job_id}-1".encode()  # what BLPOP does; then the worker dies
    reaper = Reaper(JobStore(r, KEYS, 60), max_attempts=3)

    def sweep() -> list[str]:
        r.delete(KEYS.orphan_sweep_lock)  # the next period
        return reaper.sweep_orphans()

    assert reaper.sweep_orphans() == [] and sweep() == [job_id]
    assert queue.job_ids == [f"{job_id}-2"]
    job = client.get(f"/v1/estimates/{job_id}").json()
    assert job["status"] == "queued" and job["attempts"] == 0
    assert sweep() == [] and sweep() == []  # present in the queue: nothing to do
    assert Leases(JobStore(r, KEYS, 60), 30.0).start(job_id, "w", f"{job_id}-1") is None  # stale
    assert Leases(JobStore(r, KEYS, 60), 30.0).start(job_id, "w", f"{job_id}-2") is not None
    assert not r.sismember(KEYS.jobs_queued, job_id)


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
    assert ModelStore(r, KEYS).data(model["id"]) == CUBE_OBJ  # workers fetch it from Redis
    assert [m["id"] for m in client.get("/v1/models").json()["items"]] == [model["id"]]
    assert client.get(f"/v1/models/{model['id']}").json() == model
    assert client.delete(f"/v1/models/{model['id']}").status_code == 204
    assert client.get(f"/v1/models/{model['id']}").status_code == 404


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
    ModelStore(r, KEYS).put(demo, b"glb")
    assert client.get("/v1/models/demo-sat").json()["builtin"] is True
    assert client.delete("/v1/models/demo-sat").status_code == 409


def test_probes_without_workers(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 503
    assert ready.json()["ready"] is False and ready.json()["workers"] == 0
    assert ready.json()["redis"] is True


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
