"""The browser pages without a browser: the HTML frames, static files, CSP-friendly markup,
labelled form fields, the framed default request of a model, and model previews (cached, and
answered at once without a worker). The pages in Chromium are in test_ui_browser.py."""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import redis
from conftest import settings_on_redis
from fastapi.testclient import TestClient

from schemas.estimate import EstimateResult
from schemas.jobs import EstimateCreate
from schemas.models import ModelPublic
from schemas.pose import PoseOut
from service.main import create_app
from service.pages import FILL_FRACTION, PreviewCache, suggested_request
from service.resources import estimate_outcome
from service.routes.pages import STATIC_DIR, TEMPLATES_DIR
from service.store import Keys, ModelStore
from worker.engine.posemath import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix

#: Redis database of this module (the session's Redis is shared with other modules).
DB = 6
#: What a strict CSP blocks (eval), or what would bypass our escaping or need 'unsafe-inline'.
BANNED_IN_SCRIPTS = ("eval(", "new Function", "innerHTML", "outerHTML", "document.write", ".style.")
PAGES = {"/": "index.js", "/models": "models.js", f"/estimates/{'0' * 32}": "estimate.js"}
#: A box from (−1, 2, 3) to (3, 4, 9): off-centre, so the framing must translate it.
BOX_OBJ = (
    "".join(f"v {x} {y} {z}\n" for x in (-1, 3) for y in (2, 4) for z in (3, 9))
    + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\n"
    + "f 3 4 8\nf 3 8 7\nf 1 3 7\nf 1 7 5\nf 2 6 8\nf 2 8 4\n"
).encode()


