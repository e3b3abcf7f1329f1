"""``pip install proxpose`` (no extras) in a fresh virtualenv gives a working client: it has
neither FastAPI nor Mitsuba, OpenCV or numpy, and yet submits an estimate to a running stack
(the API and a real `proxpose worker` on a real Redis), streams its progress, waits for it and
downloads the difference image; the remote CLI verbs work there too.

The install resolves the client's few dependencies with the lock file as constraints (what the
test suite ran against); pip's index is whatever this machine's pip is configured with."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO
from e2e_helpers import (
    Stack,
    assert_png,
    e2e_stack,  # noqa: F401 (the stack fixture)
    estimate_request,
    failure,
)

pytestmark = pytest.mark.slow

#: Seconds the install may take (build of the project's wheel, the few dependencies).
INSTALL_TIMEOUT_S = 600
#: What the client must not bring along.
HEAVY = ("fastapi", "starlette", "uvicorn", "numpy", "mitsuba", "drjit", "cv2", "redis", "rq")

SCRIPT = """
import json, sys
from service.client import Client, BadRequest

url, image, request_path, out = sys.argv[1:5]
request = json.loads(open(request_path).read())
heavy = [m for m in {heavy!r} if m in sys.modules]
with Client(url) as api:
    try:
        api.submit_estimate(image, dict(request, camera=dict(request["camera"], fx=-1)))
        refused = None
    except BadRequest as exc:
        refused = {{"code": exc.code, "locs": [e.loc for e in exc.errors]}}
    job = api.submit_estimate(image, request)
    events = [e.kind for e in api.events(job.id)]
    job = api.wait(job.id)
    png = api.artifact(job.id, "difference") if job.status == "succeeded" else b""
    open(out, "wb").write(png)
    heavy += [m for m in {heavy!r} if m in sys.modules]
    print(json.dumps({{"id": job.id, "status": job.status, "events": events, "refused": refused,
                      "iterations": job.result.iterations if job.result else None,
                      "error": job.error.model_dump() if job.error else None, "heavy": heavy}}))
"""


@pytest.fixture(scope="module")
def client_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    venv = tmp_path_factory.mktemp("client-venv") / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet"]
    subprocess.run(
        [*pip, "-c", str(REPO / "requirements.lock"), str(REPO)],
        check=True,
        timeout=INSTALL_TIMEOUT_S,
        cwd=tmp_path_factory.getbasetemp(),
    )
    return venv


def test_the_client_alone_installs_without_the_engine_or_the_web_stack(client_venv: Path) -> None:
    python = str(client_venv / "bin" / "python")
    probe = f"import importlib.util as u; print([m for m in {HEAVY!r} if u.find_spec(m)])"
    found = subprocess.run([python, "-c", probe], capture_output=True, text=True, check=True)
    assert found.stdout.strip() == "[]", found.stdout
    version = subprocess.run(
        [str(client_venv / "bin" / "proxpose"), "--version"], capture_output=True, text=True
    )
    assert version.returncode == 0 and version.stdout.startswith("proxpose 0"), version


def test_a_client_only_venv_runs_an_estimate_end_to_end(
    client_venv: Path, stack: Stack, tmp_path: Path
) -> None:
    stack.workers.ensure(1)
    (tmp_path / "ref.png").write_bytes(stack.references["ref128"])
    request = estimate_request(128, max_iterations=4)
    (tmp_path / "request.json").write_text(json.dumps(request))
    url = str(stack.api.base_url).rstrip("/")
    script = SCRIPT.format(heavy=HEAVY)
    run = subprocess.run(
        [
            str(client_venv / "bin" / "python"),
            "-c",
            script,
            url,
            "ref.png",
            "request.json",
            "d.png",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr + failure(stack)
    outcome = json.loads(run.stdout)
    assert outcome["status"] == "succeeded", outcome | {"logs": failure(stack)}
    assert outcome["heavy"] == []
    assert outcome["refused"] == {
        "code": "validation_error",
        "locs": [["body", "request", "camera", "fx"]],
    }
    assert outcome["events"][-1] == "end" and outcome["events"].count("progress") >= 1
    assert outcome["iterations"] >= 1
    assert_png((tmp_path / "d.png").read_bytes())

    proxpose = [str(client_venv / "bin" / "proxpose")]
    common = ["--url", url]
    submitted = subprocess.run(
        [*proxpose, "submit", *common, "--image", "ref.png", "--request", "request.json", "--json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert submitted.returncode == 0, submitted.stderr
    job_id = json.loads(submitted.stdout)["id"]
    waited = subprocess.run(
        [*proxpose, "wait", *common, job_id, "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert waited.returncode == 0, waited.stderr + failure(stack)
    assert json.loads(waited.stdout)["status"] == "succeeded"
    fetched = subprocess.run(
        [*proxpose, "fetch", *common, job_id, "difference", "-o", "cli.png"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert fetched.returncode == 0, fetched.stderr
    assert_png((tmp_path / "cli.png").read_bytes())
