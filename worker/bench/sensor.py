"""Is Mitsuba's ``batch`` sensor faster than separate renders for the perturbation views?

The N_s perturbation renders of one iteration could be one render of a ``batch`` sensor whose
children are the perturbed cameras. This measures both on the same model, size and sample
counts, side by side and both replayed from recorded kernels as the engine renders, so the
engine keeps whichever is faster (see the figures in bench/README.md). Run with
``proxpose bench --sensor``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from worker.engine.camera import PinholeCamera
from worker.engine.kernels import frozen_render, plain_render, use_frozen
from worker.engine.meshes import LoadedModel
from worker.engine.posemath import apply_increment, rotvec_to_matrix
from worker.engine.renderer import CV_FROM_MI, LightingSpec, Renderer, scalar_transform

#: Timed repetitions of each variant (after two warm-up runs).
REPEATS = 3


def _pose(model: LoadedModel, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    R = rotvec_to_matrix([0.5, 0.8, 0.2])
    d = 2.5 * model.radius * camera.fx / (0.5 * min(camera.width, camera.height))
    return R, -R @ model.centre + np.array([0.0, 0.0, d])


def _batch_scene(renderer: Renderer, n: int) -> tuple[Any, list[str]]:
    import mitsuba as mi

    scene = renderer.scene_dict()
    sensor = scene.pop("sensor0")
    assert isinstance(sensor, dict)
    film, sampler = sensor.pop("film"), sensor.pop("sampler")
    assert isinstance(film, dict)
    children = {
        # distinct start poses: identical children would be merged into one view
        f"view{i:02d}": {**sensor, "to_world": scalar_transform(np.eye(4) + np.eye(4, k=3) * i)}
        for i in range(n)
    }
    scene["batch"] = {
        "type": "batch",
        "film": {**film, "width": film["width"] * n},
        "sampler": sampler,
        **children,
    }
    loaded = mi.load_dict(scene)
    params = mi.traverse(loaded)
    keys = sorted(k for k in params.keys() if k.startswith("batch.view") and "to_world" in k)
    return (loaded, params), keys


def compare(
    model: LoadedModel, size_px: int = 256, n: int = 12, spps: tuple[int, ...] = (1, 4)
) -> list[dict[str, float]]:
    """Seconds for ``n`` perturbation views as separate renders and as one batch render."""
    camera = PinholeCamera(size_px, size_px, 1.2 * size_px, 1.2 * size_px,
                           size_px / 2 - 0.5, size_px / 2 - 0.5)  # fmt: skip
    R, t = _pose(model, camera)
    rng = np.random.default_rng(0)
    steps = [np.concatenate([rng.normal(size=3) * 5e-3, rng.normal(size=3) * 1e-2 * t[2]])
             for _ in range(n)]  # fmt: skip
    poses = [apply_increment(R, t, dp) for dp in steps]
    return [_compare_at(model, camera, poses, spp) for spp in spps]


def _compare_at(
    model: LoadedModel,
    camera: PinholeCamera,
    poses: list[tuple[np.ndarray, np.ndarray]],
    spp: int,
) -> dict[str, float]:
    import mitsuba as mi

    renderer = Renderer(model, camera, LightingSpec((0.3, -0.5, -0.81), 3.0, 0.02), spp=spp)
    (scene, params), keys = _batch_scene(renderer, len(poses))
    render_batch = frozen_render() if use_frozen(mi.variant()) else plain_render

    def separate() -> None:
        for i, (Ri, ti) in enumerate(poses):
            renderer.render(Ri, ti, spp=spp, seed=i)

    def batched() -> None:
        for key, (Ri, ti) in zip(keys, poses, strict=True):
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = Ri.T @ CV_FROM_MI, -Ri.T @ ti
            params[key] = type(params[key])(M.tolist())
        params.update()
        np.asarray(render_batch(scene, 0, spp, 0))

    sep, bat = _time(separate), _time(batched)
    return {"spp": spp, "views": len(poses), "size_px": camera.width, "separate_s": sep,
            "batch_s": bat, "batch_speedup": sep / bat}  # fmt: skip


def _time(fn: Any) -> float:
    for _ in range(2):
        fn()
    start = time.perf_counter()
    for _ in range(REPEATS):
        fn()
    return (time.perf_counter() - start) / REPEATS
