"""Atomic file writes (service/store/files.py): whole files or none, readable, no temporary left."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from service.store.files import FILE_MODE, write_atomic


def test_writes_replaces_and_creates_the_parents(tmp_path: Path) -> None:
    path = tmp_path / "cache" / "models" / "a.glb"
    assert write_atomic(path, b"first") == path
    write_atomic(path, b"second")
    assert path.read_bytes() == b"second"
    assert stat.S_IMODE(path.stat().st_mode) == FILE_MODE
    assert [p.name for p in path.parent.iterdir()] == ["a.glb"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "a.bin"
    write_atomic(path, b"old")
    with pytest.raises(TypeError):
        write_atomic(path, "not bytes")  # type: ignore[arg-type]
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]
