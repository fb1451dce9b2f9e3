"""The processes of an experiment's run (`rr_actors_lab.experiments._procs`): waiting until
they are gone works whatever the numbers of their pidfds."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from collections.abc import Iterator

import pytest

from rr_actors_lab.experiments._procs import wait_gone

MANY = 1100
"""Descriptors opened first: past 1024, which `select.select` refuses (`ValueError:
filedescriptor out of range in select()`)."""


@pytest.fixture
def many_files() -> Iterator[None]:
    """This process holds `MANY` more open files (its soft limit raised if need be)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = len(os.listdir("/proc/self/fd")) + MANY + 64
    if hard != resource.RLIM_INFINITY and hard < want:
        pytest.skip(f"the hard limit of open files ({hard}) is below {want}")
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
    fds = [os.open(os.devnull, os.O_RDONLY) for _ in range(MANY)]
    try:
        yield
    finally:
        for fd in fds:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_wait_gone_waits_on_pidfds_numbered_past_1024(many_files: None) -> None:
    body = "import sys; sys.stdin.read()"  # (ends when its stdin closes: no timing)
    ending = subprocess.Popen([sys.executable, "-c", body], stdin=subprocess.PIPE)
    staying = subprocess.Popen([sys.executable, "-c", body], stdin=subprocess.PIPE)
    try:
        probe = os.open(os.devnull, os.O_RDONLY)
        os.close(probe)
        assert probe >= 1024  # (the lowest free number: the pidfds get higher ones)
        assert ending.stdin is not None
        ending.stdin.close()

        assert [] == wait_gone([ending.pid], 30.0)
        assert [staying.pid] == wait_gone([ending.pid, staying.pid], 0.2)  # (both polled)
    finally:
        for process in (ending, staying):
            process.kill()
            process.wait()
            if process.stdin is not None:
                process.stdin.close()
