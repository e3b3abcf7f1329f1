"""Ray casts: one compiled kernel per cast, the same one whatever NumPy's buffers look like."""

from __future__ import annotations

import numpy as np
import pytest

from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.rays import drjit_floats
from worker.engine.renderer import LightingSpec, Renderer

CAMERA = PinholeCamera(96, 96, 120.0, 120.0, 47.5, 47.5)
LIGHT = LightingSpec((0.4, -0.5, -0.77), 3.0, 0.02)


def _misaligned(a: np.ndarray, offset_bytes: int) -> np.ndarray:
    """A copy of ``a`` whose buffer starts ``offset_bytes`` past a 64-byte boundary."""
    raw = np.zeros(a.nbytes + 128, dtype=np.uint8)
    start = (-raw.ctypes.data % 64) + offset_bytes
    out = np.frombuffer(raw[start : start + a.nbytes].data, dtype=a.dtype).reshape(a.shape)
    out[...] = a
    return out


def test_a_cast_is_one_kernel_and_one_hash_whatever_the_alignment(
    variant: str, demo_model: LoadedModel
) -> None:
    """Before: each of the hits, points and normals was read by its own kernel (seven traces
    of the same rays), and Dr.Jit compiled the inputs' alignment into each, so a cast whose
    NumPy copies fell on other boundaries compiled them all again (~45 ms each)."""
    if variant.startswith("scalar"):
        pytest.skip(f"{variant} casts rays one by one, without Dr.Jit kernels")
    import drjit as dr

    renderer = Renderer(demo_model, CAMERA, LIGHT, spp=4)
    R, t = np.eye(3), np.array([0.0, 0.0, 4.0 * demo_model.radius]) - demo_model.centre
    rng = np.random.default_rng(5)
    uv = rng.uniform(0.0, 95.0, size=(300, 2))
    expected_points, expected_hit = renderer.raycast(R, t, uv)
    assert 0 < expected_hit.sum() < len(uv)  # some rays hit the satellite, some miss
    hashes = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for offset in (0, 8, 16, 24, 40, 56):
            dr.kernel_history_clear()
            points, hit = renderer.raycast(R, t, _misaligned(uv, offset))
            launched = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
            assert len(launched) == 1, offset
            hashes.append(launched[0]["hash"])
            assert np.array_equal(hit, expected_hit) and np.array_equal(points, expected_points)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(set(hashes)) == 1


def test_the_floats_handed_to_drjit_hold_the_columns_of_a_misaligned_array(variant: str) -> None:
    """Their alignment shows in the kernels (the test above); here, their values."""
    if variant.startswith("scalar"):
        pytest.skip(f"{variant} has no Dr.Jit arrays to align")
    columns = _misaligned(np.arange(3 * 37, dtype=np.float64).reshape(37, 3), 8)
    floats = drjit_floats(columns)
    assert len(floats) == 3
    for k, f in enumerate(floats):
        assert np.array_equal(np.array(f), columns[:, k].astype(np.float32))
