"""Requests the API refuses, on a real Redis without workers (nothing here renders): the
validation battery of ``POST /v1/estimates`` (every bad request answered 4xx naming the field,
nothing enqueued), unknown ids (404) and oversized uploads (413). The bad requests to the other
endpoints are in test_service_api_models_renders.py."""

from __future__ import annotations

import copy
import json
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
import redis
from fastapi.testclient import TestClient
from service_api_helpers import (
    SIDE_PX,
    api_client,  # noqa: F401 (the client fixture)
    assert_field_error,
    base_request,
    png,
    queued,
    redis_db,  # noqa: F401 (the r fixture)
    submit,
)

from schemas.settings import get_settings


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


# ----------------------------------------------------------------------------- 404 and 413
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


def test_urlencoded_field_over_1_mib_is_413(client: TestClient, r: redis.Redis) -> None:
    """A urlencoded form's field over Starlette's 1 MiB cap is told apart by its own text
    ("Field exceeded", not the multipart parser's "Part exceeded"): 413, not a bare 400."""
    response = client.post("/v1/estimates", data={"request": "x" * 1_100_000})
    assert response.status_code == 413, response.text
    assert response.json()["code"] == "too_large"
    assert "1 MiB" in response.json()["detail"]
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
