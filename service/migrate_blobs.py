"""``proxpose migrate-blobs``: move the bytes an older deployment kept in Redis (reference
images, artifacts, model files) to the blob store, then sweep the store.

Safe while the API and the workers run, and to run again (it resumes); see
``service.store.blobs.migrate``. Imports are inside ``run``, so the CLI's parser stays light.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--redis-url", help="Redis (default: $PROXPOSE_REDIS_URL)")
    parser.add_argument("--no-sweep", action="store_true", help="only move, do not sweep")


def run(args: argparse.Namespace) -> int:
    import redis

    from schemas.settings import get_settings
    from service.store import Keys
    from service.store.blobs import BlobStoreUnavailable, open_blob_store
    from service.store.blobs.migrate import BlobMigration
    from service.store.blobs.sweeper import BlobSweeper

    settings = get_settings()
    r = redis.Redis.from_url(args.redis_url or settings.effective_redis_url())
    keys = Keys(settings.redis_prefix)
    blobs = open_blob_store(settings)
    try:
        blobs.ping()
        report = BlobMigration(r, keys, blobs).run()
        print(
            f"moved to {blobs.url}: {report.images} images, {report.artifacts} artifacts, "
            f"{report.models} model files ({report.bytes} bytes); {report.dropped} Redis "
            f"copies of ended or deleted records dropped; {report.results} results compressed"
        )
        if not args.no_sweep:
            swept = BlobSweeper(r, keys, blobs).sweep()
            print(
                f"swept: {swept.deleted} blobs deleted ({swept.deleted_bytes} bytes); "
                f"{swept.objects} blobs ({swept.bytes} bytes) kept"
            )
    except BlobStoreUnavailable as exc:
        print(f"error: {exc}")
        return 1
    except redis.RedisError as exc:
        print(f"error: Redis: {exc}")
        return 1
    return 0
