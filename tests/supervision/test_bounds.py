"""A tree too big for its machine (`rr_actors._supervision.bounds`): `Supervisor.start`
names the bound it ran into in one line (issue 69, "No ceiling")."""

from __future__ import annotations

import errno
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from rr_actors._supervision.bounds import bound_reached

PROGRAM = textwrap.dedent(
    """
    import resource, sys
    import rr_actors as rr

    def setup(registrar):
        registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    if __name__ == "__main__":
        hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
        resource.setrlimit(resource.RLIMIT_NOFILE, (int(sys.argv[2]), hard))
        specs = [rr.ManagerSpec(f"m{i}", setup, isolation="process") for i in range(30)]
        sup = rr.Supervisor(specs, state_dir=sys.argv[1])
        try:
            sup.start()
        except rr.SupervisorGaveUpError as exc:
            print(f"{type(exc).__name__}: {exc}", flush=True)
        else:
            print("started", flush=True)
            sup.stop()
    """
)
"""A program whose tree of 30 process managers needs more open files than it may have."""


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_NOFILE as Linux counts it")
@pytest.mark.timeout(180)
def test_a_tree_that_needs_more_open_files_than_its_process_may_have_fails_naming_rlimit_nofile(
    tmp_path: Path,
) -> None:
    done = subprocess.run(
        [sys.executable, "-c", PROGRAM, str(tmp_path), "48"],
        capture_output=True,
        text=True,
        timeout=150,
        check=False,
    )

    said = done.stdout.strip().splitlines()
    assert 1 == len(said), done.stdout + done.stderr
    assert said[0].startswith("SupervisorGaveUpError: "), said
    assert "RLIMIT_NOFILE 48" in said[0], said
    assert "can't start new thread" not in said[0]


@pytest.mark.parametrize(
    ("error", "named"),
    [
        (OSError(errno.EMFILE, "Too many open files"), "RLIMIT_NOFILE"),
        (OSError(errno.EAGAIN, "Resource temporarily unavailable"), "kernel.pid_max"),
        (RuntimeError("can't start new thread"), "RLIMIT_NPROC"),
        (
            RuntimeError("manager 'm1' failed to start:\nRuntimeError: can't start new thread"),
            "kernel.threads-max",
        ),
        (MemoryError(), "memory"),
    ],
)
def test_the_bound_an_error_ran_into_is_named_with_how_to_look_at_it(
    error: BaseException, named: str
) -> None:
    found = bound_reached(error)

    assert found is not None
    assert named in found


def test_an_error_raised_from_one_at_a_bound_names_that_bound() -> None:
    outer = RuntimeError("manager 'm7' could not start")
    outer.__cause__ = OSError(errno.EMFILE, "Too many open files")

    found = bound_reached(outer)

    assert found is not None
    assert "RLIMIT_NOFILE" in found
