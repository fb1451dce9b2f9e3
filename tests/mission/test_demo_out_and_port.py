"""`rr-actors demo --port` and `--out`: refused before anything starts or is removed.

`--port` without `--observe` used to be ignored silently (the mission ran, no page), and
a port out of range was refused only after the managers had started. `--out` a folder
whose `state/`, `bus/` (or `certs/`, on two hosts) a demo never wrote (`--out ~`) used
to have them emptied.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest


def demo(*argv: str) -> subprocess.CompletedProcess[str]:
    """`rr-actors demo ARGV` as a separate program (60 s at most)."""
    return subprocess.run(
        [sys.executable, "-m", "rr_actors", "demo", *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--port", "8080"], "--port needs --observe (it is the observer's port)"),
        (["--observe", "--port", "-5"], "--port must be from 0 to 65535, got -5"),
        (["--observe", "--port", "70000"], "--port must be from 0 to 65535, got 70000"),
    ],
    ids=["without-observe", "negative", "too-big"],
)
def test_a_port_the_demo_cannot_use_is_a_usage_error_before_anything_starts(
    tmp_path: Path, argv: list[str], says: str
) -> None:
    out = tmp_path / "out"

    result = demo("--fast", "--out", str(out), *argv)

    assert (2, "", f"rr-actors demo: {says}\n") == (
        result.returncode,
        result.stdout,
        result.stderr,
    )
    assert not out.exists()  # nothing started, nothing written


@pytest.mark.parametrize("sub", ["state", "bus", "certs"])
def test_a_folder_whose_state_bus_or_certs_no_demo_wrote_is_refused_and_kept(
    tmp_path: Path, sub: str
) -> None:
    mine = tmp_path / sub / "notes.txt"  # `--out ~` with the user's own ~/state
    mine.parent.mkdir()
    mine.write_text("mine\n")

    result = demo("--fast", "--out", str(tmp_path))

    assert (2, "") == (result.returncode, result.stdout)
    assert f"holds a {sub}/ that no mission wrote" in result.stderr
    assert ("mine\n", [sub]) == (mine.read_text(), sorted(p.name for p in tmp_path.iterdir()))
