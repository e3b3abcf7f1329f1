"""``proxpose worker``: an RQ worker for the render and estimate queues on PROXPOSE_REDIS_URL.

Start as many as the machine has cores for, on any machine that reaches the Redis: that is how
the service scales out. Jobs run in the worker process itself (RQ's SimpleWorker, no fork per
job), so the Mitsuba variant is chosen once, kernels and loaded models stay warm across jobs,
and no forked child inherits Dr.Jit's thread pool. A stop signal lets the current job finish
(warm shutdown); another one, more than a second after the first was handled, stops the job
(it goes back to the queue). Handlers run between renders, so repeat the signal.

Because a job runs in the worker process, a crash of the job (segfault, out of memory) is a
crash of the worker. The job survives it: its lease lapses and a reaper requeues it for another
worker (``service.store.leases``). Every worker runs that reaper in a maintenance thread, which
also keeps the worker's own RQ heartbeat short while a job runs, so that a dead worker leaves
``/readyz`` within WORKER_TTL_S, and sweeps the blob store (one worker per ``blob_sweep_s``:
``service.store.blobs.sweeper``). A worker that starts while the blob store is down still
serves; it registers the demo model once the store answers.
"""

from __future__ import annotations

import argparse
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import redis

    from schemas.models import ModelPublic
    from schemas.settings import Settings
    from service.store.blobs import BlobStore

log = logging.getLogger(__name__)

#: Worker registration TTL, s: a worker that vanishes drops out of /readyz within about this.
WORKER_TTL_S = 60
#: How long a starting worker waits for Redis to answer, s.
REDIS_WAIT_S = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--redis-url", help="Redis to serve (default: $PROXPOSE_REDIS_URL, else the embedded one)"
    )
    parser.add_argument("--name", help="worker name (default: <hostname>-<pid>)")
    parser.add_argument(
        "--burst", action="store_true", help="quit when the queues are empty instead of waiting"
    )
    parser.add_argument(
        "--no-warmup", action="store_true", help="skip the tiny render that warms the renderer"
    )


def run(args: argparse.Namespace) -> int:
    import redis
    from rq.serializers import JSONSerializer

    from schemas.settings import get_settings
    from service.logs import configure_logging
    from service.store import Keys, Queues
    from service.store.budget import warn_if_unbounded
    from worker.entry import init_renderer_backend
    from worker.jobs.context import job_blobs
    from worker.jobs.priority import lower_priority

    settings = get_settings()
    configure_logging(settings.log_format, replace=True)  # not the CLI's text handler
    url = args.redis_url or settings.effective_redis_url()
    r = _connect(redis.Redis.from_url(url), url)
    if r is None:
        return 1
    keys = Keys(settings.redis_prefix)
    warn_if_unbounded(r, "worker")
    lower_priority(settings.worker_nice)  # before the renderer's threads start: they inherit it
    variant = init_renderer_backend()
    demo = DemoRegistration(r, keys, settings)
    log.info("renderer variant %s", variant)
    if demo.register() and demo.model is not None and not args.no_warmup:
        _warm_up(settings.data_dir, demo.model)
    _forget_dead_local_workers(r)
    name = args.name or f"{socket.gethostname()}-{os.getpid()}"
    return _work_through_outages(
        lambda: _worker_class()(
            Queues(r, keys).all(),
            connection=r,
            name=name,
            serializer=JSONSerializer,
            worker_ttl=WORKER_TTL_S,
        ),
        r,
        lambda worker: Maintenance(worker, r, settings, job_blobs(settings), demo),
        args.burst,
    )


