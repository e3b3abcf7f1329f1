"""The renderers of a process: one per (model, camera, scales, texture level, shading, window
sizes), kept.

Building a Mitsuba scene and tracing its kernels costs far more than a render, so estimates
and render jobs on the same model and camera reuse one renderer, relit for each request.

Only one model's renderers are kept: a renderer built for another model first lets the others
go. Dr.Jit traces a call on a material, shape or light over every live instance of its kind, so
a kept scene of another model took part in every render recorded for this one (each new window
side or spp is recorded once per renderer: a tracker records them as the target grows): an ISS
sequence tracked after a demo satellite's in one process spent 4.3–8.6 s rendering, 2.9 s with
the demo's renderers let go, each recording's trace ~70 ms instead of ~14. The worker runs its
jobs in its own process (worker.jobs.runner), so this is what a worker serving several models
meets; its price is a scene built again at each change of model (bench/README.md, "Another
model's renderers slow this one's").
"""

from __future__ import annotations

import gc
import math
from collections import OrderedDict

import numpy as np

from schemas.lighting import Lighting
from worker.engine.camera import PinholeCamera
from worker.engine.meshes import LoadedModel
from worker.engine.renderer import LightingSpec, Renderer
from worker.engine.scene_meshes import TEXELS_PER_PIXEL

#: Renderers kept per process, all of one model (scene build and kernel tracing are paid once
#: per entry).
RENDERER_CACHE_SIZE = 4

_renderers: OrderedDict[tuple[object, ...], Renderer] = OrderedDict()


def release_other_models(sha256: str) -> None:
    """Let go of the kept renderers of models other than ``sha256`` (see the module docstring);
    a caller still holding one keeps it working. Their scenes are freed before the next one is
    built (a collection: Mitsuba objects can sit in reference cycles)."""
    others = [key for key in _renderers if key[0] != sha256]
    for key in others:
        del _renderers[key]
    if others:
        gc.collect()


def texture_level(model: LoadedModel, camera: PinholeCamera, R: np.ndarray, t: np.ndarray) -> int:
    """Half-octave level of the image scale (px per scene unit) at the target's range, capped
    at the first level that uses every texture as it is (0 for an untextured model): the
    levels above it build the same scene, and a renderer per level would build and record it
    again for every range band (an ISS bench estimate at a second range: 3.3 s, 1.9 s sharing
    the first one's renderer)."""
    finest = model.finest_texels_per_unit
    if finest <= 0.0:
        return 0
    d = float(np.linalg.norm(R @ model.centre + t))
    level = round(2.0 * np.log2(0.5 * (camera.fx + camera.fy) / d))
    return min(level, math.ceil(2.0 * np.log2(finest / TEXELS_PER_PIXEL)))


def lighting_spec(lighting: Lighting) -> LightingSpec:
    """The renderer's lighting from the request's."""
    return LightingSpec(tuple(lighting.sun_direction), lighting.sun_irradiance, lighting.ambient)


def get_renderer(
    model: LoadedModel,
    camera: PinholeCamera,
    lighting: LightingSpec,
    scales: tuple[float, ...],
    spp: int,
    level: int = 0,
    shading: str = "file",
    windows: tuple[tuple[float, tuple[int, int]], ...] = (),
) -> Renderer:
    """A renderer for (model, camera, scales, texture level, shading, window sizes), reused
    across estimates while they are of the same model."""
    key = (model.sha256, camera, scales, level, shading, windows)
    renderer = _renderers.get(key)
    if renderer is None:
        release_other_models(model.sha256)
        renderer = Renderer(
            model,
            camera,
            lighting,
            scales=scales,
            spp=spp,
            px_per_unit=2.0 ** (level / 2.0),
            shading=shading,
            window_sizes=dict(windows),
        )
        _renderers[key] = renderer
        while len(_renderers) > RENDERER_CACHE_SIZE:
            _renderers.popitem(last=False)
    else:
        _renderers.move_to_end(key)
        renderer.set_lighting(lighting)
    return renderer
