"""A training worker's lower CPU priority holds against the services whichever session it runs in."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT

PROBE = """
import os
from tests.services.trainer.test_priority import autogroup_nice
from services.trainer.worker import lower_priority
print(lower_priority(7, idle=True), autogroup_nice(), os.getsid(0) == os.getpid(),
      os.sched_getscheduler(0) == os.SCHED_IDLE)
"""


def autogroup_nice() -> str:
    """The niceness of this process's scheduler autogroup ("none" where the kernel shows none: some
    containers expose an empty /proc/self/autogroup)."""
    try:
        found = re.search(r"nice\s+(-?\d+)", Path("/proc/self/autogroup").read_text())
    except OSError:
        return "none"
    return found.group(1) if found else "none"


needs_autogroups = pytest.mark.skipif(
    autogroup_nice() == "none", reason="no readable scheduler autogroup here"
)


def _probe(new_session: bool) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        start_new_session=new_session,
        timeout=60,
    ).stdout
    return out.split()


@needs_autogroups
def test_a_worker_leading_its_own_session_lowers_its_autogroup() -> None:
    niceness, group_nice, leader, idle = _probe(new_session=True)
    assert leader == "True" and int(niceness) >= 7 and idle == "True"
    if group_nice == "none":  # a new session's autogroup may be hidden where the parent's is not
        pytest.skip("the new session's autogroup is not readable here")
    assert group_nice == niceness


@needs_autogroups
def test_a_worker_inside_the_stacks_session_leaves_the_shared_autogroup_alone() -> None:
    before = autogroup_nice()
    niceness, group_nice, leader, idle = _probe(new_session=False)
    assert leader == "False" and int(niceness) >= 7 and group_nice == before and idle == "True"
