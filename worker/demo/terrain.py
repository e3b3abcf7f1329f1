"""The procedural demo terrain, registered as ``demo-terrain``: a DEM-like cratered heightfield.

A square patch ``TERRAIN_SIDE_M`` on a side, sampled on a regular grid (a digital elevation
model), in metres, glTF axes (+y up, the patch in the x–z plane, centred on the origin). The
relief is fractal noise with a power-law spectrum (amplitude ∝ wavelength^H, H the Hurst
exponent) plus craters whose diameters follow a power law, N(> D) ∝ D^−2 (the cumulative
size–frequency slope of fresh crater populations), each a parabolic bowl with a raised rim and
an ejecta blanket decaying as (r/R)^−3. Two generators: ``"fractal"`` (the demo and the tuning
set) and ``"ridged"`` (ridged multifractal relief, 1 − |noise|, kept out of any tuning and used
as a held-out check). Untextured: the relief alone makes the image, as on an airless body lit
by a low sun.
"""

from __future__ import annotations

import pathlib

import numpy as np
import trimesh
from numpy.typing import NDArray

from worker.demo.geometry import untextured_mesh, write_glb

Array = NDArray[np.float64]

TERRAIN_MODEL_NAME = "Demo terrain (procedural cratered DEM)"
TERRAIN_FILE_NAME = "demo-terrain-v1.glb"
#: Side of the patch, m, and grid posts per side (the DEM's resolution is side / (posts − 1)).
TERRAIN_SIDE_M = 2000.0
TERRAIN_POSTS = 513
#: Standard deviation of the fractal relief, m, and its Hurst exponent.
RELIEF_STD_M = 18.0
HURST = 0.6
#: Crater diameters, m (smallest, largest), the cumulative power-law slope, and the count.
CRATER_DIAMETER_M = (15.0, 400.0)
CRATER_SLOPE = 2.0
CRATER_COUNT = 350
#: Depth over diameter of a fresh simple crater, and rim height over diameter.
CRATER_DEPTH_RATIO = 0.2
CRATER_RIM_RATIO = 0.04
#: Albedo of the regolith (grey, linear).
REGOLITH_ALBEDO = 0.35


def fractal_relief(n: int, side_m: float, rng: np.random.Generator, ridged: bool) -> Array:
    """(n, n) heights, m: Gaussian noise with amplitude spectrum ∝ k^−(H+1) (spectral synthesis),
    or its ridged version (1 − |noise| sharpens the crests) with the same standard deviation."""
    k = np.fft.fftfreq(n, d=side_m / n)
    kk = np.hypot(*np.meshgrid(k, k, indexing="ij"))
    kk[0, 0] = np.inf
    amp = kk ** -(HURST + 1.0)
    noise = np.fft.fft2(rng.standard_normal((n, n)))
    z = np.real(np.fft.ifft2(noise * amp))
    z = (z - z.mean()) / max(float(z.std()), 1e-12)
    if ridged:
        z = 1.0 - np.abs(z)
        z = z**2
        z = (z - z.mean()) / max(float(z.std()), 1e-12)
    return RELIEF_STD_M * z


def crater_diameters_m(count: int, rng: np.random.Generator) -> Array:
    """``count`` diameters with N(> D) ∝ D^−slope between CRATER_DIAMETER_M (inverse CDF)."""
    lo, hi = CRATER_DIAMETER_M
    u = rng.uniform(size=count)
    a, b = lo**-CRATER_SLOPE, hi**-CRATER_SLOPE
    return (a - u * (a - b)) ** (-1.0 / CRATER_SLOPE)


def crater_profile(r: Array, D: float) -> Array:
    """Height change, m, at distance ``r`` (m) from the centre of a crater of diameter ``D``:
    a parabolic bowl inside the rim, an ejecta blanket ∝ (r/R)^−3 outside."""
    R = D / 2.0
    x = r / R
    depth, rim = CRATER_DEPTH_RATIO * D, CRATER_RIM_RATIO * D
    inside = (rim + depth) * x**2 - depth
    outside = rim * np.clip(x, 1.0, None) ** -3.0
    return np.where(x < 1.0, inside, outside) * (x < 3.0)


def heightfield(seed: int = 0, generator: str = "fractal", posts: int = TERRAIN_POSTS) -> Array:
    """(posts, posts) heights, m, over the patch [−side/2, side/2]² (rows along z, columns x)."""
    if generator not in ("fractal", "ridged"):
        raise ValueError(f"generator must be 'fractal' or 'ridged', got {generator!r}")
    rng = np.random.default_rng([seed, 0 if generator == "fractal" else 1])
    z = fractal_relief(posts, TERRAIN_SIDE_M, rng, ridged=generator == "ridged")
    axis = np.linspace(-TERRAIN_SIDE_M / 2, TERRAIN_SIDE_M / 2, posts)
    X, Z = np.meshgrid(axis, axis)
    for D in np.sort(crater_diameters_m(CRATER_COUNT, rng))[::-1]:
        cx, cz = rng.uniform(-TERRAIN_SIDE_M / 2, TERRAIN_SIDE_M / 2, 2)
        z = z + crater_profile(np.hypot(X - cx, Z - cz), float(D))
    return z - z.mean()


def heightfield_mesh(heights: Array, side_m: float = TERRAIN_SIDE_M) -> trimesh.Trimesh:
    """The DEM as a triangle mesh (two triangles per grid cell, faces up, smooth normals)."""
    n = heights.shape[0]
    axis = np.linspace(-side_m / 2, side_m / 2, n)
    X, Z = np.meshgrid(axis, axis)
    V = np.stack([X.ravel(), heights.ravel(), Z.ravel()], 1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + 1, a + n, a + n + 1
    # counter-clockwise seen from +y: (a, c, b) has normal (c − a) × (b − a) ∝ +y
    F = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return untextured_mesh(V, F, REGOLITH_ALBEDO)


def write_demo_terrain(
    path: pathlib.Path, seed: int = 0, generator: str = "fractal", posts: int = TERRAIN_POSTS
) -> pathlib.Path:
    """Export the terrain as a binary glTF (GLB) with vertex normals, atomically."""
    return write_glb(path, heightfield_mesh(heightfield(seed, generator, posts)))


def demo_terrain_path(data_dir: pathlib.Path) -> pathlib.Path:
    """Path of the demo terrain GLB under ``data_dir/models``, written first if missing."""
    path = pathlib.Path(data_dir) / "models" / TERRAIN_FILE_NAME
    if not path.is_file():
        write_demo_terrain(path)
    return path
