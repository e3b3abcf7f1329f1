"""Loading target models (OBJ, PLY, STL, GLB/GLTF) into renderer-ready triangle parts.

trimesh reads every format; the scene graph's node transforms are applied, and the file's own
coordinates are kept (no recentring, no rescaling), since poses are expressed in them. Base-colour
textures and UVs are carried over (UV v flipped for Mitsuba's top-left bitmap origin), vertex
colours too. A loaded model is cached per process by content hash.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.names import DEFAULT_MAX_MODEL_FACES, MODEL_FILE_TYPES
from worker.engine import parsed_models
from worker.engine.exceptions import ModelLoadError, ModelTooLargeError
from worker.engine.images import srgb_decode
from worker.engine.parsed_models import ParsedModel, ParsedPart

log = logging.getLogger(__name__)

#: Longest texture side kept (larger ones are downsampled): memory and upload time.
MAX_TEXTURE_SIDE_PX = 4096
#: Models kept in each process's cache.
MODEL_CACHE_SIZE = 4
#: Linear value of each 8-bit sRGB code: a texture decodes by lookup (~3× the arithmetic);
#: computed as an image (16 × 16), so with the same (OpenCV) power as a decoded image.
_SRGB_DECODE_8BIT = srgb_decode(np.arange(256, dtype=np.float32).reshape(16, 16) / 255.0).ravel()
#: Base colour of parts with no material (linear RGB).
DEFAULT_ALBEDO = (0.5, 0.5, 0.5)


@dataclass
class MeshPart:
    """One triangle mesh with one material, in model coordinates."""

    vertices: NDArray[np.float32]  # (N, 3)
    faces: NDArray[np.uint32]  # (M, 3)
    normals: NDArray[np.float32] | None  # (N, 3) per-vertex, or None for flat shading
    uvs: NDArray[np.float32] | None  # (N, 2), v already flipped for Mitsuba
    texture: NDArray[np.float32] | None  # (H, W, 3) linear base colour (factor applied)
    vertex_colors: NDArray[np.float32] | None  # (N, 3) linear
    albedo: tuple[float, float, float] = DEFAULT_ALBEDO  # linear, used without texture/colours

    @property
    def texels_per_unit(self) -> float:
        """Mean texture resolution on the surface, texels per scene unit (0 if untextured)."""
        if self.texture is None or self.uvs is None:
            return 0.0
        tri = self.vertices[self.faces].astype(np.float64)
        area_world = (
            0.5
            * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        )
        uv = self.uvs[self.faces].astype(np.float64) * self.texture.shape[1::-1]
        e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        area_tex = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
        return float(np.sqrt(area_tex / area_world)) if area_world > 0 else 0.0


@dataclass
class LoadedModel:
    """A model ready to render: its parts and summary facts."""

    name: str
    sha256: str
    parts: list[MeshPart]
    bounds: NDArray[np.float64]  # (2, 3) min and max corner
    n_vertices: int
    n_faces: int
    textured: bool
    meta: dict[str, str] = field(default_factory=dict)

    @property
    def centre(self) -> NDArray[np.float64]:
        """Centre of the bounding box, model frame."""
        return self.bounds.mean(axis=0)

    @property
    def has_vertex_normals(self) -> bool:
        """Whether any part has its own (smooth) shading normals."""
        return any(p.normals is not None for p in self.parts)

    @cached_property
    def finest_texels_per_unit(self) -> float:
        """The largest texture resolution of its parts, texels per scene unit (0 if none)."""
        return max((p.texels_per_unit for p in self.parts), default=0.0)

    @cached_property
    def radius(self) -> float:
        """Radius of the bounding sphere about the bounding-box centre, scene units (computed
        once: estimates ask for it every iteration, ~4 ms over the ISS's 101,363 vertices)."""
        return max(
            float(np.linalg.norm(p.vertices - self.centre, axis=1).max()) for p in self.parts
        )


_cache: OrderedDict[str, LoadedModel] = OrderedDict()


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_model(
    path: str | Path,
    max_faces: int = DEFAULT_MAX_MODEL_FACES,
    parsed_dir: Path | None = None,
) -> LoadedModel:
    """Load a mesh file (cached by content hash). Raises ModelLoadError / ModelTooLargeError.

    ``max_faces`` is the most triangles accepted: the worker passes its setting
    (``PROXPOSE_MAX_MODEL_FACES``), the same limit the API checks uploads against.
    ``parsed_dir``, when given, keeps the parse of a self-contained file on disk for the next
    process (:mod:`worker.engine.parsed_models`).
    """
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(f"model file not found: {path}")
    if path.suffix.lower() not in MODEL_FILE_TYPES:  # before the cache: same bytes, other name
        raise ModelLoadError(
            f"unsupported model format '{path.suffix}' (use {', '.join(sorted(MODEL_FILE_TYPES))})"
        )
    digest = file_sha256(path)
    if digest in _cache:
        _cache.move_to_end(digest)
        cached = _cache[digest]
        if cached.n_faces > max_faces:  # cached under a larger limit
            raise ModelTooLargeError(f"model has more than {max_faces} faces")
        return cached
    model = _load_uncached(path, digest, max_faces, parsed_dir)
    _cache[digest] = model
    while len(_cache) > MODEL_CACHE_SIZE:
        _cache.popitem(last=False)
    return model


def _load_uncached(path: Path, digest: str, max_faces: int, parsed_dir: Path | None) -> LoadedModel:
    file_type = MODEL_FILE_TYPES[path.suffix.lower()]
    keep_in = parsed_dir if file_type in parsed_models.SELF_CONTAINED else None
    parsed = parsed_models.read(keep_in, digest) if keep_in is not None else None
    if parsed is None:
        parsed = _parse(path, file_type, max_faces)
        if keep_in is not None:
            parsed_models.write(keep_in, digest, parsed)
    if sum(len(p.faces) for p in parsed.parts) > max_faces:  # kept under a larger limit
        raise ModelTooLargeError(f"model has more than {max_faces} faces")
    parts = _with_textures(parsed)
    verts = np.concatenate([p.vertices for p in parts])
    if not np.isfinite(verts).all():
        raise ModelLoadError("model has non-finite vertex coordinates")
    bounds = np.stack([verts.min(axis=0), verts.max(axis=0)]).astype(np.float64)
    if float(np.linalg.norm(bounds[1] - bounds[0])) <= 0.0:
        raise ModelLoadError("model is degenerate (zero extent)")
    return LoadedModel(
        name=path.stem,
        sha256=digest,
        parts=parts,
        bounds=bounds,
        n_vertices=int(len(verts)),
        n_faces=int(sum(len(p.faces) for p in parts)),
        textured=any(p.texture is not None for p in parts),
    )


def _parse(path: Path, file_type: str, max_faces: int) -> ParsedModel:
    """Read the file with trimesh: every geometry node, its transform applied."""
    import trimesh

    if file_type == "gltf":
        _check_gltf_json(path)
    try:
        scene = trimesh.load(str(path), file_type=file_type, force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise ModelLoadError(f"cannot read {file_type.upper()} model: {exc}") from exc
    parsed = ParsedModel([], [])
    image_index: dict[int, int] = {}  # id of a PIL image → its index: decoded once, shared
    for node in scene.graph.nodes_geometry:
        T, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        T = np.asarray(T, dtype=np.float64)
        parsed.parts.append(_part_from_trimesh(geom, T, parsed.images, image_index))
        if sum(len(p.faces) for p in parsed.parts) > max_faces:
            raise ModelTooLargeError(f"model has more than {max_faces} faces")
    if not parsed.parts:
        raise ModelLoadError("model holds no triangles")
    return parsed


def _with_textures(parsed: ParsedModel) -> list[MeshPart]:
    """Renderer-ready parts: each base-colour image decoded to linear once (8-bit sRGB by
    lookup) and limited in size; each part gets its own array of it, scaled by its factor.

    Not OpenCV's LUT, though ~5× faster here: with it, 2 of 3 warm Phobos bench estimates ran
    at half speed throughout (4.6 and 5.1 s against 2.2 s; 6 of 6 at 2.0-2.7 s with numpy).
    That may be chance, as this VM's speed is bimodal from run to run, but it was not risked.
    """
    linear = [_limit_texture(_SRGB_DECODE_8BIT[image]) for image in parsed.images]
    parts, taken = [], set()
    for p in parsed.parts:
        texture = None
        if p.image >= 0:
            texture = linear[p.image]
            if p.factor is not None and not np.all(p.factor == 1.0):
                texture = (texture * p.factor).astype(np.float32, copy=False)
            elif p.image in taken:  # one array per part, as when each part decoded its own
                texture = texture.copy()
            taken.add(p.image)
        parts.append(
            MeshPart(p.vertices, p.faces, p.normals, p.uvs, texture, p.vertex_colors, p.albedo)
        )
    return parts


def _check_gltf_json(path: Path) -> None:
    """A .gltf must be a JSON object: trimesh reads a sibling 'model.gltf' instead of a file it
    cannot parse, which would silently load another model."""
    try:
        tree = json.loads(path.read_bytes())
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError
        raise ModelLoadError(f"cannot read GLTF model: not JSON ({exc})") from exc
    if not isinstance(tree, dict):
        raise ModelLoadError("cannot read GLTF model: not a JSON object")


def _part_from_trimesh(
    mesh: object,
    T: NDArray[np.float64],
    images: list[NDArray[np.uint8]],
    image_index: dict[int, int],
) -> ParsedPart:
    """Vertices transformed by the node matrix T; normals by its inverse transpose."""
    import trimesh

    assert isinstance(mesh, trimesh.Trimesh)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    V = V @ T[:3, :3].T + T[:3, 3]
    normals = None
    # Normals from the file are kept (cached by the loader); otherwise shade flat rather
    # than let trimesh smooth across the hard edges of a CAD model.
    if "vertex_normals" in mesh._cache.cache:
        N = np.asarray(mesh.vertex_normals, dtype=np.float64) @ np.linalg.inv(T[:3, :3])
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
        if np.isfinite(N).all():
            normals = N.astype(np.float32)
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    if np.linalg.det(T[:3, :3]) < 0:  # a mirroring node flips the winding
        faces = faces[:, ::-1].copy()
    part = ParsedPart(V.astype(np.float32), faces, normals, None, None, DEFAULT_ALBEDO)
    _material(mesh, part, images, image_index)
    return part


def _material(
    mesh: object,
    part: ParsedPart,
    images: list[NDArray[np.uint8]],
    image_index: dict[int, int],
) -> None:
    """The part's UVs and texture image, linear vertex colours, linear albedo, from trimesh."""
    visual = getattr(mesh, "visual", None)
    kind = getattr(visual, "kind", None)
    if kind == "vertex" or kind == "face":
        rgb = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0  # type: ignore
        part.vertex_colors = srgb_decode(rgb)
        return
    material = getattr(visual, "material", None)
    if material is None:
        return
    factor, image = _base_colour(material)
    part.albedo = tuple(float(c) for c in factor)  # type: ignore[assignment]
    uv = getattr(visual, "uv", None)
    if image is None or uv is None or len(uv) != len(mesh.vertices):  # type: ignore
        return
    if id(image) not in image_index:  # the scene holds its images while it loads: ids unique
        image_index[id(image)] = len(images)
        images.append(np.ascontiguousarray(np.asarray(image.convert("RGB"), dtype=np.uint8)))
    part.image = image_index[id(image)]
    part.factor = np.asarray(factor, dtype=np.float32)
    uvs = np.asarray(uv, dtype=np.float32).copy()
    uvs[:, 1] = 1.0 - uvs[:, 1]
    part.uvs = uvs


def _base_colour(material: object) -> tuple[NDArray[np.float32], object | None]:
    """Linear RGB base-colour factor and the (PIL) base-colour image of a trimesh material."""
    factor = getattr(material, "baseColorFactor", None)
    image = getattr(material, "baseColorTexture", None)
    if factor is None:
        factor = getattr(material, "diffuse", None)  # SimpleMaterial (OBJ/MTL Kd)
        image = getattr(material, "image", None) if image is None else image
    if factor is None:
        return np.ones(3, np.float32) if image is not None else np.asarray(DEFAULT_ALBEDO), image
    a = np.asarray(factor)
    f = a.astype(np.float32)[:3]
    # trimesh stores colours as 8-bit integers; glTF factors are linear.
    return (f / 255.0 if np.issubdtype(a.dtype, np.integer) else f), image


def _limit_texture(tex: NDArray[np.float32]) -> NDArray[np.float32]:
    h, w = tex.shape[:2]
    if max(h, w) <= MAX_TEXTURE_SIDE_PX:
        return tex
    import cv2

    s = MAX_TEXTURE_SIDE_PX / max(h, w)
    return cv2.resize(tex, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
