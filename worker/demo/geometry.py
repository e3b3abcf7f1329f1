"""Mesh primitives of the demo satellite: flat-shaded boxes, surfaces of revolution, transforms.

Primitives return :data:`Parts` (vertices, faces, normals, UVs) in metres; :func:`textured_mesh`
turns them into a trimesh mesh with its own PBR material. The untextured bodies (the demo
terrain, the bench's asteroid) take one grey material (:func:`untextured_mesh`), and every demo
model is written by :func:`write_glb`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from PIL import Image
from trimesh.exchange.gltf import export_glb
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial

from service.store.files import write_atomic
from worker.demo.textures import Rect

Parts = tuple[NDArray, NDArray, NDArray, NDArray]  # vertices, faces, normals, uv

_FACES = {
    "+x": ((1, 0, 0), (0, 0, 1)),
    "-x": ((-1, 0, 0), (0, 0, 1)),
    "+y": ((0, 1, 0), (0, 0, 1)),
    "-y": ((0, -1, 0), (0, 0, 1)),
    "+z": ((0, 0, 1), (0, 1, 0)),
    "-z": ((0, 0, -1), (0, 1, 0)),
}
_GRID6: dict[str, Rect] = {
    k: ((i % 3) / 3, (i // 3) / 2, (i % 3 + 1) / 3, (i // 3 + 1) / 2) for i, k in enumerate(_FACES)
}


def box(extents: ArrayLike, rects: dict[str, Rect] | None = None) -> Parts:
    """Flat-shaded box centred at the origin; each face maps upright onto its own texture rect."""
    half = np.asarray(extents, float) / 2
    rects = rects or _GRID6
    ab = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    V, F, N, UV = [], [], [], []
    for k, (key, (n, v)) in enumerate(_FACES.items()):
        n, v = np.array(n, float), np.array(v, float)
        u = np.cross(v, n)  # (u, v, n) right-handed: the texture is not mirrored
        V.append(n * half + ab[:, :1] * u * half + ab[:, 1:] * v * half)
        N.append(np.tile(n, (4, 1)))
        x0, y0, x1, y1 = rects[key]
        x, y = x0 + (ab[:, 0] + 1) / 2 * (x1 - x0), y1 - (ab[:, 1] + 1) / 2 * (y1 - y0)
        UV.append(np.stack([x, 1 - y], 1))
        F.append(4 * k + np.array([[0, 1, 2], [0, 2, 3]]))
    return np.vstack(V), np.vstack(F), np.vstack(N), np.vstack(UV)


def revolve(profile: list[ArrayLike], sections: int = 48) -> Parts:
    """Surface of revolution about +Z from (r, z) polylines; a crease between polylines.

    Traverse the profile counter-clockwise in the (r, z) plane so that normals point outwards.
    UVs: u around the axis, v along the profile arc length.
    """
    th = np.linspace(0, 2 * np.pi, sections + 1)
    segs = [np.asarray(p, float) for p in profile]
    arcs = [np.r_[0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))] for p in segs]
    offs = np.cumsum([0.0] + [a[-1] for a in arcs])
    V, F, N, UV, base = [], [], [], [], 0
    for p, arc, off in zip(segs, arcs, offs, strict=False):
        t = np.gradient(p, axis=0)
        nrz = np.stack([t[:, 1], -t[:, 0]], 1) / np.linalg.norm(t, axis=1, keepdims=True)
        for q, out in ((p, V), (nrz, N)):
            out.append(
                np.stack(
                    [
                        np.outer(q[:, 0], np.cos(th)),
                        np.outer(q[:, 0], np.sin(th)),
                        np.repeat(q[:, 1:], sections + 1, 1),
                    ],
                    -1,
                ).reshape(-1, 3)
            )
        uu, vv = np.meshgrid(th / (2 * np.pi), (off + arc) / offs[-1])
        UV.append(np.stack([uu, vv], -1).reshape(-1, 2))
        i, j = np.meshgrid(np.arange(len(p) - 1), np.arange(sections), indexing="ij")
        a = (base + i * (sections + 1) + j).ravel()
        c = a + sections + 1
        F.append(np.concatenate([np.stack([a, a + 1, c + 1], 1), np.stack([a, c + 1, c], 1)]))
        base += len(p) * (sections + 1)
    V, F, N, UV = np.vstack(V), np.vstack(F), np.vstack(N), np.vstack(UV)
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = np.einsum("ij,ij->i", cross, N[F].sum(1)) < 0
    F[flip] = F[flip][:, ::-1]
    return V, F[np.linalg.norm(cross, axis=1) > 1e-12], N, UV


def cylinder(r: float, h: float, r_top: float | None = None, sections: int = 32) -> Parts:
    """Closed cylinder or truncated cone on +Z from z=0 (radius r) to z=h (radius r_top)."""
    rt = r if r_top is None else r_top
    return revolve([[(0, 0), (r, 0)], [(r, 0), (rt, h)], [(rt, h), (0, h)]], sections)


def tf(t: ArrayLike = (0, 0, 0), axis: ArrayLike = (1, 0, 0), deg: float = 0.0) -> NDArray:
    """Rigid transform: rotate by ``deg`` about ``axis``, then translate by ``t``."""
    T = trimesh.transformations.rotation_matrix(np.radians(deg), axis)
    T[:3, 3] = t
    return T


def textured_mesh(
    parts: Parts, tex: NDArray, name: str, metallic: float = 0.0, roughness: float = 0.7
) -> trimesh.Trimesh:
    """Textured, unprocessed mesh (vertices stay unshared, so box normals are face normals)."""
    v, f, n, uv = parts
    mat = PBRMaterial(
        name=name,
        baseColorTexture=Image.fromarray(tex, "RGB"),
        metallicFactor=metallic,
        roughnessFactor=roughness,
    )
    return trimesh.Trimesh(
        v, f, vertex_normals=n, visual=TextureVisuals(uv=uv, material=mat), process=False
    )


def untextured_mesh(vertices: NDArray, faces: NDArray, albedo: float) -> trimesh.Trimesh:
    """Unprocessed mesh with one grey, rough, non-metallic material ("regolith") and smooth
    vertex normals, computed now so that an export carries them."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.visual = TextureVisuals(
        material=PBRMaterial(
            name="regolith",
            baseColorFactor=[albedo] * 3 + [1.0],
            metallicFactor=0.0,
            roughnessFactor=1.0,
        )
    )
    _ = mesh.vertex_normals
    return mesh


def write_glb(path: Path, model: trimesh.Trimesh | trimesh.Scene) -> Path:
    """Export ``model`` as a binary glTF (GLB) with its vertex normals, atomically."""
    scene = model if isinstance(model, trimesh.Scene) else trimesh.Scene(model)
    return write_atomic(Path(path), export_glb(scene, include_normals=True))
