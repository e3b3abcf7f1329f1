"""What every job function needs first: the settings, the Redis client its RQ job came on, the
key names, the blob store, and the name of the worker running it."""

from __future__ import annotations

import os

import redis
from rq import get_current_job

from schemas.settings import Settings, get_settings
from service.store import Keys
from service.store.blobs import CountingBlobStore, open_blob_store

#: The blob store of each configured URL, opened once per process (boto3 clients are costly).
_BLOB_STORES: dict[str, CountingBlobStore] = {}


def job_context() -> tuple[Settings, redis.Redis, Keys]:
    """The settings, the Redis of the running RQ job (else the configured one) and its keys."""
    settings = get_settings()
    job = get_current_job()
    r = job.connection if job is not None else redis.Redis.from_url(settings.effective_redis_url())
    return settings, r, Keys(settings.redis_prefix)


def job_blobs(settings: Settings) -> CountingBlobStore:
    """The process's blob store for ``settings`` (opened on first use)."""
    url = settings.effective_blob_store()
    key = f"{url} {settings.s3_endpoint_url}"
    if key not in _BLOB_STORES:
        _BLOB_STORES[key] = open_blob_store(settings)
    return _BLOB_STORES[key]


def worker_name() -> str:
    """The RQ worker's name running this job, else ``pid-<pid>`` (a job run by hand)."""
    job = get_current_job()
    return (job.worker_name if job is not None else None) or f"pid-{os.getpid()}"
