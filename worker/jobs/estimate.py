"""The RQ job functions (enqueued by name by the API) and the model files they need.

A job reads everything it needs from Redis (request, image, model bytes) and writes everything
back there (progress, result, artifacts), so a worker never needs the API's disk: workers on
other machines share only Redis. Model files are cached on the worker's disk by content hash,
and the engine caches loaded models per process (workers run jobs in-process, see runner.py).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import threading
import time
import traceback
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

import redis
from rq import get_current_job
from rq.timeouts import JobTimeoutException

from schemas.estimate import EstimateRequest, IterationRecord
from schemas.jobs import JobError, Progress
from schemas.models import ModelPublic
from schemas.render import RenderRequest
from schemas.settings import Settings, get_settings
from service.logs import log_context
from service.store import JobRecord, JobStats, JobStore, Keys, Leases, ModelStore, Reaper
from worker.engine.exceptions import EstimationCancelled, ProxposeError
from worker.entry import render_png, run_estimate

log = logging.getLogger(__name__)

#: Least time between two Redis reads of a job's cancel flag, s.
CANCEL_POLL_S = 0.2
#: Set by the worker process on a cold shutdown while a job runs (see worker.runner): the job
#: stops before its next render and goes back to the queue, instead of being interrupted by an
#: exception in the middle of whatever it was doing.
STOP_NOW = threading.Event()
#: How long a render's PNG and outcome wait in Redis for the API call that asked for it, s.
RENDER_RESULT_TTL_S = 300


class ModelNotFoundError(ProxposeError):
    """The job names a model that is not (or no longer) registered."""

    code = "model_not_found"


def _context() -> tuple[Settings, redis.Redis, Keys]:
    settings = get_settings()
    job = get_current_job()
    r = job.connection if job is not None else redis.Redis.from_url(settings.effective_redis_url())
    return settings, r, Keys(settings.redis_prefix)


def _worker_name() -> str:
    job = get_current_job()
    return (job.worker_name if job is not None else None) or f"pid-{os.getpid()}"


# ----------------------------------------------------------------------------- model files
def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def model_cache_path(data_dir: Path, model: ModelPublic) -> Path:
    """Where a worker keeps a model's file: by content hash, with the format's extension."""
    return Path(data_dir) / "cache" / "models" / f"{model.sha256}.{model.format}"


def fetch_model_file(models: ModelStore, model_id: str, data_dir: Path) -> Path:
    """The local path of a registered model's file, downloaded from Redis on first use."""
    meta = models.get(model_id)
    if meta is None:
        raise ModelNotFoundError(f"model '{model_id}' is not registered (was it deleted?)")
    path = model_cache_path(data_dir, meta)
    if path.is_file():
        return path
    data = models.data(model_id)
    if data is None or hashlib.sha256(data).hexdigest() != meta.sha256:
        raise ModelNotFoundError(f"the file of model '{model_id}' is missing from the store")
    _write_atomic(path, data)
    return path


def register_demo_model(r: redis.Redis, keys: Keys, data_dir: Path) -> ModelPublic:
    """Register the demo satellite as 'demo-sat' (generated on first use; idempotent)."""
    from worker.demo.satellite import DEMO_MODEL_ID, DEMO_MODEL_NAME, demo_satellite_path
    from worker.engine.meshes import load_model

    path = demo_satellite_path(Path(data_dir))
    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    models = ModelStore(r, keys)
    current = models.get(DEMO_MODEL_ID)
    if current is not None and current.sha256 == sha:
        meta = current
    else:
        loaded = load_model(path)
        meta = ModelPublic(
            id=DEMO_MODEL_ID,
            name=DEMO_MODEL_NAME,
            vertices=loaded.n_vertices,
            faces=loaded.n_faces,
            bounds=loaded.bounds.tolist(),
            textured=loaded.textured,
            format="glb",
            size_bytes=len(data),
            sha256=sha,
            created_at=datetime.now(UTC),
            builtin=True,
        )
        models.put(meta, data)
    if not model_cache_path(data_dir, meta).is_file():
        _write_atomic(model_cache_path(data_dir, meta), data)
    return meta


