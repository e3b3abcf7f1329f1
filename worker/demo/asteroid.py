"""A procedural small body for the bench: a rubble-pile contact binary, like Itokawa.

Two lobes (an elongated ellipsoid pinched at a neck), fractal relief made of smooth bumps at
five scales (each octave twice as many, half as wide, 1/1.9 as high), and boulders (sharp
domes a few metres high). Untextured, one albedo: what the image shows is shading, terminator
and limb. About 530 m × 260 m × 215 m, metres, glTF axes, smooth vertex normals. The bench
uses it as a held-out small body (``proxpose bench --models asteroid``): none of the shared
models is a smooth, untextured rubble pile, the kind of target whose features come from
shading alone.
"""

from __future__ import annotations

import pathlib

import numpy as np
import trimesh
from numpy.typing import NDArray

from worker.demo.geometry import untextured_mesh, write_glb

Array = NDArray[np.float64]

ASTEROID_FILE_NAME = "bench-asteroid-v1.glb"
#: Half-axes of the body before relief, m, and the neck's pinch (fraction, centre, width, m).
HALF_AXES_M = (256.0, 136.0, 112.0)
NECK = (0.35, 40.0, 56.0)
#: Relief: octaves, bumps in the first, the first's angular width (rad) and height (m).
OCTAVES = 5
FIRST_BUMPS = 12
FIRST_WIDTH_RAD = 0.5
FIRST_HEIGHT_M = 19.0
#: Boulders: count, angular radius (rad) and height (m).
BOULDERS = 40
BOULDER_RADIUS_RAD = 0.06
BOULDER_HEIGHT_M = 8.0
#: Albedo (grey, linear) and the icosphere's subdivisions (6: 81 920 faces).
ALBEDO = 0.3
SUBDIVISIONS = 6


def _bumps(dirs: Array, centres: Array, width: float, heights: Array) -> Array:
    """Σ heights · exp(−(angle/width)²) over the bump centres, at each unit direction."""
    angle = np.arccos(np.clip(dirs @ centres.T, -1.0, 1.0))
    return (heights * np.exp(-((angle / width) ** 2))).sum(axis=1)


def _unit(rng: np.random.Generator, n: int) -> Array:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def asteroid_mesh(seed: int = 0, subdivisions: int = SUBDIVISIONS) -> trimesh.Trimesh:
    """The body as a watertight triangle mesh with smooth normals."""
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    dirs = np.asarray(sphere.vertices, dtype=np.float64)
    v = dirs * np.asarray(HALF_AXES_M)
    pinch, centre, width = NECK
    v[:, 1:] *= (1.0 - pinch * np.exp(-(((v[:, 0] - centre) / width) ** 2)))[:, None]
    relief = np.zeros(len(dirs))
    for octave in range(OCTAVES):
        n = FIRST_BUMPS * 2**octave
        heights = FIRST_HEIGHT_M / 1.9**octave * rng.uniform(-1.0, 1.0, n)
        relief += _bumps(dirs, _unit(rng, n), FIRST_WIDTH_RAD / 2**octave, heights)
    angle = np.arccos(np.clip(dirs @ _unit(rng, BOULDERS).T, -1.0, 1.0))
    domes = np.sqrt(np.clip(1.0 - (angle / BOULDER_RADIUS_RAD) ** 2, 0.0, None))
    relief += BOULDER_HEIGHT_M * domes.sum(axis=1)
    shape = trimesh.Trimesh(v, sphere.faces, process=False)
    return untextured_mesh(v + shape.vertex_normals * relief[:, None], sphere.faces, ALBEDO)


def write_asteroid(path: pathlib.Path, seed: int = 0) -> pathlib.Path:
    """Export the body as a binary glTF (GLB) with vertex normals, atomically."""
    return write_glb(path, asteroid_mesh(seed))


def asteroid_path(data_dir: pathlib.Path) -> pathlib.Path:
    """Path of the bench asteroid's GLB under ``data_dir/models``, written first if missing."""
    path = pathlib.Path(data_dir) / "models" / ASTEROID_FILE_NAME
    return path if path.is_file() else write_asteroid(path)
