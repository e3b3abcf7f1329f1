"""The worker's log filters during a Redis outage (worker/jobs/runner.py): RQ's "quitting"
traceback is dropped when Redis went away (the outage notice says it once), kept for anything
else. The outage itself runs on real processes in test_reliability_outage.py."""

from __future__ import annotations

import logging
import sys

import redis

from worker.jobs.runner import _OutageQuitFilter


def _record(exc: BaseException) -> logging.LogRecord:
    try:
        raise exc
    except BaseException:
        info = sys.exc_info()
    return logging.LogRecord(
        "rq.worker",
        logging.ERROR,
        __file__,
        1,
        "Worker %s: found an unhandled exception, quitting...",
        ("w1",),
        info,
    )


def test_rq_quitting_on_an_outage_is_dropped_other_errors_are_kept() -> None:
    quiet = _OutageQuitFilter()
    assert not quiet.filter(_record(redis.ConnectionError("Connection refused")))
    try:
        try:
            raise redis.TimeoutError("timed out")
        except redis.TimeoutError as cause:
            raise RuntimeError("RQ wrapped it") from cause
    except RuntimeError as wrapped:
        assert not quiet.filter(_record(wrapped))
    assert quiet.filter(_record(ValueError("a bug")))
    other = logging.LogRecord("rq.worker", logging.INFO, __file__, 1, "Job OK", (), None)
    assert quiet.filter(other)
