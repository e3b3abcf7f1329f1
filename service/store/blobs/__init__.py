"""The blob store: the service's bytes (reference images, artifact PNGs, model files) out of
Redis. A filesystem directory by default, an S3-compatible bucket when the API and the workers
run on different machines; Redis keeps the names, hashes and sizes (``service.store.jobs``,
``service.store.models``). The sweeper (``sweeper``) deletes what no job or model refers to;
``migrate`` moves the bytes an older deployment kept in Redis.
"""

from __future__ import annotations

from pathlib import Path

from schemas.settings import Settings
from service.store.blobs.base import (
    BlobEntry,
    BlobOps,
    BlobStore,
    BlobStoreError,
    BlobStoreUnavailable,
    CountingBlobStore,
    artifact_media_type,
    job_artifact_name,
    job_image_name,
    job_input_name,
    job_prefix,
    model_file_name,
)
from service.store.blobs.files import FileBlobStore
from service.store.blobs.s3 import S3BlobStore


def open_blob_store(settings: Settings) -> CountingBlobStore:
    """The blob store the settings name (``effective_blob_store``), counting its operations."""
    url = settings.effective_blob_store()
    inner: BlobStore
    if url.startswith("file://"):
        inner = FileBlobStore(Path(url.removeprefix("file://")))
    else:
        bucket, _, prefix = url.removeprefix("s3://").partition("/")
        inner = S3BlobStore(
            bucket,
            prefix,
            endpoint_url=settings.s3_endpoint_url,
            region=settings.s3_region,
            access_key_id=settings.s3_access_key_id,
            secret_access_key=settings.s3_secret_access_key,
            timeout_s=settings.blob_timeout_s,
        )
    return CountingBlobStore(inner)


__all__ = [
    "BlobEntry",
    "BlobOps",
    "BlobStore",
    "BlobStoreError",
    "BlobStoreUnavailable",
    "CountingBlobStore",
    "FileBlobStore",
    "S3BlobStore",
    "artifact_media_type",
    "job_artifact_name",
    "job_image_name",
    "job_input_name",
    "job_prefix",
    "model_file_name",
    "open_blob_store",
]
