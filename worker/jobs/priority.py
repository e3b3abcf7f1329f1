"""A worker's CPU priority below the API's (``Settings.worker_nice``).

``os.nice`` alone is not enough on Linux with autogroup scheduling (``sched(7)``, on by default
in most distributions): the scheduler first shares the CPU fairly between *autogroups* (one per
session) and applies a process's niceness only against the other processes of its own session.
``proxpose serve`` starts the API, Redis and each worker in a session of its own, so a worker
at niceness 10 still took as much CPU as the API whenever both wanted it: measured with a burst
of submissions, the worker ran on both cores while the API waited for one. A worker that leads
its own session therefore also sets its autogroup's niceness (``/proc/self/autogroup``), which
touches only its own session. A worker started in a terminal shares the terminal's session and
leaves that session's autogroup alone: lowering it would lower the user's shell too.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

#: Where Linux exposes the calling process's autogroup and its niceness.
AUTOGROUP = Path("/proc/self/autogroup")


def lower_priority(nice: int, autogroup: Path = AUTOGROUP) -> int | None:
    """Add ``nice`` to this process's niceness (threads started later inherit it) and, when the
    process leads its own session, set its autogroup's niceness to ``nice`` as well.

    Returns the autogroup niceness set, or None when it was left alone (not a session leader,
    no autogroup support, or the kernel refused)."""
    if nice <= 0:
        return None
    os.nice(nice)
    if os.getsid(0) != os.getpid() or not autogroup.exists():
        return None
    try:
        autogroup.write_text(f"{nice}\n")
    except OSError as exc:  # a kernel without CONFIG_SCHED_AUTOGROUP, or a sandbox
        log.info("autogroup niceness not set (%s): only the process's own niceness applies", exc)
        return None
    return nice
