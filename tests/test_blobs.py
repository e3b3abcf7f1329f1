"""The blob store backends (service/store/blobs), each against the real thing: a directory, and
an S3-compatible server process (moto's) over HTTP. The same contract on both: round trips,
overwrites, listing, deletes, names that cannot escape the store, atomic writes, and a store
that is down or missing raising BlobStoreUnavailable rather than anything else."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from blob_helpers import S3Server, make_store, s3_server  # noqa: F401 (fixture)
from blob_helpers import backend as backend  # noqa: F401 (fixture)
from pydantic import ValidationError

from schemas.settings import Settings
from service.store.blobs import (
    BlobStore,
    BlobStoreUnavailable,
    CountingBlobStore,
    FileBlobStore,
    S3BlobStore,
    open_blob_store,
)
from service.store.blobs.files import STALE_TMP_S, TMP_PREFIX

PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 40


@pytest.fixture(name="blobs")
def blob_store(backend: str, tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[BlobStore]:
    s3 = request.getfixturevalue("s3_server") if backend == "s3" else None
    yield make_store(backend, tmp_path, s3)


def test_round_trip_overwrite_and_missing(blobs: BlobStore) -> None:
    blobs.ping()
    assert blobs.get("jobs/abc/image") is None
    blobs.put("jobs/abc/image", PNG, "image/png")
    assert blobs.get("jobs/abc/image") == PNG
    blobs.put("jobs/abc/image", b"second")
    assert blobs.get("jobs/abc/image") == b"second"
    blobs.put("empty", b"")
    assert blobs.get("empty") == b""


def test_list_by_prefix_with_sizes_and_delete(blobs: BlobStore) -> None:
    before = time.time() - 5.0
    blobs.put("jobs/a/image", b"12345")
    blobs.put("jobs/a/a1/difference.png", PNG)
    blobs.put("jobs/b/image", b"1")
    blobs.put("models/m1/" + "0" * 64, b"mesh")
    listed = {e.name: e for e in blobs.list("jobs/")}
    assert set(listed) == {"jobs/a/image", "jobs/a/a1/difference.png", "jobs/b/image"}
    assert listed["jobs/a/a1/difference.png"].size_bytes == len(PNG)
    assert all(before <= e.modified_s <= time.time() + 5.0 for e in listed.values())
    assert [e.name for e in blobs.list("models/")] == ["models/m1/" + "0" * 64]
    blobs.delete(["jobs/a/image", "jobs/a/a1/difference.png", "never/was"])
    assert {e.name for e in blobs.list("jobs/")} == {"jobs/b/image"}
    assert blobs.get("jobs/a/image") is None
    blobs.delete([])


@pytest.mark.parametrize("name", ["../escape", "/etc/passwd", "a/../../b", "a//b", "", "a b"])
def test_names_that_could_leave_the_store_are_refused(blobs: BlobStore, name: str) -> None:
    with pytest.raises(ValueError, match="not a valid blob name"):
        blobs.put(name, b"x")
    with pytest.raises(ValueError, match="not a valid blob name"):
        blobs.get(name)


def test_file_writes_leave_no_partial_file(tmp_path: Path) -> None:
    store = FileBlobStore(tmp_path / "store")
    store.put("jobs/j/image", PNG)
    files = [p.name for p in (tmp_path / "store" / "jobs" / "j").iterdir()]
    assert files == ["image"]  # the temporary file was renamed over the name


def test_a_crashed_write_is_never_listed_and_its_leftover_goes_when_stale(tmp_path: Path) -> None:
    store = FileBlobStore(tmp_path / "store")
    store.put("jobs/j/image", b"whole")
    fresh = tmp_path / "store" / "jobs" / "j" / f"{TMP_PREFIX}fresh"
    stale = tmp_path / "store" / "jobs" / "j" / f"{TMP_PREFIX}stale"
    fresh.write_bytes(b"half")
    stale.write_bytes(b"half")
    old = time.time() - STALE_TMP_S - 10
    os.utime(stale, (old, old))
    assert [e.name for e in store.list("jobs/")] == ["jobs/j/image"]
    assert fresh.exists() and not stale.exists()


def test_file_delete_removes_emptied_directories(tmp_path: Path) -> None:
    store = FileBlobStore(tmp_path / "store")
    store.put("jobs/j/a1/x.png", b"x")
    store.delete(["jobs/j/a1/x.png"])
    assert not (tmp_path / "store" / "jobs").exists() and (tmp_path / "store").is_dir()


def test_an_unusable_directory_is_unavailable_not_an_os_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_bytes(b"")
    store = FileBlobStore(tmp_path / "file" / "store")  # under a regular file
    for call in (store.ping, lambda: store.put("a", b"x"), lambda: store.get("a")):
        with pytest.raises(BlobStoreUnavailable) as caught:
            call()
        assert caught.value.store == "filesystem" and caught.value.code == "store_unavailable"


def test_an_unreachable_s3_endpoint_is_unavailable() -> None:
    from conftest import free_port

    store = S3BlobStore(
        "bucket",
        endpoint_url=f"http://127.0.0.1:{free_port()}",
        region="us-east-1",
        access_key_id="k",
        secret_access_key="s",
        timeout_s=1.0,
    )
    t0 = time.monotonic()
    for call in (store.ping, lambda: store.put("a", b"x"), lambda: store.get("a")):
        with pytest.raises(BlobStoreUnavailable) as caught:
            call()
        assert caught.value.store == "S3 bucket 'bucket'"
    assert time.monotonic() - t0 < 30.0


def test_a_missing_bucket_is_unavailable_but_a_missing_key_is_none(s3_server: S3Server) -> None:  # noqa: F811
    gone = s3_server.store("no-such-bucket-here")
    with pytest.raises(BlobStoreUnavailable, match="NoSuchBucket|404"):
        gone.ping()
    with pytest.raises(BlobStoreUnavailable, match="NoSuchBucket"):
        gone.get("a")
    assert s3_server.store(s3_server.new_bucket()).get("a") is None


def test_s3_objects_live_under_the_prefix(s3_server: S3Server) -> None:  # noqa: F811
    bucket = s3_server.new_bucket()
    s3_server.store(bucket, "deploy-a").put("jobs/j/image", b"a")
    s3_server.store(bucket, "deploy-b").put("jobs/j/image", b"b")
    client = s3_server.client()
    keys = sorted(o["Key"] for o in client.list_objects_v2(Bucket=bucket)["Contents"])  # type: ignore[attr-defined]
    assert keys == ["deploy-a/jobs/j/image", "deploy-b/jobs/j/image"]
    assert [e.name for e in s3_server.store(bucket, "deploy-a").list("jobs/")] == ["jobs/j/image"]


def test_operations_are_counted(tmp_path: Path) -> None:
    store = CountingBlobStore(FileBlobStore(tmp_path))
    store.put("a", b"12345")
    store.get("a")
    store.get("missing")
    store.delete(["a"])
    ops, written, read = store.ops.snapshot()
    assert ops == {("put", "ok"): 1, ("get", "ok"): 1, ("get", "missing"): 1, ("delete", "ok"): 1}
    assert (written, read) == (5, 5)
    broken = CountingBlobStore(FileBlobStore(tmp_path / "a"))  # "a" is gone: fine; make it a file
    (tmp_path / "a").write_bytes(b"")
    with pytest.raises(BlobStoreUnavailable):
        broken.put("x", b"1")
    assert broken.ops.snapshot()[0] == {("put", "error"): 1}


# ----------------------------------------------------------------------------- settings
def test_the_default_store_is_a_directory_under_the_data_dir(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path)
    assert settings.effective_blob_store() == f"file://{tmp_path / 'blobs'}"
    store = open_blob_store(settings)
    assert isinstance(store.inner, FileBlobStore) and store.inner.root == tmp_path / "blobs"


def test_an_s3_url_opens_the_s3_store() -> None:
    settings = Settings(blob_store="s3://my-bucket/some/prefix", s3_endpoint_url="http://m:9000")
    store = open_blob_store(settings)
    assert isinstance(store.inner, S3BlobStore)
    assert (store.inner.bucket, store.inner.prefix) == ("my-bucket", "some/prefix/")
    assert store.url == "s3://my-bucket/some/prefix/ at http://m:9000"


@pytest.mark.parametrize("url", ["redis://x", "s3://", "s3://A_B", "file://", "/plain/path"])
def test_a_bad_store_url_names_the_setting(url: str) -> None:
    with pytest.raises(ValidationError, match="blob_store"):
        Settings(blob_store=url)


def test_s3_secrets_never_show_in_the_settings_repr() -> None:
    settings = Settings(s3_access_key_id="AKIA-SECRET-ID", s3_secret_access_key="TOPSECRET")
    assert "TOPSECRET" not in repr(settings) and "AKIA-SECRET-ID" not in repr(settings)
