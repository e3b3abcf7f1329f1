"""The track page (``/tracks/{id}``) in headless Chromium against the real service (uvicorn,
Redis, a `proxpose worker` process; the `stack` of e2e_helpers): four ray-traced frames of the
demo satellite with the truth, watched live as they are tracked, then the trajectory plots
(range, attitude, errors), the per-frame table, the overlay of a chosen frame, the worker's
plot and the downloads; and a track that does not exist. No console errors under the CSP."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import pytest
from e2e_helpers import (
    Stack,
    e2e_stack,  # noqa: F401 (the stack fixture, started again for this module)
)
from test_service_tracks_worker import CAMERA, N_FRAMES, make_frames
from test_ui_browser import (
    Tab,
    browser_tab,  # noqa: F401 (the tab fixture)
    chromium_browser,  # noqa: F401 (the browser fixture)
    image_size,
    poll_until,
)

pytestmark = [pytest.mark.slow, pytest.mark.browser]

#: How long four frames at 192 × 144 px may take (with a worker starting), s.
TRACK_TIMEOUT_S = 180.0
PLOTS = ("range", "attitude-x", "attitude-y", "attitude-z", "rotation-error", "translation-error")


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory, variant: str) -> Any:
    return make_frames(tmp_path_factory.mktemp("track-ui"))


def submit_track(stack: Stack, frames: list[Path], request: dict[str, Any]) -> str:
    files = [("frames", (p.name, p.read_bytes(), "image/png")) for p in frames]
    response = stack.api.post("/v1/tracks", files=files, data={"request": json.dumps(request)})
    assert response.status_code == 202, response.text
    return str(response.json()["id"])


def test_watch_a_track_run_and_read_its_trajectory_frames_and_overlays(
    stack: Stack, tab: Tab, sequence: Any
) -> None:
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    frames, request = sequence
    job_id = submit_track(stack, frames, request)
    page = tab.page
    page.goto(f"/tracks/{job_id}")
    texts = poll_until(
        lambda: page.is_visible("#result") or page.is_visible("#failure"),
        lambda: (
            f"{page.text_content('#progress-text')} | rows "
            f"{page.locator('#frames-table tbody tr').count()}"
        ),
        TRACK_TIMEOUT_S,
    )
    job = stack.api.get(f"/v1/tracks/{job_id}").json()
    assert job["status"] == "succeeded", job["error"]
    expect(page.locator("#status")).to_have_text("succeeded")
    partial = [t for t in texts if t.startswith("Running:") and f"of {N_FRAMES}" in t]
    assert any(not t.startswith(f"Running: {N_FRAMES} ") for t in partial), texts  # live

    for name in PLOTS:
        svg = page.locator(f'figure[data-plot="{name}"] svg')
        expect(svg).to_have_attribute("data-points", str(N_FRAMES))
    rows = page.locator("#frames-table tbody tr")
    expect(rows).to_have_count(N_FRAMES)
    statuses = rows.evaluate_all("rows => rows.map(r => r.dataset.status)")
    assert statuses == [f["status"] for f in job["result"]["frames"]]
    expect(page.locator("#summary")).to_contain_text(f"{N_FRAMES} frames")
    expect(page.locator("#frames-table")).to_contain_text("Rotation error")

    assert image_size(tab, "#overlay") == (CAMERA["width"], CAMERA["height"])
    page.select_option("#frame-select", "2")
    expect(page.locator("#overlay-caption")).to_contain_text(f"Frame 2 ({frames[2].name})")
    assert image_size(tab, "#overlay") == (CAMERA["width"], CAMERA["height"])
    width, _height = image_size(tab, "#trajectory-png")
    assert width > 300

    with page.expect_download() as download:
        page.click("#download-track")
    track = json.loads(Path(download.value.path()).read_text())
    assert track["frames"] == job["result"]["frames"]
    with page.expect_download() as download:
        page.click("#download-csv")
    table = list(csv.DictReader(io.StringIO(Path(download.value.path()).read_text())))
    assert [row["image"] for row in table] == [p.name for p in frames]
    tab.shot("track")
    tab.assert_clean()


def test_a_track_that_does_not_exist_says_so(stack: Stack, tab: Tab) -> None:
    from playwright.sync_api import expect

    tab.page.goto(f"/tracks/{'0' * 32}")
    expect(tab.page.locator("#failure-title")).to_have_text("No such track")
    expect(tab.page.locator("#status")).to_have_text("missing")
    tab.assert_clean(expected_statuses=(404,))
