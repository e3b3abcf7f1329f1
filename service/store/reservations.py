"""A new job's place: the Lua script that claims a submission's idempotency key and reserves
the job's place among its owner's active jobs in one round trip, and what it refuses with."""

from __future__ import annotations

import json

#: With an idempotency key (KEYS[3]), first claim it (ARGV[3] for ARGV[4] s): a key claimed
#: already returns {-2, the earlier claim} and reserves nothing. Then reserve a place among the
#: owner's active jobs (KEYS[1]) for job ARGV[1] unless ARGV[2] > 0 of them are active already
#: ({-1}, the key staying claimed until the caller releases it); else {the job's sequence number
#: (INCR of KEYS[2])}. One round trip where a claim and a reservation took two.
RESERVE_SCRIPT = """
if KEYS[3] and not redis.call('SET', KEYS[3], ARGV[3], 'NX', 'EX', ARGV[4]) then
  return {-2, redis.call('GET', KEYS[3])}
end
local limit = tonumber(ARGV[2])
if limit > 0 and redis.call('SCARD', KEYS[1]) >= limit then return {-1} end
redis.call('SADD', KEYS[1], ARGV[1])
return {redis.call('INCR', KEYS[2])}
"""


class ActiveJobsLimitError(Exception):
    """The owner already has ``limit`` queued or running jobs."""

    def __init__(self, limit: int) -> None:
        super().__init__(f"{limit} estimates of this API key are queued or running")
        self.limit = limit


class IdempotencyKeyTaken(Exception):
    """A create's idempotency key was claimed by an earlier request: ``claim`` is that
    request's {"job_id", "fingerprint"}. Nothing was created or reserved."""

    def __init__(self, claim: dict[str, str]) -> None:
        super().__init__(f"idempotency key taken by job {claim.get('job_id')}")
        self.claim = claim


def claim_value(job_id: str, fingerprint: str) -> str:
    """What an idempotency key holds: the job it was first used for, and that request's
    fingerprint."""
    return json.dumps({"job_id": job_id, "fingerprint": fingerprint})
