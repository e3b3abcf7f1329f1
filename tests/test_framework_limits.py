"""Why the body limit (``service/limits.py``) and the part-size match (``service/errors.py``) are
ours and not the pinned framework's (FastAPI 0.165, Starlette 1.10): what the framework's own
limits answer, on a bare app with a problem-details handler. When one of these fails after an
upgrade, the framework may now do what we need: try it in place of our copy.

- ``max_body_size`` (app, router or route) answers a body whose Content-Length is over the limit
  with a plain-text 413, whatever the app's handlers answer: ``RequestBodyLimitResponder``
  (starlette/middleware/body_limit.py) swaps any response started for such a request for
  ``PlainTextResponse("Content Too Large", 413)`` in ``send_with_limit``. Only a body that
  overflows while it streams (no Content-Length) reaches our handler.
- ``form_limits={"max_part_size": …}`` (or ``request.form(max_part_size=…)``) refuses a large
  form field with ``HTTPException(400, detail=<the parser's message>)``
  (starlette/requests.py, ``_get_form``): Starlette's one ``MultiPartException`` class carries
  only a message, so a part over the size is told from malformed multipart by its text.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Any

import pytest
from fastapi import FastAPI, File, Form, Request, UploadFile
from fastapi.responses import JSONResponse
from fastapi.testclient import TestClient
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartException

from schemas.problem import PROBLEM_MEDIA_TYPE
from service.errors import STARLETTE_FIELD_TOO_LARGE, STARLETTE_PART_TOO_LARGE

MAX_BODY_BYTES = 1000
MAX_PART_BYTES = 100


@pytest.fixture
def framework_limited() -> Iterator[tuple[TestClient, list[HTTPException]]]:
    """An app with FastAPI's limits on one route and a problem handler recording what it got."""
    app = FastAPI()
    seen: list[HTTPException] = []

    async def problem(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, HTTPException)
        seen.append(exc)
        body = {"status": exc.status_code, "code": "too_large"}
        return JSONResponse(body, exc.status_code, media_type=PROBLEM_MEDIA_TYPE)

    app.add_exception_handler(HTTPException, problem)

    @app.post(
        "/upload",
        max_body_size=MAX_BODY_BYTES,
        form_limits={"max_part_size": MAX_PART_BYTES},
    )
    def upload(
        image: Annotated[UploadFile, File()], request: Annotated[str, Form()]
    ) -> dict[str, Any]:
        return {"ok": True}

    with TestClient(app) as client:
        yield client, seen


def test_max_body_size_answers_a_declared_oversize_body_in_plain_text(
    framework_limited: tuple[TestClient, list[HTTPException]],
) -> None:
    client, seen = framework_limited
    files = {"image": ("a.png", b"x" * (2 * MAX_BODY_BYTES))}
    response = client.post("/upload", files=files, data={"request": "{}"})
    assert response.status_code == 413
    assert [e.status_code for e in seen] == [413]  # our handler ran, and was overridden:
    assert response.headers["content-type"].startswith("text/plain"), response.headers
    assert response.text == "Content Too Large"


def test_max_body_size_lets_a_handler_answer_a_streamed_overflow(
    framework_limited: tuple[TestClient, list[HTTPException]],
) -> None:
    client, _ = framework_limited

    def chunks() -> Iterator[bytes]:  # no Content-Length
        yield b'--x\r\nContent-Disposition: form-data; name="image"; filename="a.png"\r\n\r\n'
        yield b"y" * (2 * MAX_BODY_BYTES)

    headers = {"content-type": "multipart/form-data; boundary=x"}
    response = client.post("/upload", content=chunks(), headers=headers)
    assert response.status_code == 413
    assert response.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)


def test_a_form_part_over_max_part_size_is_a_400_known_by_its_text(
    framework_limited: tuple[TestClient, list[HTTPException]],
) -> None:
    client, seen = framework_limited
    files = {"image": ("a.png", b"x")}
    response = client.post("/upload", files=files, data={"request": "y" * (2 * MAX_PART_BYTES)})
    assert response.status_code == 400
    (error,) = seen
    assert type(error) is HTTPException and error.status_code == 400
    assert isinstance(error.__context__, MultiPartException)
    assert vars(error.__context__) == {"message": error.detail}  # nothing but the text
    assert str(error.detail).startswith(STARLETTE_PART_TOO_LARGE)  # what service/errors.py matches


def test_a_urlencoded_field_over_max_part_size_is_a_400_in_other_words(
    framework_limited: tuple[TestClient, list[HTTPException]],
) -> None:
    client, seen = framework_limited
    response = client.post("/upload", data={"request": "y" * (2 * MAX_PART_BYTES)})
    assert response.status_code == 400
    (error,) = seen
    assert isinstance(error.__context__, MultiPartException)
    assert str(error.detail).startswith(STARLETTE_FIELD_TOO_LARGE)  # what service/errors.py matches
