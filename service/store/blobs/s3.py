"""The S3-compatible blob store (AWS S3, MinIO, Ceph RGW, ...), through boto3.

Used when the API and the workers run on different machines: they then share the bucket as
they share Redis. A PUT is atomic on S3 (an object is visible whole or not at all). Credentials
come from the settings, else from boto3's usual chain (``AWS_ACCESS_KEY_ID``, a profile, an
instance role). The bucket must exist (``docker/compose.yaml`` creates it for MinIO).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

from service.store.blobs.base import BlobEntry, BlobStoreUnavailable, check_name

#: Keys per DeleteObjects request (the S3 API's maximum).
DELETE_BATCH = 1000
#: Error codes of a GET that mean "no such blob", not "the store is broken".
_MISSING = {"NoSuchKey", "404", "NotFound"}


class S3BlobStore:
    """Blobs as objects ``<prefix><name>`` in ``bucket``."""

    def __init__(
        self,
        bucket: str,
        prefix: str = "",
        *,
        endpoint_url: str | None = None,
        region: str | None = None,
        access_key_id: str | None = None,
        secret_access_key: str | None = None,
        timeout_s: float = 10.0,
    ) -> None:
        import boto3
        from botocore.config import Config

        self.bucket = bucket
        self.prefix = f"{prefix.strip('/')}/" if prefix.strip("/") else ""
        where = f" at {endpoint_url}" if endpoint_url else ""
        self.url = f"s3://{bucket}/{self.prefix}{where}"
        self.description = f"S3 bucket '{bucket}'"
        config = Config(
            connect_timeout=timeout_s,
            read_timeout=timeout_s,
            retries={"max_attempts": 2, "mode": "standard"},
        )
        self.client: Any = boto3.session.Session().client(
            "s3",
            endpoint_url=endpoint_url,
            region_name=region,
            aws_access_key_id=access_key_id,
            aws_secret_access_key=secret_access_key,
            config=config,
        )

    def _unavailable(self, exc: Exception) -> BlobStoreUnavailable:
        from botocore.exceptions import ClientError

        if isinstance(exc, ClientError):
            error = exc.response.get("Error", {})
            reason = f"{error.get('Code', '?')}: {error.get('Message', '')}".rstrip(": ")
        else:
            reason = str(exc)
        return BlobStoreUnavailable(self.description, reason)

    def _errors(self) -> tuple[type[Exception], ...]:
        from botocore.exceptions import BotoCoreError, ClientError

        return (BotoCoreError, ClientError)

    def put(self, name: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        key = self.prefix + check_name(name)
        try:
            self.client.put_object(Bucket=self.bucket, Key=key, Body=data, ContentType=content_type)
        except self._errors() as exc:
            raise self._unavailable(exc) from exc

    def get(self, name: str) -> bytes | None:
        from botocore.exceptions import ClientError

        key = self.prefix + check_name(name)
        try:
            response = self.client.get_object(Bucket=self.bucket, Key=key)
            return response["Body"].read()  # type: ignore[no-any-return]
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in _MISSING:
                return None
            raise self._unavailable(exc) from exc
        except self._errors() as exc:
            raise self._unavailable(exc) from exc

    def delete(self, names: Iterable[str]) -> None:
        keys = [self.prefix + check_name(n) for n in names]
        try:
            for i in range(0, len(keys), DELETE_BATCH):
                batch = [{"Key": k} for k in keys[i : i + DELETE_BATCH]]
                response = self.client.delete_objects(
                    Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True}
                )
                if response.get("Errors"):
                    first = response["Errors"][0]
                    reason = f"delete of {first.get('Key')} failed: {first.get('Code')}"
                    raise BlobStoreUnavailable(self.description, reason)
        except self._errors() as exc:
            raise self._unavailable(exc) from exc

    def list(self, prefix: str) -> Iterator[BlobEntry]:
        paginator = self.client.get_paginator("list_objects_v2")
        try:
            for page in paginator.paginate(Bucket=self.bucket, Prefix=self.prefix + prefix):
                for obj in page.get("Contents", []):
                    name = obj["Key"][len(self.prefix) :]
                    yield BlobEntry(name, int(obj["Size"]), obj["LastModified"].timestamp())
        except self._errors() as exc:
            raise self._unavailable(exc) from exc

    def ping(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except self._errors() as exc:
            raise self._unavailable(exc) from exc
