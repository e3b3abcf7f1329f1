"""An API process with PROXPOSE_LOG_FORMAT=json writes nothing but JSON lines, uvicorn's own
included (started as `proxpose serve` starts it, with the log config it writes), and its access
lines carry the request's method, path and status as keys."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
from conftest import REPO, RedisServer, free_port

from service.logs import uvicorn_log_config


def test_uvicorn_lines_are_json_with_access_fields(
    redis_server: RedisServer, tmp_path: Path
) -> None:
    config = tmp_path / "logging.json"
    config.write_text(json.dumps(uvicorn_log_config("json")))
    env = dict(os.environ, PROXPOSE_REDIS_URL=redis_server.url(13), PROXPOSE_LOG_FORMAT="json")
    port = free_port()
    argv = [sys.executable, "-m", "uvicorn", "service.main:app", "--port", str(port)]
    log = tmp_path / "api.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [*argv, "--log-config", str(config)], env=env, cwd=REPO, stdout=out, stderr=out
        )
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0)
                    break
                except httpx.TransportError:
                    assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
                    time.sleep(0.1)
            httpx.get(f"http://127.0.0.1:{port}/v1/estimates/{'0' * 32}")
            time.sleep(0.3)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    entries = [json.loads(line) for line in lines]  # every line is JSON
    assert any("Uvicorn running" in e["msg"] or "Started server" in e["msg"] for e in entries)
    access = [e for e in entries if e["logger"] == "uvicorn.access"]
    miss = [e for e in access if e.get("path") == "/v1/estimates/" + "0" * 32]
    assert miss and miss[0]["method"] == "GET" and miss[0]["status"] == 404, access
