"""Overlays of a tracked sequence: a frame in red and the render at its tracked pose in blue
(aligned structure turns magenta), for a few chosen frames of the track job."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from schemas.settings import get_settings
from schemas.track import TrackRequest, TrackResult
from worker.align.artifacts import overlay
from worker.align.renderers import get_renderer, lighting_spec, texture_level
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import EstimationCancelled
from worker.engine.images import decode_image, to_grey
from worker.entry import load_target
from worker.tracking import FrameFile

#: Samples per pixel of an overlay's render (the overlay shows structure, not noise).
OVERLAY_SPP = 4


@dataclass(frozen=True)
class _Render:
    """What :func:`worker.align.artifacts.overlay` reads of a rendered view: its grey image."""

    grey: NDArray[np.float32]


def overlay_indices(result: TrackResult, max_frames: int) -> list[int]:
    """Up to ``max_frames`` frame indices, in order: every frame of a short sequence; else the
    lost and re-initialised ones (up to half the budget), then frames evenly spread."""
    n = len(result.frames)
    if n <= max_frames:
        return list(range(n))
    notable = [f.index for f in result.frames if f.status != "tracked"][: max_frames // 2]
    spread = np.linspace(0, n - 1, max_frames - len(notable)).round().astype(int)
    return sorted(set(notable) | {int(k) for k in spread})[:max_frames]


def overlays(
    model_path: str | Path,
    frames: Sequence[FrameFile],
    request: TrackRequest,
    result: TrackResult,
    indices: Sequence[int],
    should_cancel: Callable[[], bool] | None = None,
) -> dict[str, bytes]:
    """``overlay_<k>`` PNGs of frames ``indices``: each frame with the render at its pose."""
    if not indices:
        return {}
    settings = get_settings()
    model = load_target(model_path)
    camera = PinholeCamera.from_schema(request.camera)
    first = result.frames[indices[0]].pose
    R0, t0 = np.asarray(first.R, dtype=np.float64), np.asarray(first.t, dtype=np.float64)
    renderer = get_renderer(
        model,
        camera,
        lighting_spec(request.lighting),
        (1.0,),
        OVERLAY_SPP,
        texture_level(model, camera, R0, t0),
    )
    out: dict[str, bytes] = {}
    for k in indices:
        if should_cancel is not None and should_cancel():
            raise EstimationCancelled("the track was stopped while drawing its overlays")
        pose = result.frames[k].pose
        R, t = np.asarray(pose.R, dtype=np.float64), np.asarray(pose.t, dtype=np.float64)
        linear = renderer.render(R, t, spp=OVERLAY_SPP)
        reference = decode_image(frames[k].data, settings.max_image_pixels)
        out[f"overlay_{k}"] = overlay(reference, _Render(to_grey(linear)))  # type: ignore[arg-type]
    return out
