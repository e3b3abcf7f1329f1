"""The client's calls validate against the OpenAPI document (``create_app().openapi()``): every
request the client sends, to a real API process on a real Redis, is a documented operation
(method, path, query and header parameters, content type, multipart part names and their
encodings, the JSON request validated against its schema), every answer it gets is a documented
response whose JSON body validates against the documented schema, and every documented error
status of the operations it calls maps to one of its typed errors."""

from __future__ import annotations

import email
import email.policy
import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import jsonschema
import pytest
from service_api_helpers import base_request, png
from test_client import api_url, client_env  # noqa: F401 (the API process fixtures)

from service.client import ApiError, Client, NotFound
from service.client.errors import _BY_STATUS
from service.main import create_app

TETRAHEDRON_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
#: Headers every request has, which the document need not list as parameters.
TRANSPORT_HEADERS = {
    *("host", "accept", "accept-encoding", "connection", "user-agent", "content-length"),
    *("content-type", "authorization"),
}


@pytest.fixture(scope="module")
def document() -> dict[str, Any]:
    return create_app().openapi()


def operation_of(document: dict[str, Any], request: httpx.Request) -> dict[str, Any]:
    """The documented operation of ``request`` (fails when there is none)."""
    for template, item in document["paths"].items():
        pattern = "^" + re.sub(r"\{[^/}]+\}", "[^/]+", template) + "$"
        if re.match(pattern, request.url.path):
            method = request.method.lower()
            assert method in item, f"{request.method} {template} is not documented"
            return item[method]  # type: ignore[no-any-return]
    raise AssertionError(f"{request.method} {request.url.path}: no documented path")


def validate(document: dict[str, Any], instance: Any, schema: dict[str, Any], where: str) -> None:
    """``instance`` against ``schema`` (JSON Schema 2020-12, as OpenAPI 3.1 writes it), its
    ``#/components/...`` references resolved in ``document``."""
    root = {**schema, "components": document["components"]}
    errors = list(jsonschema.Draft202012Validator(root).iter_errors(instance))
    assert not errors, f"{where}: {[(list(e.absolute_path), e.message) for e in errors[:3]]}"


def check_parameters(op: dict[str, Any], request: httpx.Request, where: str) -> None:
    params = op.get("parameters", [])
    query = {p["name"] for p in params if p["in"] == "query"}
    headers = {p["name"].lower() for p in params if p["in"] == "header"}
    sent_query = {name for name, _ in request.url.params.multi_items()}
    assert sent_query <= query, (where, sent_query - query)
    sent_headers = {name.lower() for name in request.headers} - TRANSPORT_HEADERS
    assert sent_headers <= headers, (where, sent_headers - headers)
    required = {p["name"] for p in params if p.get("required") and p["in"] == "query"}
    assert required <= sent_query, (where, required - sent_query)


def multipart_parts(request: httpx.Request) -> list[tuple[str, str, bytes]]:
    """(part name, content type, bytes) of a multipart/form-data request, in order."""
    head = f"Content-Type: {request.headers['content-type']}\r\n\r\n".encode()
    message = email.message_from_bytes(head + request.read(), policy=email.policy.HTTP)
    return [
        (
            str(part.get_param("name", header="content-disposition")),
            part.get_content_type(),
            part.get_payload(decode=True),
        )
        for part in message.iter_parts()  # type: ignore[attr-defined]
    ]


