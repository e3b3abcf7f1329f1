"""Property-based fuzzing of the HTTP API from its OpenAPI schema: `schemathesis run` (every
phase: schema examples, coverage edge cases, random valid and invalid requests, stateful
sequences) against a live API (uvicorn, a private Redis database, API keys on, no workers).
No answer may be a server error, and the API's log must hold no traceback.

The deployment has no worker on purpose (nothing here should need one), so exactly one answer
is 503 by design and allowed: a *valid* ``POST /v1/renders`` ("no worker is running"). Any
other 5xx fails the test. Ids of a real job
and a real model are given to the operations that take them, so their found paths are fuzzed
too. PROXPOSE_FUZZ_EXAMPLES sets the examples per operation (default 60: ~1100 requests, ~40 s).
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import redis
from conftest import RedisServer, free_port, start_api
from PIL import Image

pytestmark = pytest.mark.slow

#: Redis database of this module.
DB = 6
KEY = "fuzz-key-0123456789abcdef"
FUZZ_EXAMPLES = int(os.environ.get("PROXPOSE_FUZZ_EXAMPLES", "60"))
CUBE_OBJ = (
    "".join(f"v {i & 1} {i >> 1 & 1} {i >> 2 & 1}\n" for i in range(8))
    + "f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\n"
    + "f 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\nf 2 4 6\nf 4 8 6\n"
).encode()

#: Loaded by schemathesis (SCHEMATHESIS_HOOKS): not_a_server_error, less the 503 above.
HOOKS = '''
import schemathesis

#: (method, path) -> what the body of its designed 503 says
DESIGNED = {("POST", "/v1/renders"): "no worker is running"}


@schemathesis.check
def no_server_error(ctx, response, case):
    """No 5xx, but for the 503 a worker-less deployment gives by design."""
    if response.status_code < 500:
        return None
    says = DESIGNED.get((case.method.upper(), case.path))
    if response.status_code == 503 and says is not None and says in response.text:
        return None
    raise AssertionError(f"{response.status_code} {case.method} {case.path}: {response.text[:300]}")
'''


def seed_data(base_url: str) -> dict[str, str]:
    """One queued estimate and one model of the fuzzing key, for the id parameters."""
    auth = {"Authorization": f"Bearer {KEY}"}
    model = httpx.post(
        f"{base_url}/v1/models", files={"file": ("cube.obj", CUBE_OBJ)}, headers=auth
    ).json()
    image = io.BytesIO()
    Image.new("RGB", (64, 64), (80, 80, 80)).save(image, format="PNG")
    request = {
        "model_id": model["id"],
        "camera": {"width": 64, "height": 64, "fx": 70.0, "fy": 70.0, "cx": 31.5, "cy": 31.5},
        "initial_pose": {"t": [0.0, 0.0, 4.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
    }
    job = httpx.post(
        f"{base_url}/v1/estimates",
        files={"image": ("ref.png", image.getvalue(), "image/png")},
        data={"request": json.dumps(request)},
        headers=auth,
    ).json()
    return {"job_id": job["id"], "model_id": model["id"]}


def config(ids: dict[str, str]) -> str:
    """schemathesis.toml: the real ids for the operations that read or delete one."""
    sections = [f"[generation]\nmax-examples = {FUZZ_EXAMPLES}\n"]
    for path, name in (
        ("/v1/estimates/{job_id}", "job_id"),
        ("/v1/estimates/{job_id}/artifacts/{name}", "job_id"),
        ("/v1/models/{model_id}", "model_id"),
    ):
        sections.append(
            f'[[operations]]\ninclude-path = "{path}"\n'
            f'parameters = {{ "path.{name}" = "{ids[name]}" }}\n'
        )
    return "\n".join(sections)


def test_schemathesis_finds_no_server_error(redis_server: RedisServer, tmp_path: Path) -> None:
    r = redis.Redis.from_url(redis_server.url(DB))
    r.flushdb()
    env = {
        **os.environ,
        "PROXPOSE_REDIS_URL": redis_server.url(DB),
        "PROXPOSE_DATA_DIR": str(tmp_path / "data"),
        "PROXPOSE_API_KEYS": f"fuzz:{KEY}",
        "PROXPOSE_SUBMISSIONS_PER_MINUTE": "0",  # validation answers, not the rate limiter
        "PROXPOSE_LOG_FORMAT": "text",
    }
    port = free_port()
    log = tmp_path / "api.log"
    api = start_api(env, log, port)
    base_url = f"http://127.0.0.1:{port}"
    (tmp_path / "fuzz_hooks.py").write_text(HOOKS)
    (tmp_path / "schemathesis.toml").write_text(config(seed_data(base_url)))
    try:
        run = subprocess.run(
            [
                *(sys.executable, "-m", "schemathesis.cli"),
                *("--config-file", str(tmp_path / "schemathesis.toml")),
                *("run", f"{base_url}/openapi.json"),
                *("--checks", "no_server_error", "--header", f"Authorization: Bearer {KEY}"),
                *("--request-timeout", "30", "--workers", "1", "--seed", "6"),
                "--continue-on-failure",
            ],
            env={**env, "SCHEMATHESIS_HOOKS": "fuzz_hooks", "PYTHONPATH": str(tmp_path)},
            cwd=tmp_path,  # its cache (.schemathesis/) stays out of the repository
            capture_output=True,
            text=True,
            timeout=600,
        )
    finally:
        api.terminate()
        api.wait(timeout=30)
        r.flushdb()
    report = run.stdout[-6000:] + run.stderr[-2000:]
    (tmp_path / "schemathesis.out").write_text(run.stdout)
    assert run.returncode == 0, report
    assert "generated" in run.stdout and "Server error" not in run.stdout, report
    server_log = log.read_text(errors="replace")
    assert "Traceback" not in server_log, server_log[-5000:]
