"""The child's side of a manager process (`rr_actors._process.child`): its name in `ps`.

The kernel's 15-byte name of a manager process is the manager's name, not a prefix:
`ps -o comm` and `top` show that name; with a prefix of 11 bytes every manager read
`rr-actors: <first 4 characters>`. The long title `rr-actors: <name>` is the command
line's, where `setproctitle` is installed.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors.testing import start_forkserver
from tests.support.supervising import linux_trick, process


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


def comm_after_set_title(name: str, *, fake_setproctitle: bool) -> tuple[str, str]:
    """`/proc/self/comm` of a fresh interpreter after `set_title(name)`, and the title set."""
    if fake_setproctitle:
        prelude = (
            "import sys, types; titles = []\n"
            "m = types.ModuleType('setproctitle'); m.setproctitle = titles.append\n"
            "sys.modules['setproctitle'] = m\n"
        )
    else:
        prelude = "import sys; titles = []; sys.modules['setproctitle'] = None\n"
    script = (
        prelude + "from rr_actors._process.child import set_title\n"
        f"set_title({name!r})\n"
        "print(open('/proc/self/comm', encoding='utf-8').read().strip())\n"
        "print(titles)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    comm, titles = result.stdout.splitlines()
    return comm, titles


@linux_trick
@pytest.mark.parametrize("fake_setproctitle", [False, True])
def test_a_long_manager_name_keeps_its_first_15_bytes_as_the_process_name(
    fake_setproctitle: bool,
) -> None:
    comm, _ = comm_after_set_title("navigation-manager-2", fake_setproctitle=fake_setproctitle)

    assert "navigation-mana" == comm


@linux_trick
def test_with_setproctitle_the_command_line_keeps_the_long_title() -> None:
    comm, titles = comm_after_set_title("erm", fake_setproctitle=True)

    assert ("erm", "['rr-actors: erm']") == (comm, titles)


@linux_trick
def test_a_name_is_never_cut_inside_a_character() -> None:
    comm, _ = comm_after_set_title("é" * 10, fake_setproctitle=False)  # 2 bytes each

    assert "é" * 7 == comm


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
