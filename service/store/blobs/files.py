"""The filesystem blob store (the default): one file per blob under a root directory.

A write goes to a temporary file in the blob's directory and is renamed over the name
(``os.replace`` is atomic on POSIX), so a reader never sees part of a blob; a crash leaves at
most a ``.tmp-`` file, which listing skips and the sweeper removes once old. The write returns
once the blob is readable by every process; the process's flusher (``flusher``) fsyncs it and
its directory within ~0.1 s, a burst's writes together (why that is as durable as the job
records in Redis: the flusher's docstring).
Directories left empty by a delete are removed up to the root.
"""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from service.store.blobs.base import BlobEntry, BlobStoreUnavailable, check_name
from service.store.blobs.flusher import Flusher, shared_flusher
from service.store.files import write_atomic

#: Prefix of the temporary files of writes in progress.
TMP_PREFIX = ".tmp-"
#: A temporary file older than this is the leftover of a crashed write, s.
STALE_TMP_S = 3600.0


class FileBlobStore:
    """Blobs as files under ``root`` (created on first use)."""

    def __init__(self, root: Path, flusher: Flusher | None = None) -> None:
        self.root = Path(root).absolute()
        self.url = f"file://{self.root}"
        self.description = "filesystem"
        self.flusher = flusher if flusher is not None else shared_flusher()

    def _path(self, name: str) -> Path:
        return self.root / check_name(name)

    def _unavailable(self, exc: OSError) -> BlobStoreUnavailable:
        reason = "the disk is full" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        return BlobStoreUnavailable(self.description, reason)

    def put(self, name: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        path = self._path(name)
        try:
            write_atomic(path, data, tmp_prefix=TMP_PREFIX, fsync=False)
        except OSError as exc:
            raise self._unavailable(exc) from exc
        self.flusher.add(path, root=self.root)

    def flush(self) -> None:
        """fsync the blobs written so far now (the flusher does it within ~0.1 s anyway)."""
        self.flusher.flush()

    def get(self, name: str) -> bytes | None:
        path = self._path(name)
        try:
            return path.read_bytes()
        except (FileNotFoundError, NotADirectoryError):
            if not self.root.is_dir():  # a new store (an upgrade) or a broken one: which?
                self.ping()
            return None
        except OSError as exc:
            raise self._unavailable(exc) from exc

    def delete(self, names: Iterable[str]) -> None:
        try:
            for name in names:
                path = self._path(name)
                path.unlink(missing_ok=True)
                self._prune(path.parent)
        except OSError as exc:
            raise self._unavailable(exc) from exc

    def _prune(self, directory: Path) -> None:
        """Remove ``directory`` and its parents up to the root while they are empty."""
        while directory != self.root and self.root in directory.parents:
            try:
                directory.rmdir()
            except OSError:  # not empty (or already gone): stop
                return
            directory = directory.parent

    def list(self, prefix: str) -> Iterator[BlobEntry]:
        top = self.root / prefix.rstrip("/") if prefix.endswith("/") else self.root
        if not top.is_dir():
            if not self.root.exists():
                return
            if not self.root.is_dir():
                raise BlobStoreUnavailable(self.description, "the store's root is not a directory")
            return
        try:
            for dirpath, _dirs, files in os.walk(top):
                for file in files:
                    path = Path(dirpath, file)
                    try:
                        st = path.stat()
                    except FileNotFoundError:
                        continue  # deleted meanwhile
                    if file.startswith(TMP_PREFIX):
                        if time.time() - st.st_mtime > STALE_TMP_S:
                            path.unlink(missing_ok=True)  # a crashed write's leftover
                        continue
                    name = path.relative_to(self.root).as_posix()
                    if name.startswith(prefix):
                        yield BlobEntry(name, st.st_size, st.st_mtime)
        except OSError as exc:
            raise self._unavailable(exc) from exc

    def ping(self) -> None:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise self._unavailable(exc) from exc
        if not os.access(self.root, os.W_OK | os.X_OK):
            raise BlobStoreUnavailable(self.description, "the directory is not writable")
