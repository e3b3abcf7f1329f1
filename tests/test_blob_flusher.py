"""The filesystem blob store's group commit (service/store/blobs/flusher.py): a write returns
before its fsync, the flusher really fsyncs the file and its directory soon after, and a blob
whose writer is killed before any flush is still there for another process (the guarantee a
202 rests on: the API may die right after it, a worker must find the image)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from service.store.blobs import FileBlobStore
from service.store.blobs.flusher import Flusher

PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 40
#: How long the background flush may take on a loaded machine, s.
FLUSH_WAIT_S = 5.0


@pytest.fixture(name="fsynced")
def record_fsyncs(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """The paths os.fsync is called on from now on (it still fsyncs)."""
    seen: list[Path] = []
    lock = threading.Lock()
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        with lock:
            seen.append(Path(os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return seen


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/fd")
def test_a_write_returns_before_its_fsync_and_the_flusher_fsyncs_it_and_its_directory(
    tmp_path: Path, fsynced: list[Path]
) -> None:
    flusher = Flusher(delay_s=0.3)
    store = FileBlobStore(tmp_path / "store", flusher=flusher)
    store.put("jobs/a/image", PNG)
    store.put("jobs/b/image", PNG)
    path_a, path_b = (store.root / f"jobs/{x}/image" for x in "ab")
    assert path_a.read_bytes() == PNG  # readable at once
    assert fsynced == [] and flusher.pending() == 2  # nothing fsynced in the write itself

    # the new job directories' entries are in jobs/, and jobs/'s in the store's root
    wanted = {path_a, path_b, path_a.parent, path_b.parent, store.root / "jobs", store.root}
    deadline = time.monotonic() + FLUSH_WAIT_S
    while not wanted <= set(fsynced) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert wanted <= set(fsynced), f"fsynced only {fsynced}"
    assert flusher.pending() == 0

    store.put("jobs/c/image", PNG)  # an explicit flush does it now
    store.flush()
    made = {store.root / "jobs/c/image", store.root / "jobs/c", store.root / "jobs", store.root}
    assert made == set(fsynced[-4:])


def test_a_blob_deleted_before_its_flush_is_no_error(tmp_path: Path) -> None:
    flusher = Flusher(delay_s=60.0)
    store = FileBlobStore(tmp_path / "store", flusher=flusher)
    store.put("jobs/a/image", PNG)
    store.delete(["jobs/a/image"])  # the job ended at once; its directory is pruned too
    flusher.flush()
    assert flusher.pending() == 0 and store.get("jobs/a/image") is None


def test_a_blob_whose_writer_is_killed_before_its_flush_is_readable_by_another_process(
    tmp_path: Path,
) -> None:
    root = tmp_path / "store"
    writer = textwrap.dedent(
        f"""
        import os, signal
        from pathlib import Path
        from service.store.blobs import FileBlobStore
        from service.store.blobs.flusher import Flusher
        flusher = Flusher(delay_s=60.0)
        store = FileBlobStore(Path({str(root)!r}), flusher=flusher)
        store.put("jobs/x/image", {PNG!r})
        assert flusher.pending() == 1  # written, not flushed
        os.kill(os.getpid(), signal.SIGKILL)  # no flush, no atexit
        """
    )
    proc = subprocess.run([sys.executable, "-c", writer], capture_output=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    assert FileBlobStore(root).get("jobs/x/image") == PNG
