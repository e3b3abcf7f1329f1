"""The model files jobs need: a cache on the worker's disk by content hash, filled from the
blob store.

A job reads a registered model's bytes from the blob store once per worker and keeps them under
``data_dir/cache/models/<sha256>.<format>``; the engine caches the loaded model per process.
The built-in demo satellite and demo terrain are registered by every worker when it starts.
"""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime
from pathlib import Path

import redis

from schemas.models import ModelPublic
from schemas.names import DEMO_MODEL_ID, DEMO_TERRAIN_ID
from service.store import Keys, ModelStore
from service.store.blobs import BlobStore, model_file_name
from service.store.files import write_atomic
from worker.engine.exceptions import ProxposeError


class ModelNotFoundError(ProxposeError):
    """The job names a model that is not (or no longer) registered."""

    code = "model_not_found"


def model_cache_path(data_dir: Path, model: ModelPublic) -> Path:
    """Where a worker keeps a model's file: by content hash, with the format's extension."""
    return Path(data_dir) / "cache" / "models" / f"{model.sha256}.{model.format}"


def fetch_model_file(models: ModelStore, model_id: str, data_dir: Path) -> Path:
    """The local path of a registered model's file, downloaded from the blob store on first
    use (BlobStoreUnavailable if it is down)."""
    meta = models.get(model_id)
    if meta is None:
        raise ModelNotFoundError(f"model '{model_id}' is not registered (was it deleted?)")
    path = model_cache_path(data_dir, meta)
    if path.is_file():
        return path
    data = models.data(model_id)
    if data is None or hashlib.sha256(data).hexdigest() != meta.sha256:
        raise ModelNotFoundError(f"the file of model '{model_id}' is missing from the store")
    write_atomic(path, data)
    return path


def register_demo_model(
    r: redis.Redis, keys: Keys, data_dir: Path, blobs: BlobStore
) -> ModelPublic:
    """Register the built-in models: the demo satellite as 'demo-sat' and the demo terrain as
    'demo-terrain' (each generated on first use; idempotent). Returns demo-sat's record."""
    from worker.demo.satellite import DEMO_MODEL_NAME, demo_satellite_path
    from worker.demo.terrain import TERRAIN_MODEL_NAME, demo_terrain_path

    path = demo_terrain_path(Path(data_dir))
    register_builtin_model(r, keys, data_dir, blobs, DEMO_TERRAIN_ID, TERRAIN_MODEL_NAME, path)
    path = demo_satellite_path(Path(data_dir))
    return register_builtin_model(r, keys, data_dir, blobs, DEMO_MODEL_ID, DEMO_MODEL_NAME, path)


def register_builtin_model(
    r: redis.Redis,
    keys: Keys,
    data_dir: Path,
    blobs: BlobStore,
    model_id: str,
    name: str,
    path: Path,
) -> ModelPublic:
    """Register the file at ``path`` as built-in model ``model_id`` (idempotent). Its file is
    written to the blob store every time (atomic, same bytes), so a store that lost it, or a
    deployment that kept it in Redis, has it again (BlobStoreUnavailable if it is down)."""
    from worker.engine.meshes import load_model

    data = path.read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    models = ModelStore(r, keys, blobs=blobs)
    current = models.get(model_id)
    if current is not None and current.sha256 == sha:
        meta = current
        blobs.put(model_file_name(model_id, sha), data)
    else:
        loaded = load_model(path)
        meta = ModelPublic(
            id=model_id,
            name=name,
            vertices=loaded.n_vertices,
            faces=loaded.n_faces,
            bounds=loaded.bounds.tolist(),
            textured=loaded.textured,
            format="glb",
            size_bytes=len(data),
            sha256=sha,
            created_at=datetime.now(UTC),
            builtin=True,
        )
        models.put(meta, data)
    if not model_cache_path(data_dir, meta).is_file():
        write_atomic(model_cache_path(data_dir, meta), data)
    return meta
