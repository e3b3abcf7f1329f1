"""Job statistics kept in Redis, so that the API's /metrics covers every worker's jobs.

Workers count finished jobs by kind and status, failures by code, and durations in fixed
histogram buckets (cumulative, as Prometheus exposes them) in one hash; the API reads it back.
Field names: ``jobs|<kind>|<status>``, ``failures|<kind>|<code>``, ``duration_bucket|<kind>|<le>``,
``duration_sum|<kind>``, ``duration_count|<kind>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import redis

from service.store.keys import Keys

#: Upper bounds of the job duration histogram buckets, s (+Inf is implied).
DURATION_BUCKETS_S = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0)


def _text(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else value


def _le(bound: float) -> str:
    return "+Inf" if bound == float("inf") else repr(bound)


@dataclass
class StatsSnapshot:
    """Everything the hash holds, parsed."""

    jobs: dict[tuple[str, str], int] = field(default_factory=dict)  # (kind, status) → count
    failures: dict[tuple[str, str], int] = field(default_factory=dict)  # (kind, code) → count
    buckets: dict[str, list[tuple[str, int]]] = field(default_factory=dict)  # kind → [(le, n)]
    duration_sum_s: dict[str, float] = field(default_factory=dict)
    duration_count: dict[str, int] = field(default_factory=dict)


class JobStats:
    """Counters of finished jobs in one Redis hash."""

    def __init__(self, r: redis.Redis, keys: Keys) -> None:
        self.r = r
        self.key = keys.stats

    def record(self, kind: str, status: str, duration_s: float, code: str | None = None) -> None:
        """Count one finished job of ``kind`` ('estimate', 'render')."""
        pipe = self.r.pipeline()
        pipe.hincrby(self.key, f"jobs|{kind}|{status}", 1)
        if code is not None:
            pipe.hincrby(self.key, f"failures|{kind}|{code}", 1)
        for bound in (*DURATION_BUCKETS_S, float("inf")):
            if duration_s <= bound:
                pipe.hincrby(self.key, f"duration_bucket|{kind}|{_le(bound)}", 1)
        pipe.hincrbyfloat(self.key, f"duration_sum|{kind}", duration_s)
        pipe.hincrby(self.key, f"duration_count|{kind}", 1)
        pipe.execute()

    def count(self, kind: str, status: str, code: str | None = None) -> None:
        """Count one finished job whose duration is unknown (ended by a reaper)."""
        pipe = self.r.pipeline()
        pipe.hincrby(self.key, f"jobs|{kind}|{status}", 1)
        if code is not None:
            pipe.hincrby(self.key, f"failures|{kind}|{code}", 1)
        pipe.execute()

    def snapshot(self) -> StatsSnapshot:
        snap = StatsSnapshot()
        raw = self.r.hgetall(self.key)
        for k, v in raw.items():  # type: ignore[union-attr]
            name, *labels = _text(k).split("|")
            value = _text(v)
            if name == "jobs":
                snap.jobs[(labels[0], labels[1])] = int(value)
            elif name == "failures":
                snap.failures[(labels[0], labels[1])] = int(value)
            elif name == "duration_bucket":
                snap.buckets.setdefault(labels[0], []).append((labels[1], int(value)))
            elif name == "duration_sum":
                snap.duration_sum_s[labels[0]] = float(value)
            elif name == "duration_count":
                snap.duration_count[labels[0]] = int(value)
        for kind, found in snap.buckets.items():
            counts = dict(found)
            snap.buckets[kind] = [
                (_le(b), counts.get(_le(b), 0)) for b in (*DURATION_BUCKETS_S, float("inf"))
            ]
        return snap
