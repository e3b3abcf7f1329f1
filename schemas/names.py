"""Names and limits the API and the worker share: one definition each, read by both sides.

The API checks uploads against these (and against the settings built on the limits); the
worker's engine reads models and images with the same tables, and its errors carry the codes
listed here, which a failed job or render reports as ``JobError.code``.
"""

from __future__ import annotations

from typing import Literal

#: Id of the built-in demo satellite, registered by every worker when it starts.
DEMO_MODEL_ID = "demo-sat"
#: Id of the built-in demo terrain (a cratered heightfield, metres), registered beside it.
DEMO_TERRAIN_ID = "demo-terrain"
#: The built-in models: registered by every worker, accepted before one has, never deleted.
BUILTIN_MODEL_IDS = (DEMO_MODEL_ID, DEMO_TERRAIN_ID)

#: Model file extensions accepted, with the format (trimesh file type) each is read as.
MODEL_FILE_TYPES = {".obj": "obj", ".ply": "ply", ".stl": "stl", ".glb": "glb", ".gltf": "gltf"}
#: Reference image formats accepted (PIL's names; checked from the header before decoding).
IMAGE_FORMATS = ("PNG", "JPEG", "TIFF")

#: Default of PROXPOSE_MAX_IMAGE_PIXELS: the largest reference image, pixels (a
#: decompression-bomb guard, checked from the header by the API and again by the worker).
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
#: Default of PROXPOSE_MAX_MODEL_FACES: the most triangles a model may have (counted from the
#: file's header by the API, and over the loaded meshes by the worker).
DEFAULT_MAX_MODEL_FACES = 2_000_000

#: Codes of the engine's named errors (``worker.engine.exceptions``): the generic two, then
#: unusable input, then estimates that cannot proceed.
EngineErrorCode = Literal[
    "engine_error",
    "invalid_input",
    "invalid_pose",
    "invalid_image",
    "image_too_large",
    "image_size_mismatch",
    "invalid_model",
    "model_too_large",
    "render_failed",
    "empty_render",
    "unlit_render",
    "too_few_features",
    "cancelled",
]
#: Codes a failed job or render reports: the engine's, and those the worker process and the
#: job store add (the model is not registered; the job ran out of time; its workers died
#: ``job_max_attempts`` times; the blob store was down or full on each of its attempts;
#: anything else, with the traceback kept for operators).
JobErrorCode = Literal[
    EngineErrorCode,
    "model_not_found",
    "timeout",
    "worker_lost",
    "store_unavailable",
    "internal_error",
]
#: Codes of a rejected upload (the ``type`` of its 422 answer): the engine's codes for the
#: same faults, and a file type that is not accepted at all.
UploadErrorCode = Literal[
    "invalid_image",
    "image_too_large",
    "invalid_model",
    "model_too_large",
    "unsupported_format",
]
