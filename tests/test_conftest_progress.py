"""The suite's own reporting: with `-q` and xdist workers, a failure is named as it
happens (`tests/conftest.py`'s `pytest_runtest_logreport`; issue 44 item 8).

`-q` shows only `F` on the progress line, and pytest names the failures once the last
worker has ended: on the suite's three workers, minutes later. The test runs a small
suite of two files on two workers with this conftest: one test fails at once, the other
waits (bounded) until the failure's name has been read from the run's output.

And the order files go out in: the slowest first (`FIRST`), as conftest lists them.
"""

from __future__ import annotations

import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

from tests import conftest

ROOT = Path(__file__).resolve().parent.parent

FAILS = "def test_fails_at_once():\n    assert 1 == 2\n"
WAITS = """
import pathlib, threading

def test_waits_for_the_failure_to_be_named():
    gate = pathlib.Path({gate!r})
    pause = threading.Event()
    for _ in range(300):  # 30 s at most: then it ends, and the failure is named late
        if gate.exists():
            return
        pause.wait(0.1)
"""


@pytest.mark.timeout(180)  # (two workers to start, then at most 30 s of waiting)
def test_with_q_and_workers_a_failure_is_named_while_other_tests_still_run(
    tmp_path: Path,
) -> None:
    gate = tmp_path / "named"
    (tmp_path / "test_a.py").write_text(FAILS)
    (tmp_path / "test_b.py").write_text(WAITS.format(gate=str(gate)))
    lines: list[str] = []
    with subprocess.Popen(
        [
            *(sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider"),
            *("-p", "tests.conftest", "--rootdir", str(tmp_path), "-c", "/dev/null"),
            *(str(tmp_path / "test_a.py"), str(tmp_path / "test_b.py")),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    ) as run:
        assert run.stdout is not None
        try:
            for line in run.stdout:
                lines.append(line)
                if line.startswith("FAILED ") and "test_a.py::test_fails_at_once (call)" in line:
                    gate.touch()  # named while test_b still waits: it may end now
            code = run.wait(120)
        finally:
            if run.poll() is None:
                run.kill()

    assert 1 == code, "".join(lines)
    assert gate.exists(), "".join(lines)  # named before test_b ended (it waits for this)
    assert "1 failed, 1 passed" in lines[-1], "".join(lines)


def test_the_slowest_files_go_out_first_in_conftests_order_not_re_sorted_by_xdist() -> None:
    # pytest-xdist re-sorts files by their count of tests unless told not to: the one test
    # of `core/test_base.py` (minutes) then ran last, and the suite waited for it alone.
    options = types.SimpleNamespace(loadscopereorder=True)
    conftest.pytest_configure(
        types.SimpleNamespace(option=options, addinivalue_line=lambda *_: None)
    )

    assert options.loadscopereorder is False
    assert [] == [name for name in conftest.FIRST if not (ROOT / "tests" / name).is_file()]


LEAVES_A_RUN = """
import threading

import pytest

from rr_actors import simulation
from tests import conftest

conftest.SIMULATION_GRACE = 1.0  # (the suite's is minutes)


def test_leaves_a_simulation_going():
    real = threading.Event()  # (never set: the run's thread blocks for real, for ever)
    with pytest.raises(simulation.SimulationError, match="did not end"):
        simulation.run(real.wait, seed=1, timeout=0.5)


def test_runs_a_simulation_after_it():
    assert 7 == simulation.run(lambda: 7, seed=1).value
"""


@pytest.mark.timeout(180)  # (two workers to start, then seconds)
def test_a_simulation_that_outlives_its_test_fails_it_and_the_next_test_gets_a_fresh_worker(
    tmp_path: Path,
) -> None:
    """Stop 74: a simulation run cancelled by its test's timeout did not end, its process
    stayed simulated, and the 85 tests its worker ran next failed ("a simulation already
    runs", a manager process that did not start). The test that left it fails; the worker
    ends after it, and the next test runs on a fresh one."""
    (tmp_path / "test_left.py").write_text(LEAVES_A_RUN)
    done = subprocess.run(
        [
            *(sys.executable, "-m", "pytest", "-q", "-n", "1", "-p", "no:cacheprovider"),
            *("-p", "tests.conftest", "--rootdir", str(tmp_path), "-c", "/dev/null"),
            str(tmp_path / "test_left.py"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=150,
        check=False,
    )
    out = done.stdout + done.stderr

    # (xdist runs the crashed test again on the fresh worker: it passes there too)
    assert re.search(r"\b1 failed, 2 passed, 1 error\b", out), out
    assert "did not end within 1 s of its test's end" in out, out
    assert "a simulation already runs" not in out, out
