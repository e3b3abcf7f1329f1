"""worker.jobs.priority on real processes: a session leader lowers its autogroup's niceness
with its own; a process in someone else's session (a terminal's) leaves the autogroup alone."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO

from worker.jobs.priority import AUTOGROUP, lower_priority

PROBE = (
    "import os; from worker.jobs.priority import AUTOGROUP, lower_priority; "
    "print(lower_priority(7)); print(os.getpriority(os.PRIO_PROCESS, 0)); "
    "print((AUTOGROUP.read_text().split() or ['root'])[-1])"
)


def probe(new_session: bool) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        start_new_session=new_session,
        check=True,
    )
    return out.stdout.split()


def autogroup_nice() -> str:
    """The calling process's autogroup niceness; "root" for the kernel's default autogroup (a
    process whose session never called setsid, as in a container started without one), for
    which Linux prints nothing."""
    return (AUTOGROUP.read_text().split() or ["root"])[-1]


needs_autogroup = pytest.mark.skipif(
    not AUTOGROUP.exists(), reason="no /proc/self/autogroup (not Linux with autogroup)"
)


@needs_autogroup
def test_a_session_leader_lowers_its_autogroup() -> None:
    base = os.getpriority(os.PRIO_PROCESS, 0)
    returned, nice, group = probe(new_session=True)
    assert returned == "7" and group == "7"
    assert int(nice) == min(19, base + 7)


@needs_autogroup
def test_a_process_in_another_session_leaves_the_autogroup_alone() -> None:
    before = autogroup_nice()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    returned, nice, group = probe(new_session=False)
    assert returned == "None" and group == before == autogroup_nice()
    assert int(nice) == min(19, base + 7)


def test_no_niceness_changes_nothing(tmp_path: Path) -> None:
    marker = tmp_path / "autogroup"
    marker.write_text("/autogroup-1 nice 0\n")
    before = os.getpriority(os.PRIO_PROCESS, 0)
    assert lower_priority(0, autogroup=marker) is None
    assert os.getpriority(os.PRIO_PROCESS, 0) == before
    assert marker.read_text() == "/autogroup-1 nice 0\n"
