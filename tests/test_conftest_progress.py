"""The suite's own reporting: with `-q` and xdist workers, a failure is named as it
happens (`tests/conftest.py`'s `pytest_runtest_logreport`; issue 44 item 8).

`-q` shows only `F` on the progress line, and pytest names the failures once the last
worker has ended: on the suite's three workers, minutes later. The test runs a small
suite of two files on two workers with this conftest: one test fails at once, the other
waits (bounded) until the failure's name has been read from the run's output.

And the order files go out in: the slowest first (`FIRST`), as conftest lists them.
"""

from __future__ import annotations

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
