"""Blob store fixtures: a real S3-compatible server (moto's standalone server, a separate
process on a free port, spoken to over HTTP by boto3: no mock of the client), its settings, and
a ``blobs`` fixture that runs a test on each backend."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import free_port

from service.store.blobs import BlobStore, FileBlobStore, S3BlobStore

#: Credentials the moto server accepts (any will do; they must only be present).
S3_KEY_ID, S3_SECRET = "proxpose-test", "proxpose-test-secret"


@dataclass
class S3Server:
    endpoint_url: str
    proc: subprocess.Popen[bytes]

    def client(self) -> object:
        import boto3

        return boto3.session.Session().client(
            "s3",
            endpoint_url=self.endpoint_url,
            region_name="us-east-1",
            aws_access_key_id=S3_KEY_ID,
            aws_secret_access_key=S3_SECRET,
        )

    def new_bucket(self) -> str:
        bucket = f"proxpose-{uuid.uuid4().hex[:12]}"
        self.client().create_bucket(Bucket=bucket)  # type: ignore[attr-defined]
        return bucket

    def env(self, bucket: str, prefix: str = "blobs") -> dict[str, str]:
        """The PROXPOSE_* settings of a store in ``bucket`` of this server."""
        return {
            "PROXPOSE_BLOB_STORE": f"s3://{bucket}/{prefix}",
            "PROXPOSE_S3_ENDPOINT_URL": self.endpoint_url,
            "PROXPOSE_S3_REGION": "us-east-1",
            "PROXPOSE_S3_ACCESS_KEY_ID": S3_KEY_ID,
            "PROXPOSE_S3_SECRET_ACCESS_KEY": S3_SECRET,
        }

    def store(self, bucket: str, prefix: str = "blobs", **kw: float) -> S3BlobStore:
        return S3BlobStore(
            bucket,
            prefix,
            endpoint_url=self.endpoint_url,
            region="us-east-1",
            access_key_id=S3_KEY_ID,
            secret_access_key=S3_SECRET,
            **kw,
        )


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """``python -m moto.server`` on a free port for the session."""
    import httpx

    port = free_port()
    log = open(tmp_path_factory.mktemp("moto") / "moto.log", "wb")  # noqa: SIM115
    argv = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
    proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60.0
    while True:
        try:
            httpx.get(f"{url}/moto-api/", timeout=1.0)
            break
        except httpx.TransportError:
            if time.monotonic() > deadline or proc.poll() is not None:
                proc.kill()
                pytest.fail("the moto S3 server did not start")
            time.sleep(0.1)
    yield S3Server(url, proc)
    proc.terminate()
    proc.wait(timeout=10)


@pytest.fixture(params=["file", "s3"])
def backend(request: pytest.FixtureRequest) -> str:
    """Each test asking for it runs once per backend."""
    return str(request.param)


def backend_env(backend: str, tmp_path: Path, s3: S3Server | None) -> dict[str, str]:
    """Settings of a fresh store of ``backend`` (file: under ``tmp_path``)."""
    if backend == "file":
        return {"PROXPOSE_BLOB_STORE": f"file://{tmp_path / 'blob-store'}"}
    assert s3 is not None
    return s3.env(s3.new_bucket())


def make_store(backend: str, tmp_path: Path, s3: S3Server | None) -> BlobStore:
    if backend == "file":
        return FileBlobStore(tmp_path / "blob-store")
    assert s3 is not None
    return s3.store(s3.new_bucket())
