"""``/v1/models``: register, list, show and delete target models."""

from __future__ import annotations

import hashlib
import re
from datetime import UTC, datetime
from pathlib import PurePath
from typing import Annotated

from fastapi import APIRouter, File, Form, Response, UploadFile

from schemas.models import (
    MODEL_ID_HEX_DIGITS,
    MODEL_ID_PATTERN,
    MODEL_NAME_MAX_CHARS,
    ModelList,
    ModelPublic,
)
from schemas.names import BUILTIN_MODEL_IDS
from service.auth import PrincipalDep
from service.deps import ModelStoreDep, Multipart, SettingsDep
from service.errors import ApiError, field_error, not_found
from service.uploads import UploadRejected, inspect_model, model_format

router = APIRouter(prefix="/v1/models", tags=["models"])

_ID = re.compile(MODEL_ID_PATTERN)


def _get_or_404(models: ModelStoreDep, model_id: str) -> ModelPublic:
    model = models.get(model_id) if _ID.match(model_id) else None
    if model is None and model_id in BUILTIN_MODEL_IDS:
        msg = f"model '{model_id}' is not registered yet: the first worker to start registers it"
        raise ApiError(404, detail=msg, code="not_found")
    if model is None:
        raise not_found("model", model_id)
    return model


@router.post(
    "",
    status_code=201,
    response_model=ModelPublic,
    summary="Register a model file",
    dependencies=[Multipart],
    description="Upload a mesh (OBJ, PLY, STL, GLB or GLTF with embedded buffers). The id is "
    "the file's content address: uploading the same bytes again answers 200 with the model "
    "already registered (under the name first given).",
    responses={
        200: {"model": ModelPublic, "description": "This key registered the same file before."},
        403: {"description": "The key has max_models_per_key models already."},
        413: {"description": "The file is larger than max_model_bytes."},
        415: {"description": "The body is not multipart/form-data."},
        422: {"description": "Not a readable mesh, too many faces, or a bad name."},
        429: {"description": "The key submits too fast; see `Retry-After`."},
    },
)
def create_model(
    file: Annotated[UploadFile, File(description="The mesh: .obj, .ply, .stl, .glb or .gltf.")],
    models: ModelStoreDep,
    settings: SettingsDep,
    principal: PrincipalDep,
    response: Response,
    name: Annotated[
        str | None,
        Form(
            min_length=1,
            max_length=MODEL_NAME_MAX_CHARS,
            description="Display name (default: the file name without extension).",
        ),
    ] = None,
) -> ModelPublic:
    try:
        file_format = model_format(file.filename)
    except UploadRejected as exc:
        raise field_error(422, ("body", "file"), str(exc), exc.code) from exc
    data = file.file.read(settings.max_model_bytes + 1)
    if len(data) > settings.max_model_bytes:
        raise field_error(
            413,
            ("body", "file"),
            f"the model file is larger than the limit of {settings.max_model_bytes} bytes",
            "too_large",
        )
    sha = hashlib.sha256(data).hexdigest()
    model_id = sha[:MODEL_ID_HEX_DIGITS]
    response.headers["Location"] = f"/v1/models/{model_id}"
    existing = models.get(model_id)
    if existing is not None:
        response.status_code = 200
        return existing
    quota = settings.max_models_per_key
    if quota and models.owned(principal.name) >= quota:
        raise ApiError(
            403,
            detail=f"API key '{principal.name}' has registered {quota} models, the most allowed "
            "(max_models_per_key); delete one first",
            code="model_quota",
        )
    try:
        info = inspect_model(data, file_format, settings.max_model_faces)
    except UploadRejected as exc:
        raise field_error(422, ("body", "file"), str(exc), exc.code) from exc
    model = ModelPublic(
        id=model_id,
        name=name or PurePath(file.filename or "model").stem,
        vertices=info.vertices,
        faces=info.faces,
        bounds=info.bounds,
        textured=info.textured,
        format=info.format,
        size_bytes=len(data),
        sha256=sha,
        created_at=datetime.now(UTC),
    )
    models.put(model, data, owner=principal.name)
    return model


@router.get("", response_model=ModelList, summary="List the registered models, newest first")
def list_models(models: ModelStoreDep) -> ModelList:
    return ModelList(items=models.list())


@router.get(
    "/{model_id}",
    response_model=ModelPublic,
    summary="Show one model",
    responses={404: {"description": "No such model."}},
)
def get_model(model_id: str, models: ModelStoreDep) -> ModelPublic:
    return _get_or_404(models, model_id)


@router.delete(
    "/{model_id}",
    status_code=204,
    summary="Delete a model",
    description="Drops this key's registration of the model; the file goes when no key has it "
    "any more (an admin key deletes it for everyone). Jobs already queued for a deleted model "
    "fail with 'model_not_found'. The built-in demo-sat cannot be deleted.",
    responses={404: {"description": "No such model."}, 409: {"description": "Built in."}},
)
def delete_model(model_id: str, models: ModelStoreDep) -> Response:
    model = _get_or_404(models, model_id)
    if model.builtin:
        raise ApiError(
            409, detail=f"model '{model_id}' is built in and cannot be deleted", code="builtin"
        )
    models.delete(model_id)
    return Response(status_code=204)