def _work_through_outages(
    make_worker: Callable[[], Any],
    r: redis.Redis,
    maintenance: Callable[[Any], Maintenance],
    burst: bool,
) -> int:
    """RQ's work loop, started again whenever it ends for a Redis outage (RQ quits on one):
    wait for Redis with capped backoff, clear this worker's stale registration, go on. It ends
    on a stop signal, or in burst mode when the queues are empty."""
    import redis as redis_lib
    from rq.exceptions import StopRequested

    from worker.jobs.lease import STOP_NOW
    from worker.jobs.outage import OUTAGE_BACKOFF_MAX_S, OutageNotice, is_outage, wait_for_redis

    notice = OutageNotice("worker")
    rq_log = logging.getLogger("rq.worker")
    for kind in (_RepeatedRetryFilter, _OutageQuitFilter):
        if not any(isinstance(f, kind) for f in rq_log.filters):
            rq_log.addFilter(kind())
    restarts = 0
    while True:
        worker = make_worker()
        started = time.monotonic()
        failure: BaseException | None = None
        try:
            with maintenance(worker):
                worker.work(burst=burst, logging_level="INFO")
        except redis_lib.RedisError as exc:  # raised from RQ's teardown, Redis being away
            failure = exc
        if worker.stop_signalled or STOP_NOW.is_set() or (burst and failure is None):
            return 0
        if failure is not None and not is_outage(failure):
            raise failure
        try:
            redis_ok = wait_for_redis(r, notice, lambda w=worker: bool(w.stop_signalled))
            # RQ also quits on errors of its own; do not spin if Redis was fine all along
            quick = time.monotonic() - started < 5.0
            restarts = restarts + 1 if quick else 0
            time.sleep(min(OUTAGE_BACKOFF_MAX_S, 0.5 * restarts))
        except (StopRequested, KeyboardInterrupt):
            return 0
        if not redis_ok or worker.stop_signalled:
            return 0
        log.warning(
            "worker %s: RQ's work loop ended (Redis outage); starting it again", worker.name
        )
        _forget_worker(r, worker)


def _forget_worker(r: redis.Redis, worker: Any) -> None:
    """Drop ``worker``'s registration (a restarted loop registers the same name again, and RQ
    refuses a name whose key is still alive)."""
    from rq.worker_registration import unregister

    pipe = r.pipeline()
    unregister(worker, pipe)
    pipe.delete(worker.key)
    pipe.execute()


class _RepeatedRetryFilter(logging.Filter):
    """RQ logs "could not connect to Redis instance ... retrying" on every retry of its wait
    for a job: let one through per outage (one quiet minute ends an outage)."""

    QUIET_S = 60.0

    def __init__(self) -> None:
        super().__init__()
        self.last = float("-inf")

    def filter(self, record: logging.LogRecord) -> bool:
        if "could not connect to Redis" not in record.getMessage():
            return True
        now, last = time.monotonic(), self.last
        self.last = now
        return now - last > self.QUIET_S


class _OutageQuitFilter(logging.Filter):
    """RQ logs "found an unhandled exception, quitting..." with a traceback when Redis goes away
    under its work loop; for an outage that is not news (the outage notice logs it once, and the
    loop is started again), so drop that record. Any other exception still gets it."""

    def filter(self, record: logging.LogRecord) -> bool:
        from worker.jobs.outage import is_outage

        if "unhandled exception, quitting" not in record.getMessage():
            return True
        exc = record.exc_info[1] if record.exc_info else None
        return exc is None or not is_outage(exc)


def _worker_class() -> type[Any]:
    """RQ's SimpleWorker that tells the maintenance thread when it is running a job."""
    from rq import SimpleWorker

    from worker.jobs.lease import STOP_NOW

    class ProxposeWorker(SimpleWorker):
        busy = threading.Event()
        #: A stop signal arrived (RQ's own flag stays unset when it stops an idle worker).
        stop_signalled = False

        def request_stop(self, signum: int, frame: Any) -> None:
            self.stop_signalled = True
            super().request_stop(signum, frame)

        def execute_job(self, job: Any, queue: Any) -> None:
            self.busy.set()
            try:
                super().execute_job(job, queue)
            finally:
                self.busy.clear()

        def request_force_stop(self, signum: int, frame: Any) -> None:
            self.stop_signalled = True
            # RQ raises SystemExit from the signal handler, wherever the job is (inside a
            # render, a Redis write); instead, a running job stops before its next render and
            # goes back to the queue, then the worker exits as after a warm stop
            if self.busy.is_set():
                self.log.warning("Worker %s: cold shut down: the running job goes back", self.name)
                STOP_NOW.set()
                self._stop_requested = True
                return
            super().request_force_stop(signum, frame)

    return ProxposeWorker


class DemoRegistration:
    """The demo model's registration, retried until the blob store takes its file."""

    def __init__(self, r: redis.Redis, keys: Any, settings: Settings) -> None:
        self.r, self.keys, self.settings = r, keys, settings
        self.model: ModelPublic | None = None

    def register(self) -> bool:
        """Register it unless done; whether it is registered."""
        from service.store.blobs import BlobStoreUnavailable
        from worker.jobs.context import job_blobs
        from worker.jobs.models import register_demo_model

        if self.model is not None:
            return True
        try:
            blobs = job_blobs(self.settings)
            self.model = register_demo_model(self.r, self.keys, self.settings.data_dir, blobs)
        except BlobStoreUnavailable as exc:
            log.error("%s: the demo model is not registered yet (retried)", exc)
            return False
        log.info("model '%s' registered", self.model.id)
        return True


