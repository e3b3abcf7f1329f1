"""Redis memory: what it uses, its limit, and the warning when it has none.

With the blobs in the blob store, a finished estimate costs Redis about 8 kB (its hash: the
request and the result JSON, compressed); README "Blob storage" has the measured figure.
Redis without ``maxmemory`` grows until the machine runs out, so the API and the workers warn
at start.
"""

from __future__ import annotations

import logging

import redis

log = logging.getLogger(__name__)


def redis_memory(r: redis.Redis) -> tuple[int, int]:
    """(used_memory, maxmemory) of Redis, bytes (maxmemory 0: no limit)."""
    info = r.info("memory")
    return int(info["used_memory"]), int(info.get("maxmemory", 0))  # type: ignore[index,union-attr]


def warn_if_unbounded(r: redis.Redis, who: str) -> bool:
    """Log a warning if Redis has no ``maxmemory``; True if it warned (False also when Redis
    cannot tell: the caller's first real command reports an outage)."""
    try:
        _used, limit = redis_memory(r)
    except (redis.RedisError, KeyError, ValueError):
        return False
    if limit:
        return False
    log.warning(
        "%s: Redis has no maxmemory set: it grows until the machine runs out of memory; set "
        "maxmemory (with maxmemory-policy noeviction, so that no job is evicted)",
        who,
    )
    return True
