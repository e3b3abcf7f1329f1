"""Ray casts against a Mitsuba scene: the points and shading normals a bundle of rays hits."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Ray batches are padded to a multiple of this, so Dr.Jit reuses one compiled kernel.
RAY_BATCH = 4096


def intersect(
    scene: object, origin: Array, dirs: Array, geometric: bool = False
) -> tuple[NDArray[np.bool_], Array, Array]:
    """Intersect rays (common origin) with the scene; batches padded to RAY_BATCH. Returns the
    hits, the points and the shading normals (model frame; zeros where a ray missed), or with
    ``geometric`` the normals of the triangles hit."""
    import drjit as dr
    import mitsuba as mi

    n = len(dirs)
    if mi.variant().startswith("scalar"):
        hits = np.zeros(n, dtype=bool)
        pts = np.zeros((n, 3))
        nrm = np.zeros((n, 3))
        o = mi.Point3f(*origin)
        for i, d in enumerate(dirs):
            si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(*d)))  # type: ignore[attr-defined]
            if si.is_valid():
                hits[i] = True
                pts[i] = [si.p.x, si.p.y, si.p.z]
                m = si.n if geometric else si.sh_frame.n
                nrm[i] = [m.x, m.y, m.z]
        return hits, pts, nrm
    padded = -(-n // RAY_BATCH) * RAY_BATCH
    D = np.zeros((padded, 3))
    D[:n] = dirs
    D[n:] = dirs[0]
    ray = mi.Ray3f(
        mi.Point3f(*[mi.Float(np.full(padded, c, dtype=np.float32)) for c in origin]),
        mi.Vector3f(*[mi.Float(D[:, k].astype(np.float32)) for k in range(3)]),
    )
    si = scene.ray_intersect(ray)  # type: ignore[attr-defined]
    hits = np.array(si.is_valid(), dtype=bool)
    pts = np.stack([np.array(si.p.x), np.array(si.p.y), np.array(si.p.z)], axis=1)
    sh = si.n if geometric else si.sh_frame.n
    nrm = np.stack([np.array(sh.x), np.array(sh.y), np.array(sh.z)], axis=1)
    dr.eval()
    nrm[~hits] = 0.0
    return hits, pts.astype(np.float64), nrm.astype(np.float64)
