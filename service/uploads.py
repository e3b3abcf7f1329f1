"""Checks of uploaded files in the API process: images by their header (PIL, no decoding) and
models with trimesh. Neither imports OpenCV or Mitsuba; the workers decode and load for real.
"""

from __future__ import annotations

import io
import json
import math
import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any

from PIL import Image

from schemas.names import IMAGE_FORMATS, MODEL_FILE_TYPES, UploadErrorCode


class UploadRejected(ValueError):
    """An uploaded file is unusable; ``code`` names why (the engine's codes where they exist)."""

    def __init__(self, code: UploadErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class ImageInfo:
    format: str
    width: int
    height: int


@dataclass(frozen=True)
class ModelInfo:
    format: str
    vertices: int
    faces: int
    bounds: list[list[float]]
    textured: bool


def load_image_codecs() -> None:
    """Import PIL's PNG, JPEG and TIFF readers now (~15 ms, plus ~35 ms for PIL's scan of all
    its plugins that the first TIFF set off) instead of inside the first upload's request, where
    a burst of submissions would wait for it."""
    Image.preinit()
    from PIL import TiffImagePlugin  # noqa: F401  (registers TIFF, so no full scan is needed)


def inspect_image(data: bytes, max_pixels: int) -> ImageInfo:
    """Format and size of a PNG/JPEG/TIFF from its header; the pixel count is checked before
    anything is decoded, then the file structure is verified (PIL ``verify``)."""
    if not data:
        raise UploadRejected("invalid_image", "the image is empty")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data), formats=IMAGE_FORMATS) as img:
                info = ImageInfo(str(img.format), *img.size)
    except Image.DecompressionBombError as exc:
        raise UploadRejected("image_too_large", f"the image is too large ({exc})") from exc
    except Exception as exc:  # PIL raises many types for unknown or corrupt data
        raise UploadRejected("invalid_image", "not a readable PNG, JPEG or TIFF image") from exc
    if info.width * info.height > max_pixels:
        raise UploadRejected(
            "image_too_large",
            f"the image has {info.width}×{info.height} pixels, more than {max_pixels}",
        )
    try:
        with Image.open(io.BytesIO(data), formats=IMAGE_FORMATS) as img:
            img.verify()
    except Exception as exc:
        raise UploadRejected("invalid_image", f"the {info.format} file is corrupt ({exc})") from exc
    return info


def model_format(filename: str | None) -> str:
    """The model format from the upload's file name (by extension)."""
    suffix = PurePath(filename or "").suffix.lower()
    if suffix not in MODEL_FILE_TYPES:
        accepted = ", ".join(sorted(MODEL_FILE_TYPES))
        got = f"'{suffix}'" if suffix else "no extension"
        raise UploadRejected("unsupported_format", f"file name has {got}; use one of {accepted}")
    return MODEL_FILE_TYPES[suffix]


def inspect_model(data: bytes, file_format: str, max_faces: int) -> ModelInfo:
    """Counts, bounds and texturing of a mesh file, read the way the engine reads it (scene
    graph transforms applied, instances counted once per node)."""
    import numpy as np
    import trimesh

    if not data:
        raise UploadRejected("invalid_model", "the model file is empty")
    declared = declared_faces(data, file_format)
    if declared is not None and declared > max_faces:
        raise UploadRejected(
            "model_too_large", f"the model declares {declared} faces, more than {max_faces}"
        )
    try:
        scene: Any = trimesh.load(
            file_obj=io.BytesIO(data), file_type=file_format, force="scene", process=False
        )
    except Exception as exc:  # trimesh raises many types for bad files
        raise UploadRejected(
            "invalid_model", f"cannot read the {file_format.upper()} model: {exc}"
        ) from exc
    n_vertices = n_faces = 0
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    textured = False
    for node in scene.graph.nodes_geometry:
        T, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        n_vertices += len(geom.vertices)
        n_faces += len(geom.faces)
        if n_faces > max_faces:
            raise UploadRejected("model_too_large", f"the model has more than {max_faces} faces")
        V = np.asarray(geom.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        lo, hi = np.minimum(lo, V.min(axis=0)), np.maximum(hi, V.max(axis=0))
        textured = textured or _has_texture(geom)
    if n_faces == 0:
        raise UploadRejected("invalid_model", "the model holds no triangles")
    bounds = [lo.tolist(), hi.tolist()]
    if not all(math.isfinite(c) for corner in bounds for c in corner):
        raise UploadRejected("invalid_model", "the model has non-finite vertex coordinates")
    if float(np.linalg.norm(hi - lo)) <= 0.0:
        raise UploadRejected("invalid_model", "the model is degenerate (zero extent)")
    return ModelInfo(file_format, n_vertices, n_faces, bounds, textured)


def _has_texture(mesh: object) -> bool:
    visual = getattr(mesh, "visual", None)
    material = getattr(visual, "material", None)
    image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
    uv = getattr(visual, "uv", None)
    return image is not None and uv is not None and len(uv) == len(mesh.vertices)  # type: ignore[attr-defined]


# ----------------------------------------------------------------------------- header counts
#: Bytes of a PLY header read at most (a real header is far shorter).
PLY_HEADER_MAX_BYTES = 64 * 1024
_PLY_FACES = re.compile(rb"^element\s+face\s+(\d+)\s*$", re.MULTILINE)
_GLB_MAGIC = b"glTF"
_GLB_JSON_CHUNK = 0x4E4F534A
_TRIANGLES = 4


def declared_faces(data: bytes, file_format: str) -> int | None:
    """The triangle count a file's header declares, read before parsing it (a small file must
    not make the parser allocate for billions of faces); None when the format has no such
    count (OBJ) or the header is unreadable (the parser then reports the problem)."""
    try:
        if file_format == "ply":
            end = data.find(b"end_header", 0, PLY_HEADER_MAX_BYTES)
            found = _PLY_FACES.search(data, 0, end if end > 0 else PLY_HEADER_MAX_BYTES)
            return int(found.group(1)) if found else None
        if file_format == "stl" and not data[:5].lower().startswith(b"solid"):
            return int(struct.unpack_from("<I", data, 80)[0]) if len(data) >= 84 else None
        if file_format in ("glb", "gltf"):
            return _gltf_faces(_gltf_json(data, file_format))
    except (ValueError, KeyError, TypeError, IndexError, struct.error, RecursionError):
        return None
    return None


def _gltf_json(data: bytes, file_format: str) -> dict[str, Any]:
    if file_format == "gltf":
        return dict(json.loads(data))
    magic, _version, _length = struct.unpack_from("<4sII", data, 0)
    size, kind = struct.unpack_from("<II", data, 12)
    if magic != _GLB_MAGIC or kind != _GLB_JSON_CHUNK:
        raise ValueError("not a GLB file")
    return dict(json.loads(data[20 : 20 + size]))


def _gltf_faces(gltf: dict[str, Any]) -> int:
    """Σ over the nodes' meshes (each instance counts) of the triangles their accessors claim."""
    accessors = gltf.get("accessors", [])

    def mesh_faces(mesh: dict[str, Any]) -> int:
        total = 0
        for prim in mesh.get("primitives", []):
            if prim.get("mode", _TRIANGLES) != _TRIANGLES:
                continue
            index = prim["indices"] if "indices" in prim else prim["attributes"]["POSITION"]
            total += int(accessors[index]["count"]) // 3
        return total

    meshes = [mesh_faces(m) for m in gltf.get("meshes", [])]
    nodes = [n["mesh"] for n in gltf.get("nodes", []) if "mesh" in n]
    return sum(meshes[i] for i in nodes) if nodes else sum(meshes)
