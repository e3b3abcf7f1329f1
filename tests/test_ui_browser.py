"""The pages in headless Chromium against the real service (uvicorn, Redis, worker processes;
the `stack` fixture of e2e_helpers): submit an estimate through the form and watch it run,
read the result (plots, overlays, difference image, downloads), the list's auto-refresh and
status filter, a failure in words, model previews and uploads, and the key form when API keys
are configured. Every page must load without console errors or uncaught exceptions under the
service's Content Security Policy. Screenshots go to test-output/ui/.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import REPO, free_port, start_api
from e2e_helpers import (
    CUBE_OBJ,
    DB,
    R_TRUE,
    T_TRUE,
    Stack,
    camera,
    e2e_stack,  # noqa: F401 (the stack fixture, started again for this module)
    estimate_request,
    initial_pose,
    pose,
    submit,
)

pytestmark = [pytest.mark.slow, pytest.mark.browser]

CHROMIUM = Path(os.environ.get("PROXPOSE_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    *("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"),
    *("--disable-component-update", "--disable-sync", "--no-first-run"),
]
SCREENSHOTS = REPO / "test-output" / "ui"
#: How long an estimate of the demo satellite at 128–192 px may take, s.
ESTIMATE_TIMEOUT_S = 180.0
#: Playwright's waits, ms.
WAIT_MS = 60_000
API_KEY = "ui-test-key-0123456789abcdef"
ARTIFACT_IMAGES = ("overlay_1", "overlay_2", "overlay_final", "difference", "final_render")


@pytest.fixture(scope="module", name="browser")
def chromium_browser() -> Iterator[Any]:
    """Debian's Chromium driven by Playwright (no browser download): skipped when missing,
    unless PROXPOSE_REQUIRE_BROWSER=1."""
    if not CHROMIUM.is_file():
        reason = f"{CHROMIUM} is missing (`make system-deps` installs chromium as root)"
        if os.environ.get("PROXPOSE_REQUIRE_BROWSER") == "1":
            pytest.fail(f"PROXPOSE_REQUIRE_BROWSER=1 but {reason}")
        pytest.skip(reason)
    from playwright.sync_api import sync_playwright

    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@dataclass
class Tab:
    """A page in a fresh browser context, recording console errors and uncaught exceptions."""

    page: Any
    problems: list[str] = field(default_factory=list)

    def assert_clean(self, expected_statuses: tuple[int, ...] = ()) -> None:
        """No console error or warning, no uncaught exception; a failed resource load counts
        unless its status is expected (Chromium logs a 4xx answer to fetch() as an error)."""
        bad = [
            p
            for p in self.problems
            if not any(f"status of {status}" in p for status in expected_statuses)
        ]
        assert bad == [], bad

    def shot(self, name: str) -> None:
        self.page.screenshot(path=SCREENSHOTS / f"{name}.png", full_page=True)


def open_tab(browser: Any, base_url: str) -> Tab:
    context = browser.new_context(
        base_url=base_url, viewport={"width": 1280, "height": 900}, accept_downloads=True
    )
    tab = Tab(context.new_page())
    tab.page.set_default_timeout(WAIT_MS)
    tab.page.on(
        "console",
        lambda m: (
            m.type in ("error", "warning")
            and tab.problems.append(f"{m.type}: {m.text} ({m.location.get('url')})")
        ),
    )
    tab.page.on("pageerror", lambda e: tab.problems.append(f"uncaught: {e}"))
    return tab


@pytest.fixture(name="tab")
def browser_tab(browser: Any, stack: Stack) -> Iterator[Tab]:
    opened = open_tab(browser, str(stack.api.base_url))
    yield opened
    opened.page.context.close()


def image_size(tab: Tab, selector: str) -> tuple[int, int]:
    """The decoded size of a loaded image (0 × 0 while loading or when broken)."""
    tab.page.wait_for_selector(selector)
    deadline = time.monotonic() + WAIT_MS / 1000
    while True:
        complete, width, height = tab.page.eval_on_selector(
            selector, "img => [img.complete && img.src !== '', img.naturalWidth, img.naturalHeight]"
        )
        if complete and width or time.monotonic() > deadline:
            return width, height
        time.sleep(0.1)


def poll_until(done: Callable[[], bool], seen: Callable[[], str], timeout_s: float) -> list[str]:
    """Record ``seen()`` every 50 ms until ``done()``; every distinct value, in order."""
    values: list[str] = []
    deadline = time.monotonic() + timeout_s
    while not done():
        value = seen()
        if not values or values[-1] != value:
            values.append(value)
        assert time.monotonic() < deadline, f"not done in {timeout_s} s; saw {values}"
        time.sleep(0.05)
    return values


def fill_vector(tab: Tab, prefix: str, values: list[float]) -> None:
    for i, value in enumerate(values):
        tab.page.fill(f"#{prefix}-{i}", repr(value))


# ----------------------------------------------------------------------------- the flows
def test_submit_an_estimate_through_the_form_and_read_the_result(
    browser: Any, stack: Stack, tab: Tab, tmp_path: Path
) -> None:
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    reference = tmp_path / "reference.png"
    reference.write_bytes(stack.references["ref192"])
    page = tab.page
    page.goto("/")
    expect(page.locator("#model")).to_have_value("demo-sat")
    expect(page.locator("#cam-fx")).not_to_have_value("")  # the model's defaults arrived
    page.set_input_files("#image", reference)
    expect(page.locator("#cam-width")).to_have_value("192")  # sized from the image
    for name, value in camera(192).items():
        page.fill(f"#cam-{name}", repr(value))
    guess, truth = initial_pose(), pose(R_TRUE, T_TRUE)
    fill_vector(tab, "pose-t", guess["t"])
    fill_vector(tab, "pose-q", guess["quaternion"])
    page.locator("#truth-panel summary").press("Enter")  # keyboard: open the ground truth
    fill_vector(tab, "truth-t", truth["t"])
    fill_vector(tab, "truth-q", truth["quaternion"])
    page.locator("#submit-button").press("Enter")

    page.wait_for_url(re.compile(r"/estimates/[0-9a-f]{32}$"))
    job_id = page.url.rsplit("/", 1)[1]
    texts = poll_until(
        lambda: page.is_visible("#result") or page.is_visible("#failure"),
        lambda: page.text_content("#progress-text") or "",
        ESTIMATE_TIMEOUT_S,
    )
    job = stack.api.get(f"/v1/estimates/{job_id}").json()
    assert job["status"] == "succeeded", job["error"]
    expect(page.locator("#status")).to_have_text("succeeded")
    iterations = [t for t in texts if t.startswith("Running: iteration")]
    assert len(iterations) >= 2, texts  # the progress moved while we watched

    result = job["result"]
    n = result["iterations"]
    # the cost is on a log scale: iterations that measured none (cost 0) are left out
    costs = [h for h in result["history"] if h["cost"] > 0]
    rejected = sum(not h["accepted"] for h in costs)
    for name, points in (("rotation", n + 1), ("translation", n + 1), ("cost", len(costs))):
        svg = page.locator(f'figure[data-plot="{name}"] svg')
        expect(svg).to_have_attribute("data-points", str(points))  # +1: the initial guess
        expect(svg.locator(".pt")).to_have_count(points)
    expect(page.locator('figure[data-plot="cost"] .pt.rejected')).to_have_count(rejected)
    expect(page.locator("#history-table tbody tr")).to_have_count(n)
    for name in ARTIFACT_IMAGES:
        assert image_size(tab, f'img[data-artifact="{name}"]') == (192, 192), name
    width, height = image_size(tab, 'img[data-artifact="convergence"]')
    assert width > 200 and height > 100
    expect(page.locator("#sigma-table tbody tr")).to_have_count(7)
    expect(page.locator("#errors-table")).to_contain_text("rotation (°)")
    tilt = f"{result['sun_tilt_deg']:.2f}° from the request's"
    expect(page.locator("#run-facts")).to_contain_text(tilt)  # the sun the fit ended with
    assert result["reflectance_share"] == 0.0  # demo-sat is no smooth body: Lambert kept
    expect(page.locator("#run-facts")).not_to_contain_text("Reflectance law")
    expect(page.locator("#request-json")).to_contain_text('"model_id": "demo-sat"')
    with page.expect_download() as download:
        page.click("#download-result")
    downloaded = json.loads(Path(download.value.path()).read_text())
    assert downloaded["pose"] == result["pose"] and downloaded["history"] == result["history"]
    tab.shot("estimate")
    page.set_viewport_size({"width": 390, "height": 844})
    tab.shot("estimate-narrow")
    page.set_viewport_size({"width": 1280, "height": 900})

    page.goto("/")
    row = page.locator(f'tr[data-id="{job_id}"]')
    expect(row).to_contain_text("succeeded")
    cells = row.locator("td")
    assert float(cells.nth(4).inner_text()) == pytest.approx(
        job["outcome"]["rotation_change_deg"], rel=1e-2
    )
    assert cells.nth(2).inner_text() == f"{n} / {job['progress']['max_iterations']}"
    tab.shot("estimates")
    tab.assert_clean()


def test_the_list_refreshes_while_jobs_run_and_a_failure_is_told_in_words(
    browser: Any, stack: Stack, tab: Tab
) -> None:
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    quick = submit(stack, estimate_request(128, max_iterations=2)).json()["id"]
    lost = estimate_request(128)
    lost["initial_pose"]["t"] = [60.0, 0.0, 14.0]  # the target far outside the view
    failing = submit(stack, lost).json()["id"]
    page = tab.page
    page.goto("/")
    expect(page.locator(f'tr[data-id="{quick}"]')).to_be_visible()
    # no reload: the list polls while a job is queued or running
    for job_id, status in ((quick, "succeeded"), (failing, "failed")):
        expect(page.locator(f'tr[data-id="{job_id}"]')).to_have_attribute(
            "data-status", status, timeout=ESTIMATE_TIMEOUT_S * 1000
        )
    page.select_option("#status-filter", "failed")
    # the filter empties the list and fetches it again: wait for the fetch, not the empty list
    expect(page.locator(f'tr[data-id="{failing}"]')).to_be_visible()
    expect(page.locator(f'tr[data-id="{quick}"]')).to_have_count(0)
    statuses = page.locator("#jobs tr").evaluate_all("rows => rows.map(r => r.dataset.status)")
    assert statuses and set(statuses) == {"failed"}
    tab.shot("estimates-failed-filter")

    page.locator(f'tr[data-id="{failing}"] a').press("Enter")
    page.wait_for_url(f"**/estimates/{failing}")
    expect(page.locator("#failure")).to_be_visible()
    expect(page.locator("#failure-title")).to_have_text("The estimate failed")
    expect(page.locator("#failure-code")).to_have_text("empty_render")
    assert len(page.inner_text("#failure-message")) > 20
    expect(page.locator("#failure-hint")).to_contain_text("not visible at the initial pose")
    expect(page.locator("#result")).to_be_hidden()
    tab.shot("estimate-failed")
    tab.assert_clean()


def test_models_page_previews_each_model_and_registers_an_upload(
    browser: Any, stack: Stack, tab: Tab
) -> None:
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    page = tab.page
    page.goto("/models")
    assert image_size(tab, 'img[data-model="demo-sat"]') == (256, 256)
    cube = {"name": "ui-cube.obj", "mimeType": "text/plain", "buffer": CUBE_OBJ + b"# ui\n"}
    page.set_input_files("#model-file", files=[cube])
    page.fill("#model-name", "UI cube")
    page.click("#upload-button")
    expect(page.locator("#upload-status")).to_contain_text("Registered “UI cube”")
    card = page.locator(".card", has_text="UI cube")
    expect(card).to_be_visible()
    model_id = card.get_attribute("id").removeprefix("model-")  # type: ignore[union-attr]
    assert image_size(tab, f'img[data-model="{model_id}"]') == (256, 256)
    expect(card.locator("a", has_text="New estimate")).to_have_attribute(
        "href", f"/?model={model_id}#new-estimate"
    )
    tab.shot("models")
    tab.assert_clean()


def test_form_errors_name_the_field_and_take_the_focus(
    browser: Any, stack: Stack, tab: Tab, tmp_path: Path
) -> None:
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    reference = tmp_path / "reference.png"
    reference.write_bytes(stack.references["ref128"])
    page = tab.page
    page.goto("/")
    expect(page.locator("#cam-fx")).not_to_have_value("")
    page.click("#submit-button")
    expect(page.locator("#submit-errors")).to_contain_text("choose the reference image")
    page.set_input_files("#image", reference)
    expect(page.locator("#cam-width")).to_have_value("128")
    page.fill("#cam-fx", "-5")
    page.click("#submit-button")
    expect(page.locator("#submit-errors")).to_contain_text("camera.fx")
    expect(page.locator("#cam-fx")).to_have_attribute("aria-invalid", "true")
    expect(page.locator("#cam-fx")).to_be_focused()
    tab.shot("form-errors")
    tab.assert_clean(expected_statuses=(422,))


def test_with_api_keys_the_pages_go_through_the_key_form(
    browser: Any, stack: Stack, redis_server: Any, tmp_path: Path
) -> None:
    """An API with keys configured beside the open one (same Redis and workers): the browser
    signs in at /session, then the pages and their API calls work on the cookie."""
    from playwright.sync_api import expect

    stack.workers.ensure(1)
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(stack.data_dir),
        "PROXPOSE_API_KEYS": f"ui:{API_KEY}",
    }
    port = free_port()
    api = start_api(env, tmp_path / "api-keys.log", port)
    tab = open_tab(browser, f"http://127.0.0.1:{port}")
    page = tab.page
    try:
        assert httpx.get(f"http://127.0.0.1:{port}/v1/models").status_code == 401
        page.goto("/")
        page.wait_for_url("**/session?next=/")
        page.fill("input[name=api_key]", API_KEY)
        page.click("button[type=submit]")
        page.wait_for_url(f"http://127.0.0.1:{port}/")
        expect(page.locator("#model")).to_have_value("demo-sat")
        expect(page.locator(".signout")).to_contain_text("Sign out")

        # the JSON mode of the form, on the cookie
        reference = tmp_path / "reference.png"
        reference.write_bytes(stack.references["ref128"])
        page.set_input_files("#image", reference)
        page.check("input[name=mode][value=json]")
        request = {key: value for key, value in estimate_request(128).items() if key != "model_id"}
        request["options"] = {"max_iterations": 2}
        page.fill("#request-json", json.dumps(request))
        page.click("#submit-button")
        page.wait_for_url(re.compile(r"/estimates/[0-9a-f]{32}$"))
        expect(page.locator("#status")).to_have_text("succeeded", timeout=ESTIMATE_TIMEOUT_S * 1000)
        assert image_size(tab, 'img[data-artifact="overlay_final"]') == (128, 128)
        tab.shot("estimate-with-key")

        page.click(".signout button")
        page.wait_for_url("**/session")
        page.goto("/models")
        page.wait_for_url("**/session?next=/models")
        tab.assert_clean()
    finally:
        page.context.close()
        api.terminate()
        api.wait(timeout=30)
