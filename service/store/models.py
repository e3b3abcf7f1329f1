"""Models: metadata hash per id in Redis, the owners of each, indexes; the file in the blob store.

Ids are content addresses (a SHA-256 prefix), so the same bytes registered twice are stored once;
each API key that registers them becomes an owner, under the name it gave. A store built for a
``viewer`` sees the built-in models and the ones the viewer owns (an admin sees all), and a
viewer's delete only drops its ownership: the file goes when its last owner lets go. The
built-in demo satellite has the fixed id ``demo-sat`` and is (re)registered by workers.

The file is the blob ``models/<id>/<sha256>``, written before the metadata that refers to it and
deleted after the last owner lets go (the sweeper deletes it if that delete fails). A model of an
older deployment whose bytes are still in Redis (``model:<id>:data``) is read from there.
"""

from __future__ import annotations

import logging
import time

import redis

from schemas.models import ModelPublic
from schemas.names import BUILTIN_MODEL_IDS
from service.store.access import Principal
from service.store.blobs.base import BlobStore, BlobStoreError, model_file_name
from service.store.keys import Keys

log = logging.getLogger(__name__)


class ModelStore:
    """Reads and writes registered models. ``r`` is a bytes-returning Redis client; ``blobs``
    holds the files (needed by ``data``, ``put`` and ``delete``)."""

    def __init__(
        self,
        r: redis.Redis,
        keys: Keys,
        viewer: Principal | None = None,
        blobs: BlobStore | None = None,
    ) -> None:
        self.r = r
        self.keys = keys
        self.viewer = viewer
        self._blobs = blobs

    @property
    def blobs(self) -> BlobStore:
        if self._blobs is None:
            raise RuntimeError("this ModelStore was made without a blob store")
        return self._blobs

    def _sees_all(self) -> bool:
        return self.viewer is None or self.viewer.admin

    def get(self, model_id: str) -> ModelPublic | None:
        """The model as the viewer named it, or None if absent or not the viewer's."""
        pipe = self.r.pipeline(transaction=False)
        pipe.hget(self.keys.model(model_id), "meta")
        pipe.hget(self.keys.model_owners(model_id), self.viewer.name if self.viewer else "")
        raw, own_name = pipe.execute()
        if not raw:
            return None
        model = ModelPublic.model_validate_json(raw)
        if own_name:
            return model.model_copy(update={"name": own_name.decode()})
        return model if model.builtin or self._sees_all() else None

    def exists(self, model_id: str) -> bool:
        return self.get(model_id) is not None

    def data(self, model_id: str) -> bytes | None:
        """The model's file (None if the model or its file is gone)."""
        meta = self._meta(model_id)
        if meta is None:
            return None
        data = self.blobs.get(model_file_name(model_id, meta.sha256))
        if data is None:  # registered by an older deployment: still in Redis
            data = self.r.get(self.keys.model_data(model_id))  # type: ignore[assignment]
        return data

    def owned(self, owner: str) -> int:
        """How many models ``owner`` has registered."""
        return int(self.r.zcard(self.keys.owner_models(owner)))  # type: ignore[arg-type]

    def list(self) -> list[ModelPublic]:
        """The models the viewer sees, newest first (dangling index entries are pruned)."""
        index = self.keys.models_index
        if not self._sees_all():
            assert self.viewer is not None
            index = self.keys.owner_models(self.viewer.name)
        ids = [m.decode() for m in self.r.zrevrange(index, 0, -1)]  # type: ignore[union-attr]
        if not self._sees_all():
            ids += [m for m in BUILTIN_MODEL_IDS if m not in ids]
        models, gone = [], []
        for model_id in ids:
            model = self.get(model_id)
            if model is not None:
                models.append(model)
            elif model_id not in BUILTIN_MODEL_IDS:
                gone.append(model_id)
        if gone:
            self.r.zrem(index, *gone)
        return models

    def put(self, model: ModelPublic, data: bytes, owner: str | None = None) -> bool:
        """Register ``model`` with its file bytes (kept if the same content is there) and make
        ``owner`` one of its owners under ``model.name``; True if something new was written
        (the content, or this owner's ownership). The file goes to the blob store first
        (BlobStoreUnavailable if that fails, and nothing is registered)."""
        current = self._meta(model.id)
        new_content = current is None or current.sha256 != model.sha256
        if new_content:
            self.blobs.put(model_file_name(model.id, model.sha256), data)
        now = time.time()
        pipe = self.r.pipeline()
        if new_content:
            pipe.delete(self.keys.model_data(model.id))  # an older deployment's copy
            pipe.hset(self.keys.model(model.id), "meta", model.model_dump_json())
            pipe.zadd(self.keys.models_index, {model.id: now})
        if owner is not None:
            pipe.hsetnx(self.keys.model_owners(model.id), owner, model.name)
            pipe.zadd(self.keys.owner_models(owner), {model.id: now}, nx=True)
        results = pipe.execute()
        if new_content and current is not None:  # replaced (the demo model, regenerated)
            self._forget(model_file_name(model.id, current.sha256))
        return new_content or (owner is not None and bool(results[-2]))

    def delete(self, model_id: str) -> bool:
        """Drop the viewer's ownership (an admin's or a worker's delete drops the model); the
        file and metadata go with the last owner. True if something was removed."""
        owners_key = self.keys.model_owners(model_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(owners_key)
                    owners = [o.decode() for o in pipe.hkeys(owners_key)]  # type: ignore[union-attr]
                    mine = self.viewer.name if self.viewer is not None else None
                    drop = owners if self._sees_all() else [o for o in owners if o == mine]
                    if not self._sees_all() and not drop:
                        pipe.unwatch()
                        return False
                    remaining = [o for o in owners if o not in drop]
                    meta = None if remaining else self._meta(model_id)
                    pipe.multi()
                    for owner in drop:
                        pipe.hdel(owners_key, owner)
                        pipe.zrem(self.keys.owner_models(owner), model_id)
                    if not remaining:
                        pipe.delete(self.keys.model(model_id), self.keys.model_data(model_id))
                        pipe.delete(owners_key)
                        pipe.zrem(self.keys.models_index, model_id)
                    results = pipe.execute()
                    if meta is not None:
                        self._forget(model_file_name(model_id, meta.sha256))
                    return any(bool(x) for x in results)
                except redis.WatchError:
                    continue

    def _forget(self, name: str) -> None:
        if self._blobs is None:
            return  # the sweeper deletes it
        try:
            self._blobs.delete([name])
        except BlobStoreError as exc:
            log.warning("could not delete blob %s now (%s); the sweep will", name, exc)

    def _meta(self, model_id: str) -> ModelPublic | None:
        raw = self.r.hget(self.keys.model(model_id), "meta")
        return ModelPublic.model_validate_json(raw) if raw else None  # type: ignore[arg-type]
