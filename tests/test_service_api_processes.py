"""``PROXPOSE_API_PROCESSES=2``: ``proxpose serve`` runs two API processes (uvicorn --workers)
and ``/metrics`` adds up the HTTP figures of both (Prometheus multiprocess mode), whichever
process answers the scrape."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from conftest import REPO, free_port

pytestmark = pytest.mark.slow

#: Requests made, each on a new connection (so both processes take some).
REQUESTS = 60


def test_two_api_processes_share_their_metrics(tmp_path: Path) -> None:
    port, data_dir = free_port(), tmp_path / "data"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PROXPOSE_", "PROMETHEUS_"))}
    env |= {
        "PROXPOSE_PORT": str(port),
        "PROXPOSE_EMBEDDED_REDIS_PORT": str(free_port()),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PROXPOSE_API_PROCESSES": "2",
    }
    log = tmp_path / "serve.log"
    with open(log, "ab") as out:
        serve = subprocess.Popen(
            [sys.executable, "-m", "worker.cli", "serve", "--workers", "0"],
            env=env,
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60.0
        while "API on http" not in log.read_text():
            assert serve.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        time.sleep(1.0)  # the second process is up too
        for _ in range(REQUESTS):
            assert httpx.get(f"{url}/healthz", timeout=5.0).status_code == 200
        pattern = (
            r'proxpose_http_requests_total\{method="GET",route="/healthz",status="200"\} (\S+)'
        )
        counts = []
        for _ in range(6):  # on new connections: both processes answer scrapes
            text = httpx.get(f"{url}/metrics", timeout=5.0).text
            counts.append(float(re.search(pattern, text)[1]))  # type: ignore[index]
        files = sorted(p.name for p in (data_dir / "prometheus").glob("counter_*.db"))
    finally:
        serve.send_signal(signal.SIGINT)
        try:
            serve.wait(timeout=30)
        except subprocess.TimeoutExpired:
            serve.kill()
            serve.wait()
    # /healthz of the supervisor's own start-up probe counts too: at least REQUESTS, and equal
    # in every scrape (each adds up both processes' files)
    assert len(set(counts)) == 1 and counts[0] >= REQUESTS, counts
    assert len(files) == 2, files  # one counter file per API process: both answered
