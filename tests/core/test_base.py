"""The process tests again, on the portable platform (`rr_actors._platform.base`'s
`PortablePlatform`).

The tests of each place a Linux trick is used (`rr_actors._platform`'s `PLATFORM`: the
manager's context and forkserver, its exit and CPU watches, a child's death with its
parent and its name, the runtime folder, the end of the main thread) run again in a
subprocess with `RR_ACTORS_PLATFORM=portable`, as part of the normal run, so the
fallback of each trick cannot rot. Modules that only use manager processes, through
those places, are not run twice: `tests/transport/test_transport.py` and
`tests/transport/unix/test_link.py` (a third of this run's time) call no `PLATFORM`
method of their own.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rr_actors._platform import PLATFORM

ROOT = Path(__file__).resolve().parents[2]

PORTABLE_MODULES = (
    "tests/core/test_platform.py",
    "tests/process/test_child.py",  # (the tests of the kernel's name are Linux tricks only)
    "tests/process/test_manager.py",
    "tests/supervision/test_policy.py",  # (but PORTABLE_LEFT_OUT)
    "tests/supervision/test_tree.py::TestStateDir",
    "tests/supervision/test_supervisor.py",
    "tests/registrar/test_consumer.py::TestDurableConsumerKilled",
    "tests/registrar/test_life.py::TestCrash",
    "tests/transport/test_codec.py",
    "tests/transport/unix/test_system.py",
    "tests/transport/test_messenger.py::TestStoppingAListener",
    "tests/registrar/test_consumer.py::TestReconcileEdges",
    "tests/process/test_spare.py::TestWarmUp",
    "tests/process/test_heartbeat.py",
)
"""The tests of the places a Linux trick is used, run again on the portable platform."""

POLICY = "tests/supervision/test_policy.py"
PORTABLE_LEFT_OUT = (
    f"{POLICY}::test_a_host_that_stops_its_tree_for_good_is_no_loss_at_its_consumer_on_another_host",
    f"{POLICY}::test_a_host_killed_with_its_supervisor_is_a_loss_fatal_at_its_consumer_on_another_host",
    f"{POLICY}::TestStoppedForGood",
    f"{POLICY}::test_a_childs_exit_carries_its_supervisors_strategy_and_children_in_start_order",
    f"{POLICY}::test_a_tree_that_needs_more_open_files_than_its_process_may_have_fails_naming_rlimit_nofile",
)
"""Tests of those modules that use no Linux trick of their own (a stopped tree's ends), not
run twice; and one the portable platform does not pass: a manager spawned there that runs out
of open files dies before it can say why, and its bound is named only from its error."""


@pytest.mark.skipif(PLATFORM.name != "linux", reason="this run is on the portable platform")
@pytest.mark.timeout(1500)
def test_the_process_tests_pass_on_the_portable_platform() -> None:
    # (its run takes about 530 s alone; beside a whole suite and other runs, over 850 s)
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            *PORTABLE_MODULES,
            *(f"--deselect={test}" for test in PORTABLE_LEFT_OUT),
        ],
        cwd=ROOT,
        env={  # (not a pytest-xdist worker's: this run is a session of its own)
            **{k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")},
            "RR_ACTORS_PLATFORM": "portable",
        },
        capture_output=True,
        text=True,
        timeout=1400,
        check=False,
    )

    assert 0 == result.returncode, result.stdout[-6000:] + result.stderr[-2000:]