@pytest.fixture
def r(redis_server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[redis.Redis]:
    with settings_on_redis(redis_server, DB, tmp_path, monkeypatch) as client:
        yield client


@pytest.fixture
def client(r: redis.Redis) -> Iterator[TestClient]:
    with TestClient(create_app()) as c:
        yield c


def register_box(client: TestClient) -> dict[str, Any]:
    response = client.post("/v1/models", files={"file": ("box.obj", BOX_OBJ)}, data={"name": "Box"})
    assert response.status_code == 201, response.text
    return response.json()  # type: ignore[no-any-return]


class Markup(HTMLParser):
    """Collects what the CSP and accessibility checks look at."""

    def __init__(self) -> None:
        super().__init__()
        self.inline_scripts = 0
        self.handlers: list[str] = []
        self.styles = 0
        self.controls: list[dict[str, str | None]] = []
        self.label_for: set[str] = set()
        self.images_without_alt = 0
        self._label_depth = 0
        self._in_script_without_src = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self.handlers += [name for name in a if name.startswith("on")]
        self.styles += "style" in a
        if tag == "script" and "src" not in a and a.get("type") != "application/json":
            self._in_script_without_src = True
        if tag == "label":
            self._label_depth += 1
            if a.get("for"):
                self.label_for.add(a["for"] or "")
        if tag in ("input", "select", "textarea") and a.get("type") not in ("hidden", "submit"):
            self.controls.append({**a, "wrapped": "yes" if self._label_depth else None})
        if tag == "img" and "alt" not in a:
            self.images_without_alt += 1

    def handle_endtag(self, tag: str) -> None:
        if tag == "label":
            self._label_depth -= 1
        if tag == "script":
            self._in_script_without_src = False

    def handle_data(self, data: str) -> None:
        if self._in_script_without_src and data.strip():
            self.inline_scripts += 1


def parse(html: str) -> Markup:
    markup = Markup()
    markup.feed(html)
    return markup


# ----------------------------------------------------------------------------- the frames
@pytest.mark.parametrize("path", PAGES)
def test_pages_are_html_frames_loading_their_script(client: TestClient, path: str) -> None:
    response = client.get(path)
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/html")
    html = response.text
    assert '<html lang="en">' in html and '<main id="main"' in html
    assert f'<script type="module" src="/static/{PAGES[path]}"></script>' in html
    assert 'href="/static/app.css"' in html
    assert "Sign out" not in html  # no API keys configured


def test_root_is_the_estimates_page_not_a_redirect(client: TestClient) -> None:
    response = client.get("/", follow_redirects=False)
    assert response.status_code == 200 and "New estimate" in response.text


def test_a_malformed_estimate_id_gets_a_404_page(client: TestClient) -> None:
    response = client.get("/estimates/not-an-id")
    assert response.status_code == 404 and "No such estimate" in response.text
    assert "<script" not in response.text


def test_static_files_are_served_and_revalidated(client: TestClient) -> None:
    types = {".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
    files = sorted(f for f in STATIC_DIR.iterdir() if f.is_file())  # swagger/: test_docs_offline
    assert {f.suffix for f in files} == set(types)
    for path in files:
        response = client.get(f"/static/{path.name}")
        assert response.status_code == 200, path.name
        assert response.headers["content-type"].startswith(types[path.suffix]), path.name
        assert response.headers["cache-control"] == "no-cache"
        again = client.get(
            f"/static/{path.name}", headers={"If-None-Match": response.headers["etag"]}
        )
        assert again.status_code == 304


@pytest.mark.parametrize("path", PAGES)
def test_pages_are_csp_friendly_and_labelled(client: TestClient, path: str) -> None:
    markup = parse(client.get(path).text)
    assert markup.inline_scripts == 0
    assert markup.handlers == []
    assert markup.styles == 0
    assert markup.images_without_alt == 0
    unlabelled = [
        c.get("id") or c.get("name")
        for c in markup.controls
        if not (c.get("wrapped") or c.get("aria-label") or c.get("id") in markup.label_for)
    ]
    assert unlabelled == []


def test_templates_and_scripts_avoid_what_the_csp_forbids() -> None:
    for template in TEMPLATES_DIR.iterdir():
        text = template.read_text()
        assert not re.search(r"\son[a-z]+\s*=", text), template.name
        assert not re.search(r"\sstyle\s*=", text), template.name
        assert not re.search(r"<script(?![^>]*\bsrc=)", text), template.name
    for script in STATIC_DIR.glob("*.js"):
        text = script.read_text()
        for banned in BANNED_IN_SCRIPTS:
            assert banned not in text, f"{script.name} uses {banned}"
        assert 'setAttribute("style"' not in text, script.name


# ----------------------------------------------------------------------------- defaults
def box_corners(bounds: list[list[float]]) -> np.ndarray:
    """The 8 corners of an axis-aligned box [[xmin, ymin, zmin], [xmax, ymax, zmax]], (8, 3)."""
    lo, hi = bounds
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def project(request: dict[str, Any], points: np.ndarray) -> np.ndarray:
    """Pixel coordinates of model points under the request's camera and initial pose."""
    cam, pose = request["camera"], request["initial_pose"]
    R = quaternion_to_matrix(np.asarray(pose["quaternion"]))
    b = points @ R.T + np.asarray(pose["t"])
    assert (b[:, 2] > 0).all()
    return np.stack(
        [cam["fx"] * b[:, 0] / b[:, 2] + cam["cx"], cam["fy"] * b[:, 1] / b[:, 2] + cam["cy"]], 1
    )


def test_the_model_defaults_frame_its_bounding_sphere(client: TestClient) -> None:
    box = register_box(client)
    response = client.get(f"/models/{box['id']}/request.json", params={"width": 320, "height": 240})
    assert response.status_code == 200
    request = response.json()
    EstimateCreate.model_validate(request)
    assert request["model_id"] == box["id"]
    assert (request["camera"]["width"], request["camera"]["height"]) == (320, 240)
    lo, hi = np.asarray(box["bounds"])
    uv = project(request, box_corners(box["bounds"]))
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < 319).all()
    assert (uv[:, 1] > 0).all() and (uv[:, 1] < 239).all()
    centre = project(request, ((lo + hi) / 2)[None])[0]
    np.testing.assert_allclose(centre, [159.5, 119.5], atol=1e-3)  # on the optical axis
    # the bounding sphere's image radius is FILL_FRACTION of half the shorter side
    R = quaternion_to_matrix(np.asarray(request["initial_pose"]["quaternion"]))
    d = np.linalg.norm(R @ ((lo + hi) / 2) + request["initial_pose"]["t"])
    radius = np.linalg.norm(hi - lo) / 2
    image_radius = request["camera"]["fx"] * radius / math.sqrt(d**2 - radius**2)
    assert image_radius == pytest.approx(FILL_FRACTION * 120, rel=1e-3)
    sun = np.asarray(request["lighting"]["sun_direction"])
    assert sun[2] < 0  # from behind the camera


def test_the_model_defaults_validate_the_size_and_the_model(client: TestClient) -> None:
    box = register_box(client)
    assert client.get(f"/models/{box['id']}/request.json?width=8").status_code == 422
    assert client.get("/models/0123456789abcdef/request.json").status_code == 404
    assert client.get("/models/BAD!/request.json").status_code == 404


def test_demo_satellite_defaults_view_it_whole() -> None:
    bounds = [[-1.1, -8.05, -1.69], [2.29, 8.05, 2.0]]  # the demo satellite's
    model = ModelPublic(
        id="demo-sat", name="demo", vertices=8, faces=12, bounds=bounds, textured=False,
        format="glb", size_bytes=1, sha256="0" * 64, created_at="2026-01-01T00:00:00Z",
    )  # fmt: skip
    request = suggested_request(model, 512, 512)
    uv = project(request, box_corners(bounds))
    assert ((uv > 0) & (uv < 511)).all()


# ----------------------------------------------------------------------------- previews
def test_a_preview_without_a_worker_is_answered_at_once(client: TestClient) -> None:
    box = register_box(client)
    start = time.monotonic()
    response = client.get(f"/models/{box['id']}/preview.png")
    assert response.status_code == 503
    assert time.monotonic() - start < 2.0
    assert "worker" in response.json()["detail"]


def test_a_cached_preview_is_served_with_an_etag(client: TestClient, r: redis.Redis) -> None:
    box = register_box(client)
    model = ModelStore(r, Keys()).get(box["id"])
    assert model is not None
    PreviewCache(r, Keys()).put(model, b"\x89PNG fake")
    response = client.get(f"/models/{box['id']}/preview.png?v={box['sha256'][:16]}")
    assert response.status_code == 200 and response.content == b"\x89PNG fake"
    assert response.headers["content-type"] == "image/png"
    assert "max-age" in response.headers["cache-control"]
    etag = response.headers["etag"]
    again = client.get(f"/models/{box['id']}/preview.png", headers={"If-None-Match": etag})
    assert again.status_code == 304
    assert client.get("/models/0123456789abcdef/preview.png").status_code == 404


# ----------------------------------------------------------------------------- listing figures
def test_the_outcome_is_the_change_from_the_initial_guess() -> None:
    R0 = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 0.3)
    R1 = R0 @ axis_angle_to_matrix(np.array([1.0, 2.0, 2.0]) / 3.0, np.radians(7.5))

    def pose(R: np.ndarray, t: list[float]) -> PoseOut:
        quaternion = matrix_to_quaternion(R).tolist()
        return PoseOut(R=R.tolist(), q=[0.0, 0.0, 0.0], quaternion=quaternion, t=t)

    # only the fields the outcome reads (the rest of the result is the engine's business)
    result = EstimateResult.model_construct(
        pose=pose(R1, [0.3, 0.4, 10.0]),
        initial_pose=pose(R0, [0.0, 0.0, 10.0]),
        converged=True,
        reason="cost_converged",
    )
    outcome = estimate_outcome(result)
    assert outcome.rotation_change_deg == pytest.approx(7.5, abs=1e-6)
    assert outcome.translation_change == pytest.approx(0.5)
    assert outcome.converged and outcome.reason == "cost_converged"
