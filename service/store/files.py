"""Writing files that other processes read while they are written: the filesystem blob store,
the worker's model cache and the generated demo models, which several processes share."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

#: Mode of the files written: readable by every user (mkstemp's own is 0o600).
FILE_MODE = 0o644


def write_atomic(
    path: Path, data: bytes, tmp_prefix: str | None = None, fsync: bool = True
) -> Path:
    """Write ``data`` to ``path`` so that readers see the old file or the whole new one.

    The bytes go to a temporary file in the same directory (created with ``path``'s parents;
    named ``tmp_prefix…``, by default ``.NAME.….tmp``), reach the disk (fsync; skipped with
    ``fsync=False``, for a caller that fsyncs later, see ``service.store.blobs.flusher``) and
    are moved into place; a failure leaves no temporary file. Returns ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix, suffix = (tmp_prefix, "") if tmp_prefix else (f".{path.name}.", ".tmp")
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path
