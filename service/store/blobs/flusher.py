"""Group commit of the filesystem blob store's fsyncs: a write returns once its bytes are in the
file (renamed into place, readable by every process), and a background thread of the writing
process fsyncs the files and their directories at most ``FLUSH_DELAY_S`` later, all the writes
of a burst in one pass.

Why a blob need not be on disk before the write returns: a job is accepted (202) once its image
is written and its record committed to Redis. If the API process dies right after, the image is
in the kernel's page cache, which the process's death does not touch: a worker on the machine
reads it (``tests/test_blobs.py`` kills a writer before its flush). Only a crash of the machine
itself (power, kernel) loses data that is not yet on disk, and the Redis of ``proxpose serve``
(``appendfsync everysec``) then loses its last second of writes, jobs included; the image of a
job is flushed within ``FLUSH_DELAY_S`` (0.1 s, plus the fsyncs themselves), well inside that
second. Until this module, each write fsynced its file in the request (7–16 ms in a burst of
30 on the 2-core VM); the rename itself was never fsynced (its directory now is, and so is
every directory up to the store's root that the write may have made).
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

#: How long the flusher waits after the first pending write, gathering the rest of a burst, s.
FLUSH_DELAY_S = 0.1


def fsync_path(path: Path, directory: bool = False) -> None:
    """fsync the file (or directory) at ``path``; one deleted meanwhile is no error."""
    flags = os.O_RDONLY | (os.O_DIRECTORY if directory else 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Flusher:
    """fsyncs the files handed to :meth:`add` (and their directories) from a daemon thread,
    ``delay_s`` after the first of a batch; :meth:`flush` does it now (also at exit)."""

    def __init__(self, delay_s: float = FLUSH_DELAY_S) -> None:
        self.delay_s = delay_s
        self._files: set[Path] = set()
        self._dirs: set[Path] = set()
        self._wake = threading.Condition()
        self._thread: threading.Thread | None = None
        self._flush_lock = threading.Lock()  # one pass at a time (the thread, flush(), exit)
        atexit.register(self.flush)

    def add(self, path: Path, root: Path | None = None) -> None:
        """Have ``path`` (a file just renamed into place) and its directory fsynced soon; with
        ``root``, every directory from that one up to ``root`` too: the write may have made
        them (``jobs/<id>/`` for a new job), and a new directory's entry is in its parent."""
        dirs = [path.parent]
        if root is not None and path.parent.is_relative_to(root):
            dirs += [d for d in path.parent.parents if d.is_relative_to(root)]
        with self._wake:
            self._files.add(path)
            self._dirs.update(dirs)
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="blob-flusher", daemon=True)
                self._thread.start()
            self._wake.notify()

    def pending(self) -> int:
        """Files written and not yet fsynced."""
        with self._wake:
            return len(self._files)

    def flush(self) -> None:
        """fsync every pending file, then their directories (the renames), now."""
        with self._flush_lock:
            with self._wake:
                files, dirs = self._files, self._dirs
                self._files, self._dirs = set(), set()
            failed = 0
            for path, directory in [(f, False) for f in files] + [(d, True) for d in dirs]:
                try:
                    fsync_path(path, directory)
                except OSError as exc:
                    # the bytes are written and readable; only their durability against a
                    # crash of the machine is in doubt, and no client can be told any more
                    failed += 1
                    log.error("blob store: fsync of %s failed: %s", path, exc)
            if failed:
                log.error("blob store: %d of the last writes may not be on disk", failed)

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._files:
                    self._wake.wait()
            time.sleep(self.delay_s)  # gather the rest of a burst
            self.flush()


_shared: Flusher | None = None
_shared_lock = threading.Lock()


def shared_flusher() -> Flusher:
    """The process's flusher, made on first use (every filesystem store of a process shares
    it: one thread, one batch)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = Flusher()
        return _shared
