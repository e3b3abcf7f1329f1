"""The names the API and the worker share (schemas/names.py) are the ones both sides use: the
error codes match the engine's named errors, and the engine's defaults are the settings'."""

from __future__ import annotations

import inspect
from typing import get_args

from schemas.names import (
    DEFAULT_MAX_IMAGE_PIXELS,
    DEFAULT_MAX_MODEL_FACES,
    EngineErrorCode,
    JobErrorCode,
    UploadErrorCode,
)
from schemas.settings import Settings


def _engine_errors() -> list[type]:
    from worker.engine import exceptions

    return [
        c
        for c in vars(exceptions).values()
        if inspect.isclass(c) and issubclass(c, exceptions.ProxposeError)
    ]


def test_every_engine_error_has_its_own_listed_code() -> None:
    codes = [c.code for c in _engine_errors()]
    assert sorted(codes) == sorted(get_args(EngineErrorCode))  # each listed code, once


def test_job_codes_are_the_engines_and_the_workers() -> None:
    from service.store.blobs import BlobStoreUnavailable
    from worker.jobs.models import ModelNotFoundError

    worker_codes = {ModelNotFoundError.code, "timeout", "worker_lost", "internal_error"}
    worker_codes.add(BlobStoreUnavailable.code)  # the blob store, down or full
    assert set(get_args(JobErrorCode)) == set(get_args(EngineErrorCode)) | worker_codes


def test_upload_codes_are_the_engines_for_the_same_faults() -> None:
    assert set(get_args(UploadErrorCode)) - set(get_args(EngineErrorCode)) == {"unsupported_format"}


def test_the_engine_defaults_are_the_settings_defaults() -> None:
    from worker.engine.images import decode_image
    from worker.engine.meshes import load_model

    defaults = Settings()
    assert defaults.max_image_pixels == DEFAULT_MAX_IMAGE_PIXELS
    assert defaults.max_model_faces == DEFAULT_MAX_MODEL_FACES
    assert inspect.signature(decode_image).parameters["max_pixels"].default == (
        DEFAULT_MAX_IMAGE_PIXELS
    )
    assert inspect.signature(load_model).parameters["max_faces"].default == (
        DEFAULT_MAX_MODEL_FACES
    )