class Maintenance:
    """A thread beside the worker: every sweep_s it recovers the jobs of dead workers and
    shortens the TTL of this worker's RQ registration to WORKER_TTL_S (RQ sets 2 min when idle,
    and the job timeout + 60 s while a job runs in-process), so that a killed worker leaves
    /readyz within about a minute. EXPIRE is a no-op once the worker has unregistered. It also
    sweeps the blob store when no other worker did within blob_sweep_s, and registers the demo
    model if the blob store was down when the worker started."""

    def __init__(
        self,
        worker: Any,
        r: redis.Redis,
        settings: Settings,
        blobs: BlobStore,
        demo: DemoRegistration | None = None,
    ) -> None:
        from service.store import JobStore, Keys, Reaper
        from service.store.blobs.sweeper import BlobSweeper

        keys = Keys(settings.redis_prefix)
        store = JobStore(r, keys, settings.retention_s, blobs=blobs)
        self.reaper = Reaper(store, settings.job_max_attempts)
        self.sweeper = BlobSweeper(r, keys, blobs)
        self.blob_sweep_s = settings.blob_sweep_s
        self.demo = demo
        self.worker, self.r = worker, r
        self.sweep_s = max(0.5, settings.job_lease_s / 6.0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="maintenance", daemon=True)

    def _run(self) -> None:
        import redis

        from service.store.blobs import BlobStoreError
        from worker.jobs.outage import OUTAGE_ERRORS, OutageNotice

        notice = OutageNotice("maintenance")
        while not self._stop.wait(self.sweep_s):
            try:
                self.reaper.sweep()
                self.reaper.sweep_orphans()
                self.r.expire(self.worker.key, WORKER_TTL_S)
                if self.demo is not None:
                    self.demo.register()
                self.sweeper.sweep_if_due(self.blob_sweep_s)
                notice.ok()
            except OUTAGE_ERRORS as exc:  # once per outage, not every sweep
                notice.failed(exc)
            except redis.RedisError as exc:
                log.warning("maintenance: Redis error: %s", exc)
            except BlobStoreError as exc:
                log.warning("maintenance: %s", exc)
            except Exception:  # never let the thread die: it guards the other workers' jobs
                log.exception("maintenance: unexpected error")

    def __enter__(self) -> Maintenance:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)


def _connect(r: redis.Redis, url: str) -> redis.Redis | None:
    """``r`` once Redis answers a PING (waiting up to REDIS_WAIT_S), else None."""
    import redis

    deadline = time.monotonic() + REDIS_WAIT_S
    while True:
        try:
            r.ping()
            return r
        except redis.ConnectionError as exc:
            if time.monotonic() > deadline:
                log.error("Redis at %s does not answer (%s); set PROXPOSE_REDIS_URL", url, exc)
                return None
            time.sleep(0.5)


def _forget_dead_local_workers(r: redis.Redis) -> None:
    """Unregister workers of this host whose process is gone (killed, crashed), so that
    /readyz does not count them until their heartbeat key expires."""
    from rq import Worker
    from rq.worker_registration import unregister

    host = socket.gethostname()
    for worker in Worker.all(connection=r):
        if worker.hostname != host or worker.pid in (None, os.getpid()):
            continue
        try:
            os.kill(worker.pid, 0)
        except ProcessLookupError:
            log.info("unregistering worker %s (process %d is gone)", worker.name, worker.pid)
            pipe = r.pipeline()
            unregister(worker, pipe)
            pipe.delete(worker.key)
            pipe.execute()
        except PermissionError:
            pass  # alive, another user's


def _warm_up(data_dir: Path, demo: ModelPublic) -> None:
    """One tiny render of the demo model: loads it and compiles the renderer's kernels."""
    from schemas import Camera, Pose, RenderRequest
    from worker.entry import render_png
    from worker.jobs.models import model_cache_path

    t0 = time.monotonic()
    camera = Camera(width=64, height=64, fx=64.0, fy=64.0, cx=31.5, cy=31.5)
    request = RenderRequest(camera=camera, pose=Pose(t=[0.0, 0.0, 40.0], q=[0.3, 0.2, 0.1]), spp=1)
    render_png(model_cache_path(data_dir, demo), request)
    log.info("warm-up render in %.1f s", time.monotonic() - t0)
