"""A program that forgets `stop()`, or raises before it, still ends, and ends cleanly.

Each test runs a real program in its own interpreter (`python -c`), with registrars in
threads or a supervisor with a manager process, and checks its exit code, how long it
took, and that a durable backup holds what was loaded: the registrars and supervisors it
left running were stopped when its main thread ended, their catalogs written.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

import rr_actors as rr
from tests.support.supervising import wait_gone

# The provider's backup is written on a clean stop only (`save_interval` is long and
# there is no `save_on_modify`). Its consumer is stopped after it (it was started
# before: newest first), so the provider's catalog still holds the consumer's id when
# it is written.
THREADS = textwrap.dedent(
    """
    import sys
    import rr_actors as rr

    backup, uid, ending = sys.argv[1:4]
    consumer = rr.ResourceRegistrar.start(f"consumer-{uid}")
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(f"provider-{uid}", backup_path=backup, save_interval=3600.0)
    )
    provider.register_server("res", load=lambda r: {"r": r}, unload=lambda r, s: None)
    print(consumer.call(f"provider-{uid}", "res", "camera").id, flush=True)
    if ending == "raises":
        raise RuntimeError("the program fails before it stops anything")
    """
)

# The manager process is the provider; the consumer in the program's own process is
# not the supervisor's, so stopping the supervisor (first) does not release its id.
SUPERVISED = textwrap.dedent(
    """
    import sys
    import rr_actors as rr

    backup, uid, ending = sys.argv[1:4]

    def setup(registrar):
        registrar.register_server("res", load=lambda r: {"r": r}, unload=lambda r, s: None)

    config = rr.RegistrarConfig(f"provider-{uid}", backup_path=backup, save_interval=3600.0)
    consumer = rr.ResourceRegistrar.start(f"consumer-{uid}")
    sup = rr.Supervisor(
        [rr.ManagerSpec(config.name, setup, isolation="process", config=config)]
    ).start()
    query = consumer.call(config.name, "res", "camera")
    print(query.id, sup.child(config.name).pid, flush=True)
    if ending == "raises":
        raise RuntimeError("the program fails before it stops anything")
    """
)

BOUND = 20.0
"""Seconds such a program may take, start to end (it takes about one)."""


def run_program(source: str, backup: Path, uid: str, ending: str) -> tuple[int, float, str, str]:
    """Run `source` with its arguments; its exit code, duration, stdout and stderr."""
    started = time.monotonic()
    try:
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", source, str(backup), uid, ending],
            capture_output=True,
            text=True,
            timeout=2 * BOUND,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"},
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"the program did not end within {2 * BOUND:g} s: {exc.stderr!r}")
    return done.returncode, time.monotonic() - started, done.stdout, done.stderr


def held_ids(backup: Path, name: str) -> list[str]:
    """The consumer ids that the backup of registrar `name` holds at its server `res`."""
    config = rr.RegistrarConfig(name, backup_path=backup)
    registrar = rr.ResourceRegistrar.start(
        config, setup=lambda r: r.register_server("res", load=lambda q: q, unload=lambda q, s: None)
    )
    try:
        return [query.id for query in registrar.server_queries("res")]
    finally:
        registrar.stop()


@pytest.mark.parametrize(("ending", "code"), [("raises", 1), ("returns", 0)])
def test_a_program_that_leaves_registrars_running_ends_and_writes_their_backups(
    tmp_path: Path, ending: str, code: int
) -> None:
    uid = uuid.uuid4().hex[:8]
    backup = tmp_path / "provider.db"

    returncode, took, out, err = run_program(THREADS, backup, uid, ending)

    assert (code, True) == (returncode, took < BOUND), err
    assert "Exception ignored" not in err
    assert [out.split()[0]] == held_ids(backup, f"provider-{uid}")


@pytest.mark.parametrize(("ending", "code"), [("raises", 1), ("returns", 0)])
def test_a_program_that_leaves_a_supervisor_running_ends_and_stops_its_managers(
    tmp_path: Path, ending: str, code: int
) -> None:
    uid = uuid.uuid4().hex[:8]
    backup = tmp_path / "provider.db"

    returncode, took, out, err = run_program(SUPERVISED, backup, uid, ending)

    query_id, pid = out.split()
    assert (code, True) == (returncode, took < BOUND), err
    assert "Exception ignored" not in err
    assert [] == wait_gone([int(pid)])
    assert [query_id] == held_ids(backup, f"provider-{uid}")
