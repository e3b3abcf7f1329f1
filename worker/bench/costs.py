"""What an estimate costs beside its seconds: render-equivalents and peak memory.

A *render-equivalent* is the time of one full-resolution render of the case's model through
its camera (the estimator's main spp), measured in the same run: engine seconds ÷ that time
says how many full renders' worth an estimate takes, whatever the machine. Peak memory is the
process's resident high-water mark during the estimate (Linux: reset through
/proc/self/clear_refs, read from VmHWM), and its *rise*: that mark less the resident memory when
the estimate started (what the estimate itself added to a process that already held the
libraries, the cached renderers and the earlier cases); elsewhere neither is reported.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from schemas.estimate import EstimateRequest
from worker.engine.meshes import LoadedModel

#: Untimed renders before the timed ones: a frozen render records its kernels on its first call
#: and once more on its second (Dr.Jit; seen on a bare Mitsuba scene), then replays them.
UNTIMED_RENDERS = 2
#: Timed renders per case; the median is kept.
RENDER_REPEATS = 5
_STATUS = Path("/proc/self/status")
_CLEAR_REFS = Path("/proc/self/clear_refs")


def full_render_seconds(model: LoadedModel, request: EstimateRequest) -> float:
    """Median time of one full-resolution render at the request's true pose (its camera,
    lighting and main spp), s."""
    from worker.align.renderers import get_renderer, lighting_spec, texture_level
    from worker.engine.camera import PinholeCamera
    from worker.engine.posemath import pose_from_schema

    camera = PinholeCamera.from_schema(request.camera)
    pose = request.ground_truth or request.initial_pose
    R, t = pose_from_schema(pose)
    spp = request.options.resolved().spp
    level = texture_level(model, camera, R, t)
    renderer = get_renderer(model, camera, lighting_spec(request.lighting), (1.0,), spp, level)
    for _ in range(UNTIMED_RENDERS):
        renderer.render(R, t, spp=spp)
    times = []
    for i in range(RENDER_REPEATS):
        start = time.perf_counter()
        renderer.render(R, t, spp=spp, seed=i)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def reset_peak_memory() -> None:
    """Start a new resident-memory high-water mark (no-op where the OS has none to reset)."""
    try:
        _CLEAR_REFS.write_text("5")
    except OSError:
        pass


def peak_memory_mb() -> float | None:
    """The resident-memory high-water mark since the last reset, MiB (None: unknown)."""
    return _status_mb("VmHWM:")


def resident_memory_mb() -> float | None:
    """The process's resident memory now, MiB (None: unknown)."""
    return _status_mb("VmRSS:")


def _status_mb(field: str) -> float | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return None