def check_multipart(
    document: dict[str, Any], media: dict[str, Any], request: httpx.Request, valid: bool
) -> None:
    where = f"{request.method} {request.url.path}"
    schema = media["schema"]
    if "$ref" in schema:
        schema = document["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    properties, encoding = schema["properties"], media.get("encoding", {})
    parts = multipart_parts(request)
    names = [name for name, _, _ in parts]
    assert set(names) <= set(properties), (where, set(names) - set(properties))
    assert set(schema.get("required", [])) <= set(names), (where, names)
    for name, content_type, data in parts:
        prop = properties[name]
        assert names.count(name) == 1 or prop.get("type") == "array", (where, name, "repeated")
        default = "application/octet-stream" if _is_binary(prop) else "text/plain"
        documented = encoding.get(name, {}).get("contentType", default)
        allowed = {t.strip() for t in documented.split(",")}
        assert content_type in allowed, (where, name, content_type, allowed)
        if content_type == "application/json" and valid:
            validate(document, json.loads(data), prop, f"{where} part {name}")


def _is_binary(prop: dict[str, Any]) -> bool:
    item = prop.get("items", prop)
    return item.get("format") == "binary" or "contentMediaType" in item


def check_request(
    document: dict[str, Any], request: httpx.Request, valid: bool = True
) -> dict[str, Any]:
    """The checks of the module docstring on one request; its operation. ``valid``: the JSON
    sent validates against its schema (not so for a request the service refused with 422:
    the client sends the caller's request as given, for the service to name each bad field)."""
    where = f"{request.method} {request.url.path}"
    op = operation_of(document, request)
    check_parameters(op, request, where)
    body = op.get("requestBody")
    sent = request.headers.get("content-type", "").split(";")[0]
    if body is None:
        assert not request.read(), f"{where}: a body the document does not describe"
        return op
    assert sent in body["content"], (where, sent, list(body["content"]))
    if sent == "multipart/form-data":
        check_multipart(document, body["content"][sent], request, valid)
    elif sent == "application/json" and valid:
        validate(document, json.loads(request.read()), body["content"][sent]["schema"], where)
    return op


def check_response(document: dict[str, Any], op: dict[str, Any], response: httpx.Response) -> None:
    where = f"{response.request.method} {response.request.url.path} → {response.status_code}"
    documented = op["responses"].get(str(response.status_code))
    assert documented is not None, (where, sorted(op["responses"]))
    media = response.headers.get("content-type", "").split(";")[0]
    content = {k.split(";")[0]: v for k, v in documented.get("content", {}).items()}
    if not content:
        return
    assert media in content, (where, media, list(content))
    schema = content[media].get("schema")
    if schema and media.endswith("json"):
        validate(document, response.json(), schema, where)


class Recorder:
    """Every (request, response) of a client, checked against the document at the end."""

    def __init__(self) -> None:
        self.responses: list[httpx.Response] = []

    def attach(self, client: Client) -> Client:
        client.http.event_hooks["response"] = [self.responses.append]
        return client

    def check(self, document: dict[str, Any]) -> set[str]:
        """The ids of the operations seen, after checking each exchange."""
        seen = set()
        for response in self.responses:
            op = check_request(document, response.request, response.status_code != 422)
            check_response(document, op, response)
            seen.add(op["operationId"])
        return seen


@pytest.fixture
def recorded(api_url: str) -> Iterator[tuple[Client, Recorder]]:  # noqa: F811
    recorder = Recorder()
    with Client(api_url, timeout_s=10.0) as client:
        yield recorder.attach(client), recorder


def call_everything(api: Client, tmp_path: Path) -> None:
    """Each method of the client, on its success and on an error answer."""
    mesh = tmp_path / "tetra.obj"
    mesh.write_text(TETRAHEDRON_OBJ)
    model = api.upload_model(mesh, name="A tetrahedron")
    assert {m.id for m in api.models()} >= {model.id}
    assert api.model(model.id).id == model.id
    api.delete_model(model.id)
    image = tmp_path / "ref.png"
    image.write_bytes(png())
    job = api.submit_estimate(image, base_request(), idempotency_key="openapi-check-1")
    api.submit_estimate(png(), base_request())
    assert api.get(job.id).id == job.id
    list(api.iter_estimates(status=["queued", "cancelled"], model_id="demo-sat"))
    api.cancel(job.id)
    list(api.events(job.id))
    api.wait(job.id, timeout_s=5.0)
    track = api.submit_track([image, png()], base_request(), idempotency_key="openapi-check-2")
    assert api.get_track(track.id).id == track.id
    api.cancel_track(track.id)
    list(api.track_events(track.id))
    api.wait_track(track.id, timeout_s=5.0)
    failing = [
        lambda: api.artifact(job.id, "difference"),
        lambda: api.track_artifact(track.id, "trajectory"),
        lambda: api.track_json(track.id),
        lambda: api.cancel(job.id),
        lambda: api.model("0" * 16),
        lambda: api.submit_estimate(png(32, 32), base_request()),
        lambda: api.submit_track([png()], base_request(model_id="Not An Id")),
    ]
    for call in failing:
        with pytest.raises(ApiError):
            call()
    with pytest.raises(NotFound):
        list(api.track_events("0" * 32))


def test_the_clients_calls_and_their_answers_are_documented(
    recorded: tuple[Client, Recorder], document: dict[str, Any], tmp_path: Path
) -> None:
    api, recorder = recorded
    call_everything(api, tmp_path)
    seen = recorder.check(document)
    statuses = {r.status_code for r in recorder.responses}
    assert {200, 201, 202, 204, 404, 409, 422} <= statuses, statuses
    assert len(recorder.responses) >= 24
    expected = {
        *("create_model", "list_models", "get_model", "delete_model"),
        *("create_estimate", "get_estimate", "list_estimates", "cancel_estimate"),
        *("stream_events", "get_artifact", "create_track", "get_track", "cancel_track"),
        *("stream_track_events", "get_track_artifact", "get_track_json"),
    }
    assert expected <= seen, expected - seen


def test_a_render_and_readiness_are_documented_requests(document: dict[str, Any]) -> None:
    """No worker here to render: the requests are checked as sent, the answers as scripted."""
    sent: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        if request.url.path == "/readyz":
            return httpx.Response(200, json={"status": "ready"})
        return httpx.Response(200, content=png(), headers={"content-type": "image/png"})

    render = {k: v for k, v in base_request().items() if k != "initial_pose"}
    render["pose"] = base_request()["initial_pose"]
    with Client("http://proxpose.test", transport=httpx.MockTransport(handle)) as api:
        api.render(render)
        api.ready()
    assert [operation_of(document, r)["operationId"] for r in sent] == ["create_render", "readyz"]
    for request in sent:
        check_request(document, request)


def test_every_documented_error_of_the_clients_operations_is_typed(
    document: dict[str, Any],
) -> None:
    untyped = set()
    for item in document["paths"].values():
        for method, op in item.items():
            if not isinstance(op, dict) or "responses" not in op:
                continue
            for status, response in op["responses"].items():
                code = int(status)
                if code < 400:
                    continue
                if code not in _BY_STATUS and code < 500:
                    untyped.add((method, op["operationId"], code))
                schema = response["content"]["application/problem+json"]["schema"]
                assert schema["$ref"].endswith("/Problem"), (op["operationId"], status)
    assert not untyped, untyped
