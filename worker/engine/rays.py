"""Ray casts against a Mitsuba scene: the points and shading normals a bundle of rays hits."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Ray batches are padded to a multiple of this, so Dr.Jit reuses one compiled kernel.
RAY_BATCH = 4096
#: Byte alignment of the arrays handed to Dr.Jit (a cache line; AVX needs 32).
KERNEL_ALIGN = 64


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
    D = np.empty((padded, 3))
    D[:n] = dirs
    D[n:] = dirs[0]
    o3, d3 = drjit_floats(np.broadcast_to(origin, (padded, 3))), drjit_floats(D)
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o3), mi.Vector3f(*d3)))  # type: ignore[attr-defined]
    valid, sh = si.is_valid(), si.n if geometric else si.sh_frame.n
    dr.eval(valid, si.p, sh)  # one kernel for all three: each read alone traced the rays again
    hits, nrm = np.array(valid, dtype=bool), numpy_vectors(sh)
    nrm[~hits] = 0.0
    return hits, numpy_vectors(si.p), nrm


def numpy_vectors(v: object) -> Array:
    """A Dr.Jit 3-vector array (x, y, z of N each) as an (N, 3) float64 array."""
    xyz = [np.array(v.x), np.array(v.y), np.array(v.z)]  # type: ignore[attr-defined]
    return np.stack(xyz, axis=1).astype(np.float64)


def drjit_floats(columns: NDArray[np.floating]) -> list[object]:
    """The columns of an (N, k) array as k Dr.Jit Floats, each copied to a KERNEL_ALIGN-byte
    boundary first. Dr.Jit reads a NumPy array in place and compiles the alignment it finds into
    the kernel: NumPy's 16-byte-aligned buffers made a kernel per combination of aligned
    inputs, each compiled again (~45 ms at 4096 rays) the first time it came up."""
    import mitsuba as mi

    n, k = columns.shape
    per_line = KERNEL_ALIGN // 4  # float32s
    row = -(-n // per_line) * per_line  # each column starts aligned
    buf = np.empty(k * row + per_line, dtype=np.float32)
    skip = (-buf.ctypes.data % KERNEL_ALIGN) // 4
    cols = buf[skip : skip + k * row].reshape(k, row)
    cols[:, :n] = columns.T
    return [mi.Float(c[:n]) for c in cols]
