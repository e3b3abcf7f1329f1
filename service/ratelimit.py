"""Per-key rate limit of submissions, answered 429 with Retry-After before the body is read.

Submissions (POST of estimates, tracks, renders and models) are metered per API key by the
generic cell rate algorithm (GCRA): a key may send ``submission_burst`` at once, then one
every ``60 / submissions_per_minute`` seconds. The state is one Redis key per API key holding the
theoretical arrival time, updated by a Lua script on Redis' clock, so every API process shares
the limit. (The cap on queued jobs per key is checked when a job is created, see JobStore.)
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable

import redis
import redis.asyncio
from starlette.types import ASGIApp, Receive, Scope, Send

from schemas.settings import Settings
from service.inline import InlineSubmissions
from service.problems import send_problem
from service.store import Keys, Principal

log = logging.getLogger(__name__)

#: The longest a submission waits for the rate limit's answer from Redis, s (then 503).
ADMIT_TIMEOUT_S = 2.0

#: Routes that count as submissions.
SUBMISSIONS = frozenset(
    {
        ("POST", "/v1/estimates"),
        ("POST", "/v1/tracks"),
        ("POST", "/v1/renders"),
        ("POST", "/v1/models"),
    }
)

# KEYS: the key's state. ARGV: emission interval (ms), burst tolerance (ms).
# Returns {allowed (0/1), ms to wait}.
_GCRA = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
local interval = tonumber(ARGV[1])
local tolerance = tonumber(ARGV[2])
local tat = tonumber(redis.call('GET', KEYS[1]) or now)
if tat < now then tat = now end
if tat - tolerance > now then
  return {0, tat - tolerance - now}
end
local new = tat + interval
redis.call('SET', KEYS[1], new, 'PX', new - now + 1000)
return {1, 0}
"""


def _gcra_args(keys: Keys, settings: Settings, principal: Principal) -> list[str | int] | None:
    """The GCRA script's key and arguments for ``principal``; None when there is no limit."""
    if settings.submissions_per_minute <= 0:
        return None
    interval_ms = 60_000.0 / settings.submissions_per_minute
    tolerance_ms = interval_ms * (settings.submission_burst - 1)
    return [keys.rate(principal.name), int(interval_ms), int(tolerance_ms)]


def _wait_s(reply: list[int]) -> float | None:
    allowed, wait_ms = reply
    return None if allowed else max(0.001, int(wait_ms) / 1000.0)


async def admit(
    r: redis.asyncio.Redis, keys: Keys, settings: Settings, principal: Principal
) -> float | None:
    """None if ``principal`` may submit now (and count it), else the seconds to wait."""
    args = _gcra_args(keys, settings, principal)
    if args is None:
        return None
    return _wait_s(await r.eval(_GCRA, 1, *args))  # type: ignore[misc]


def admit_now(r: redis.Redis, keys: Keys, settings: Settings, principal: Principal) -> float | None:
    """:func:`admit` through a sync client (the inline one, on the event loop)."""
    args = _gcra_args(keys, settings, principal)
    if args is None:
        return None
    return _wait_s(r.eval(_GCRA, 1, *args))  # type: ignore[arg-type]


async def admit_in_time(
    scope: Scope, keys: Keys, settings: Settings, principal: Principal
) -> float | None:
    """:func:`admit` through the inline client while that is usable (service/inline.py: a
    few tens of µs on the loop, where the async client costs more), else through the async
    client within ADMIT_TIMEOUT_S (TimeoutError after it: a hung Redis is not waited on)."""
    state = scope["app"].state
    inline: InlineSubmissions | None = getattr(state, "inline", None)
    if inline is not None and inline.ready():
        return inline.guard(lambda r: admit_now(r, keys, settings, principal))
    return await asyncio.wait_for(admit(state.aredis, keys, settings, principal), ADMIT_TIMEOUT_S)


class SubmissionRateLimitMiddleware:
    """429 + Retry-After for a key that submits faster than its rate (after AuthMiddleware)."""

    def __init__(self, app: ASGIApp, settings: Callable[[], Settings]) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        principal = scope.get("state", {}).get("principal")
        if (
            scope["type"] != "http"
            or (scope["method"], scope["path"]) not in SUBMISSIONS
            or not isinstance(principal, Principal)
        ):
            await self.app(scope, receive, send)
            return
        settings = self.settings()
        try:
            wait_s = await admit_in_time(scope, Keys(settings.redis_prefix), settings, principal)
        except (redis.RedisError, TimeoutError) as exc:
            log.error("rate limiter: Redis error: %s", exc or type(exc).__name__)
            detail = "the job store (Redis) is unreachable; try again shortly"
            await send_problem(
                send,
                503,
                detail,
                code="unavailable",
                instance=scope["path"],
                headers=[(b"retry-after", b"5")],
            )
            return
        if wait_s is None:
            await self.app(scope, receive, send)
            return
        retry_s = max(1, math.ceil(wait_s))
        detail = (
            f"too many submissions from API key '{principal.name}': the limit is "
            f"{settings.submissions_per_minute:g} per minute (bursts of "
            f"{settings.submission_burst}); retry after {retry_s} s"
        )
        await send_problem(
            send,
            429,
            detail,
            code="rate_limited",
            instance=scope["path"],
            headers=[(b"retry-after", str(retry_s).encode())],
        )