# ----------------------------------------------------------------------------- estimate job
class LeaseKeeper:
    """Renews the running job's lease from a thread (see ``service.store.leases``), so that a
    worker that dies is noticed; sets ``lost`` when the job has been taken from this attempt."""

    def __init__(self, leases: Leases, job_id: str, attempt: int) -> None:
        self.leases, self.job_id, self.attempt = leases, job_id, attempt
        self.lost = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"lease-{job_id}", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.leases.renew_interval_s):
            try:
                if not self.leases.renew(self.job_id, self.attempt):
                    log.warning("job %s: attempt %d no longer holds the job", *self._ids())
                    self.lost.set()
                    return
            except redis.RedisError as exc:
                log.warning(
                    "job %s: could not renew the lease of attempt %d: %s", *self._ids(), exc
                )

    def _ids(self) -> tuple[str, int]:
        return self.job_id, self.attempt

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


class CancelFlag:
    """``should_cancel`` for the engine, read before every render: true once a client asked the
    job to stop, this attempt no longer holds the job, the job's time is up, or the worker is
    stopping cold. ``reason`` says which; Redis is read at most every CANCEL_POLL_S."""

    def __init__(self, leases: Leases, keeper: LeaseKeeper, timeout_s: float) -> None:
        self.leases, self.keeper = leases, keeper
        self.deadline = time.monotonic() + timeout_s
        self.reason: str | None = None
        self._last_poll = float("-inf")

    def __call__(self) -> bool:
        if self.reason is None:
            self.reason = self._check()
        return self.reason is not None

    def _check(self) -> str | None:
        if STOP_NOW.is_set():
            return "stopped"
        if self.keeper.lost.is_set():
            return "superseded"
        now = time.monotonic()
        if now > self.deadline:
            return "timeout"
        if now - self._last_poll < CANCEL_POLL_S:
            return None
        self._last_poll = now
        owned, cancel = self.leases.check(self.keeper.job_id, self.keeper.attempt)
        if not owned:
            self.keeper.lost.set()
            return "superseded"
        return "cancelled" if cancel else None


