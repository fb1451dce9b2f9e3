"""The platform tricks and their plain fallback (`rr_actors._platform`).

`PLATFORM` is `linux` on Linux and `portable` elsewhere or with
`RR_ACTORS_PLATFORM=portable`. Every test that uses manager processes must pass on both:
`tests/core/test_portable_platform.py` runs those modules (this one too) again, in a
subprocess on the portable platform, as part of the normal run. Tests of what only a
trick does are marked `linux_trick` (see `supervising.py`) and skipped there.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._platform import PLATFORM
from rr_actors.testing import start_forkserver
from tests.support.supervising import linux_trick, process

_FORCED = os.environ.get("RR_ACTORS_PLATFORM") == "portable"


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


def test_the_platform_is_the_one_the_environment_asks_for() -> None:
    expected = "portable" if _FORCED or not sys.platform.startswith("linux") else "linux"

    assert expected == PLATFORM.name


# -- process titles -------------------------------------------------------------------------


def _cmdline(pid: int) -> str:
    return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()


@pytest.mark.skipif(not Path("/proc").exists(), reason="reads /proc")
def test_a_manager_process_is_named_after_its_manager_in_ps(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    pytest.importorskip("setproctitle", reason="the whole command line needs setproctitle")
    name = f"erm-{uid}"
    sup = supervisors([process(name)]).start()
    pid = sup.child(name).pid
    assert pid is not None

    assert f"rr-actors: {name}" == _cmdline(pid)


@linux_trick
def test_without_setproctitle_the_kernel_name_of_a_manager_process_is_set() -> None:
    script = (
        "import sys; sys.modules['setproctitle'] = None\n"  # as if it were not installed
        "from rr_actors._process.child import set_title\n"
        "set_title('erm')\n"
        "print(open('/proc/self/comm').read().strip())\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )

    assert "erm" == result.stdout.strip()
