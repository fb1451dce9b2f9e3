"""Two demos in one `--out` folder: the second refuses at once, the first is untouched."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rr_actors.mission.run import lock_out


def demo_process(out: Path) -> subprocess.Popen[str]:
    """`rr-actors demo --fast --out OUT` as a separate program, its output in pipes."""
    return subprocess.Popen(
        [sys.executable, "-m", "rr_actors", "demo", "--fast", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.timeout(120)
def test_a_second_demo_in_the_same_folder_refuses_and_the_first_completes(
    tmp_path: Path,
) -> None:
    out = tmp_path / "demo"
    first = demo_process(out)
    try:
        assert first.stdout is not None
        # Its first line of story comes after it took the lock and emptied state/ and bus/.
        assert "starting the managers" in first.stdout.readline()

        second = subprocess.run(
            [sys.executable, "-m", "rr_actors", "demo", "--fast", "--out", str(out)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        rest, errors = first.communicate(timeout=90)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait(10)

    assert (2, "") == (second.returncode, second.stdout)
    assert (
        f"rr-actors demo: {str(out)!r} is in use by another demo (pid {first.pid}); wait for "
        "it to end, or give this one another folder with --out\n"
    ) == second.stderr
    assert (0, "") == (first.returncode, errors), rest
    assert "leaked processes: 0; catalog entries left: 0" in rest


def test_the_lock_is_free_again_after_a_mission(tmp_path: Path) -> None:
    with lock_out(tmp_path):
        pass

    with lock_out(tmp_path):  # would raise if the first were still held
        pass