def _interruption(exc: BaseException) -> BaseException | None:
    """A stop or a timeout signal in ``exc``'s chain: the signal handlers raise them wherever
    the worker is, and the renderer may wrap them (Dr.Jit turns them into a RuntimeError)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, SystemExit | KeyboardInterrupt | JobTimeoutException):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def run_estimate_job(job_id: str) -> None:
    """Run the estimate stored as job ``job_id`` (RQ entry point, enqueued by the API)."""
    settings, r, keys = _context()
    store = JobStore(r, keys, settings.retention_s)
    leases = Leases(store, settings.job_lease_s)
    job = get_current_job()
    worker = _worker_name()
    record = leases.start(job_id, worker, job.id if job is not None else "")
    if record is None:
        log.info("job %s is no longer queued (cancelled, expired or requeued): skipped", job_id)
        return
    attempt = record.attempts
    timeout_s = record.timeout_s or settings.job_timeout_s
    t0 = time.monotonic()
    status, code = "failed", None
    with log_context(job_id=job_id, attempt=attempt, worker=worker):
        log.info("job %s: attempt %d started (model %s)", job_id, attempt, record.model_id)
        with LeaseKeeper(leases, job_id, attempt) as keeper:
            flag = CancelFlag(leases, keeper, timeout_s)
            try:
                status, code = _estimate(store, flag, record, ModelStore(r, keys), settings)
            except BaseException as exc:
                status, code = _failed(store, leases, flag, record, exc, timeout_s, settings)
                if not isinstance(exc, Exception) or code == "internal_error":
                    raise  # a stop signal ends the worker; RQ keeps internal errors too
            finally:
                log.info("job %s: attempt %d ended: %s %s", job_id, attempt, status, code or "")
                if status not in ("superseded", "stopped"):
                    JobStats(r, keys).record("estimate", status, time.monotonic() - t0, code)


def _estimate(
    store: JobStore, flag: CancelFlag, record: JobRecord, models: ModelStore, settings: Settings
) -> tuple[str, str | None]:
    """Run the engine for a started job and store the outcome; (status, failure code). Errors
    other than a stop requested through ``flag`` propagate (see _failed)."""
    job_id, attempt = record.id, flag.keeper.attempt

    def on_iteration(rec: IterationRecord, max_iterations: int) -> None:
        progress = Progress(
            iteration=rec.iteration, max_iterations=max_iterations, cost=rec.cost, stage=rec.stage
        )
        if not flag.leases.set_progress(job_id, attempt, progress):
            flag.keeper.lost.set()

    request = EstimateRequest.model_validate_json(record.request)
    image = store.get_image(job_id)
    if image is None:
        raise ProxposeError("the job's image is missing from the store")
    model_path = fetch_model_file(models, record.model_id, settings.data_dir)
    try:
        result, artifacts = run_estimate(
            model_path, image, request, on_iteration, should_cancel=flag
        )
    except EstimationCancelled:
        if flag.reason != "cancelled":
            raise
        _finish(store, record, attempt, "cancelled")
        return "cancelled", None
    _finish(
        store,
        record,
        attempt,
        "succeeded",
        result_json=result.model_dump_json(),
        artifacts=artifacts,
    )
    return "succeeded", None


def _finish(store: JobStore, record: JobRecord, attempt: int, status: str, **outcome: Any) -> None:
    if not store.finish(record.id, status, attempt=attempt, **outcome):
        log.warning(
            "job %s: attempt %d was superseded; its %s is dropped", record.id, attempt, status
        )


def _failed(
    store: JobStore,
    leases: Leases,
    flag: CancelFlag,
    record: JobRecord,
    exc: BaseException,
    timeout_s: float,
    settings: Settings,
) -> tuple[str, str | None]:
    """Record why the attempt ended early; (status, failure code). A stopping worker gives the
    job back to the queue, a superseded attempt writes nothing, the rest fail the job."""
    attempt = flag.keeper.attempt
    interruption = _interruption(exc)
    reason = flag.reason if isinstance(exc, EstimationCancelled) else None
    if reason == "stopped" or isinstance(interruption, SystemExit | KeyboardInterrupt):
        log.warning(
            "job %s: the worker is stopping; attempt %d goes back to the queue", record.id, attempt
        )
        _give_back(leases, store, record.id, attempt, settings.job_max_attempts)
        return "stopped", None
    if reason == "superseded":
        log.warning("job %s: attempt %d stopped: another attempt holds the job", record.id, attempt)
        return "superseded", None
    if reason == "timeout" or isinstance(interruption, JobTimeoutException):
        message = f"the estimate ran longer than the job timeout ({timeout_s:g} s)"
        tb = traceback.format_exc()
        _finish(
            store,
            record,
            attempt,
            "failed",
            error=JobError(code="timeout", message=message),
            traceback=tb,
        )
        return "failed", "timeout"
    if isinstance(exc, ProxposeError):
        _finish(store, record, attempt, "failed", error=JobError(code=exc.code, message=str(exc)))
        return "failed", exc.code
    log.exception("job %s: internal error", record.id)
    message = "internal error in the worker (the traceback is in the job record)"
    error = JobError(code="internal_error", message=message)
    _finish(store, record, attempt, "failed", error=error, traceback=traceback.format_exc())
    return "failed", "internal_error"


def _give_back(
    leases: Leases, store: JobStore, job_id: str, attempt: int, max_attempts: int
) -> None:
    """Put the job of a stopping worker back in the queue now, instead of a lease later."""
    try:
        if leases.drop(job_id, attempt):
            Reaper(store, max_attempts).recover(job_id, why="its worker is stopping")
    except redis.RedisError as exc:  # the lease lapses and a reaper requeues it
        log.warning("job %s: could not requeue it now (%s); a reaper will", job_id, exc)


# ----------------------------------------------------------------------------- render job
def run_render_job(render_id: str, model_id: str, request_json: str) -> None:
    """Render once and hand the PNG to the waiting API call (RQ entry point)."""
    settings, r, keys = _context()
    t0 = time.monotonic()
    outcome: dict[str, object] = {"status": "failed"}
    try:
        request = RenderRequest.model_validate_json(request_json)
        path = fetch_model_file(ModelStore(r, keys), model_id, settings.data_dir)
        png = render_png(path, request)
        r.set(keys.render_png(render_id), png, ex=RENDER_RESULT_TTL_S)
        outcome = {"status": "succeeded"}
    except ProxposeError as exc:
        outcome["error"] = {"code": exc.code, "message": str(exc)}
    except JobTimeoutException:
        message = f"the render ran longer than {settings.render_timeout_s:g} s"
        outcome["error"] = {"code": "timeout", "message": message}
        raise
    except Exception:
        log.exception("render %s: internal error", render_id)
        message = "internal error in the worker (the traceback is in the worker's log)"
        outcome["error"] = {"code": "internal_error", "message": message}
        raise
    finally:
        pipe = r.pipeline()
        pipe.rpush(keys.render_done(render_id), json.dumps(outcome))
        pipe.expire(keys.render_done(render_id), RENDER_RESULT_TTL_S)
        pipe.execute()
        error = outcome.get("error")
        code = error["code"] if isinstance(error, dict) else None
        JobStats(r, keys).record("render", str(outcome["status"]), time.monotonic() - t0, code)
