"""Parsed models kept on disk between processes, so a model file is parsed once, not per run.

Parsing goes through trimesh, whose import alone takes ~0.65 s here (scipy, networkx), and
decodes every texture image: about 1 s of a command-line estimate's start-up for the demo
satellite. The cache keeps what the parse yields (triangles, normals, UVs, vertex colours and
the 8-bit base-colour images, before any decoding to linear) in one ``<sha256>.npz`` per model
file, read without trimesh and without pickle. Only self-contained files are kept (GLB, PLY,
STL): an OBJ or GLTF reads other files (MTL, textures, buffers) that its hash does not cover.

Entries are written atomically (a temporary file, then a rename) and evicted least recently
used beyond :data:`MAX_ENTRIES`; an entry of another :data:`FORMAT`, or one that cannot be read,
is parsed again. Failing to write is logged, never an error: the cache only saves time.
"""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

#: Version of what a parse yields; bump it when parsing changes, and older entries are re-parsed.
FORMAT = 1
#: Parsed models kept; the least recently used beyond it are deleted.
MAX_ENTRIES = 64
#: Model file types whose content hash covers everything their parse reads.
SELF_CONTAINED = frozenset({"glb", "ply", "stl"})
#: The per-part arrays an entry holds (absent when the part has none).
_PART_ARRAYS = ("vertices", "faces", "normals", "uvs", "vertex_colors")


@dataclass
class ParsedPart:
    """One triangle mesh as parsed: model-frame geometry, its material, no decoded texture."""

    vertices: NDArray[np.float32]  # (N, 3), node transform applied
    faces: NDArray[np.uint32]  # (M, 3)
    normals: NDArray[np.float32] | None
    uvs: NDArray[np.float32] | None  # v flipped for Mitsuba
    vertex_colors: NDArray[np.float32] | None  # (N, 3) linear
    albedo: tuple[float, float, float]
    image: int = -1  # index into ParsedModel.images, −1 without a texture
    factor: NDArray[np.float32] | None = None  # (3,) linear base-colour factor of the texture


@dataclass
class ParsedModel:
    """A model file as parsed, before its textures are decoded to linear colour."""

    parts: list[ParsedPart]
    images: list[NDArray[np.uint8]]  # (H, W, 3) 8-bit sRGB base-colour images, shared by parts


def read(directory: Path, digest: str) -> ParsedModel | None:
    """The parsed model of the file with SHA-256 ``digest``, or None when none is kept."""
    path = directory / f"{digest}.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != FORMAT:
                return None
            parts = [_read_part(z, i) for i in range(int(z["n_parts"]))]
            images = [np.asarray(z[f"image{j}"]) for j in range(int(z["n_images"]))]
        os.utime(path)  # recently used
    except FileNotFoundError:
        return None
    except Exception as exc:  # a truncated or foreign file: parse the model again
        log.warning("ignoring unreadable parsed model %s: %s", path, exc)
        return None
    return ParsedModel(parts, images)


def write(directory: Path, digest: str, parsed: ParsedModel) -> None:
    """Keep ``parsed`` for the file with SHA-256 ``digest`` (atomic; logs and goes on on error)."""
    arrays: dict[str, NDArray[np.generic]] = {
        "format": np.asarray(FORMAT),
        "n_parts": np.asarray(len(parsed.parts)),
        "n_images": np.asarray(len(parsed.images)),
    }
    for i, part in enumerate(parsed.parts):
        for name in _PART_ARRAYS:
            value = getattr(part, name)
            if value is not None:
                arrays[f"{i}.{name}"] = value
        arrays[f"{i}.albedo"] = np.asarray(part.albedo, dtype=np.float64)
        arrays[f"{i}.image"] = np.asarray(part.image)
        if part.factor is not None:
            arrays[f"{i}.factor"] = part.factor
    for j, image in enumerate(parsed.images):
        arrays[f"image{j}"] = image
    tmp_name = None
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=directory, suffix=".tmp", delete=False) as tmp:
            tmp_name = tmp.name
            np.savez(tmp, **arrays)  # type: ignore[arg-type]
        os.replace(tmp_name, directory / f"{digest}.npz")
        tmp_name = None
        _evict(directory)
    except OSError as exc:
        log.warning("could not keep the parsed model in %s: %s", directory, exc)
    finally:
        if tmp_name is not None:
            Path(tmp_name).unlink(missing_ok=True)


def _read_part(z: np.lib.npyio.NpzFile, i: int) -> ParsedPart:
    got = {name: (z[f"{i}.{name}"] if f"{i}.{name}" in z else None) for name in _PART_ARRAYS}
    factor = z[f"{i}.factor"] if f"{i}.factor" in z else None
    albedo = tuple(float(c) for c in z[f"{i}.albedo"])
    return ParsedPart(**got, albedo=albedo, image=int(z[f"{i}.image"]), factor=factor)  # type: ignore[arg-type]


def _evict(directory: Path) -> None:
    entries = sorted(directory.glob("*.npz"), key=lambda p: p.stat().st_mtime, reverse=True)
    for stale in entries[MAX_ENTRIES:]:
        stale.unlink(missing_ok=True)
