"""The engine's entry points, shared by the CLI and the RQ job: bytes and JSON in, result out.

Nothing here knows about HTTP, Redis or RQ; progress and cancellation are plain callbacks. The
process's settings are read here and handed to the engine: the Mitsuba variant, and the limits
on images and models (``PROXPOSE_MAX_IMAGE_PIXELS``, ``PROXPOSE_MAX_MODEL_FACES``) that the API
checks uploads against, so that what the API accepts a worker does not refuse.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from schemas.estimate import EstimateRequest, EstimateResult
from schemas.render import RenderRequest
from schemas.settings import get_settings
from worker.align.artifacts import make_artifacts
from worker.align.session import CancelCheck, ProgressCallback
from worker.engine.camera import PinholeCamera
from worker.engine.exceptions import EmptyRenderError
from worker.engine.images import decode_image, encode_png, to_display
from worker.engine.meshes import LoadedModel, load_model
from worker.engine.posemath import pose_from_schema
from worker.engine.variant import choose_variant

log = logging.getLogger(__name__)


def init_renderer_backend() -> str:
    """Pick the Mitsuba variant from the settings (once per process) and return it."""
    settings = get_settings()
    return choose_variant(settings.variant, settings.llvm_path)


def load_target(model_path: str | Path) -> LoadedModel:
    """The model at ``model_path`` under the process's settings: the face limit the API checks
    uploads against, and the on-disk parsed-model cache."""
    settings = get_settings()
    return load_model(model_path, settings.max_model_faces, settings.parsed_model_dir())


def run_estimate(
    model_path: str | Path,
    image: bytes,
    request: EstimateRequest,
    on_iteration: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
    with_artifacts: bool = True,
) -> tuple[EstimateResult, dict[str, bytes]]:
    """Estimate the pose; returns the result (artifact names filled in) and the PNG artifacts."""
    settings = get_settings()
    start = time.perf_counter()
    variant = init_renderer_backend()
    from worker.align.estimator import estimate

    ready = time.perf_counter()
    reference = decode_image(image, settings.max_image_pixels)
    model = load_target(model_path)
    loaded = time.perf_counter()
    log.info(
        "ready: variant %s %.2f s, then reference and model %.2f s",
        variant,
        ready - start,
        loaded - ready,
    )
    est = estimate(model, reference, request, on_iteration, should_cancel)
    artifacts: dict[str, bytes] = {}
    if with_artifacts:
        done = time.perf_counter()
        artifacts = make_artifacts(est.result, est.reference, est.views)
        log.info("artifacts %.2f s", time.perf_counter() - done)
    est.result.artifacts = list(artifacts)
    return est.result, artifacts


def render_png(model_path: str | Path, request: RenderRequest) -> bytes:
    """One render of the model at the request's pose, as an 8-bit sRGB PNG."""
    init_renderer_backend()
    from worker.align.renderers import get_renderer, lighting_spec, texture_level

    model = load_target(model_path)
    camera = PinholeCamera.from_schema(request.camera)
    R, t = pose_from_schema(request.pose)
    renderer = get_renderer(
        model,
        camera,
        lighting_spec(request.lighting),
        (1.0,),
        request.spp,
        texture_level(model, camera, R, t),
    )
    if renderer.coverage(R, t) <= 0.0:
        raise EmptyRenderError("the model is not visible at this pose")
    linear = renderer.render(R, t, spp=request.spp, seed=request.seed)
    return encode_png(to_display(linear))
