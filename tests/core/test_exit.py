"""A program that forgets `stop()`, or raises before it, still ends, and ends cleanly.

Each test runs a real program in its own interpreter (`python -c`), with registrars in
threads or a supervisor with a manager (a process or a thread), and checks its exit
code, how long it took, and what its provider saw: the registrars and supervisors it
left running were stopped when its main thread ended, a consumer before the provider it
holds an id at (which unloaded it, with no WARNING), their catalogs written.
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

# The consumer was started first, so it comes after the provider in the exit's order
# (newest first); it holds an id there, so it is stopped first all the same: it releases
# the id (the provider's `unload` runs, appending to the file `marker`) before the
# provider stops and writes its backup (`save_interval` is long, no `save_on_modify`).
THREADS = textwrap.dedent(
    """
    import sys
    import rr_actors as rr

    backup, uid, ending, marker, isolation = sys.argv[1:6]

    def unload(request, response):
        with open(marker, "a") as file:
            file.write(request + "\\n")

    consumer = rr.ResourceRegistrar.start(f"consumer-{uid}")
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(f"provider-{uid}", backup_path=backup, save_interval=3600.0)
    )
    provider.register_server("res", load=lambda r: {"r": r}, unload=unload)
    print(consumer.call(f"provider-{uid}", "res", "camera").id, flush=True)
    if ending == "raises":
        raise RuntimeError("the program fails before it stops anything")
    """
)

# The manager (a process, or a thread) is the provider; the consumer in the program's own
# process is not the supervisor's, and the supervisor is stopped first in the exit's
# order, but the consumer holds an id at its manager: it is stopped before the tree. The
# other manager (a thread manager is a registrar of the program too, newer than the
# consumer) is stopped by its tree, never on its own (its tree would restart it).
SUPERVISED = textwrap.dedent(
    """
    import functools
    import sys
    import rr_actors as rr

    backup, uid, ending, marker, isolation = sys.argv[1:6]

    def unload(marker, request, response):
        with open(marker, "a") as file:
            file.write(request + "\\n")

    def setup(marker, registrar):
        registrar.register_server(
            "res", load=lambda r: {"r": r}, unload=functools.partial(unload, marker)
        )

    def serve_nothing(registrar):
        pass

    config = rr.RegistrarConfig(f"provider-{uid}", backup_path=backup, save_interval=3600.0)
    consumer = rr.ResourceRegistrar.start(f"consumer-{uid}")
    sup = rr.Supervisor(
        [
            rr.ManagerSpec(
                config.name, functools.partial(setup, marker), isolation=isolation, config=config
            ),
            rr.ManagerSpec(f"other-{uid}", serve_nothing, isolation=isolation),
        ]
    ).start()
    query = consumer.call(config.name, "res", "camera")
    print(query.id, sup.child(config.name).pid or 0, flush=True)
    if ending == "raises":
        raise RuntimeError("the program fails before it stops anything")
    """
)

BOUND = 20.0
"""Seconds such a program may take, start to end (it takes about one)."""


def run_program(
    source: str, backup: Path, uid: str, ending: str, isolation: str = "process"
) -> tuple[int, float, str, str]:
    """Run `source` with its arguments; its exit code, duration, stdout and stderr.

    Its provider's `unload` appends each request to `<backup>.unloaded`.
    """
    started = time.monotonic()
    try:
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", source, str(backup), uid, ending, unloaded(backup), isolation],
            capture_output=True,
            text=True,
            timeout=2 * BOUND,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"},
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"the program did not end within {2 * BOUND:g} s: {exc.stderr!r}")
    return done.returncode, time.monotonic() - started, done.stdout, done.stderr


def unloaded(backup: Path) -> str:
    """The file the program's provider appends each request it unloads to."""
    return f"{backup}.unloaded"


def unloads(backup: Path) -> list[str]:
    """The requests the program's provider unloaded, in order."""
    path = Path(unloaded(backup))
    return path.read_text().splitlines() if path.exists() else []


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
def test_a_program_that_leaves_registrars_running_ends_its_consumer_first_and_writes_backups(
    tmp_path: Path, ending: str, code: int
) -> None:
    uid = uuid.uuid4().hex[:8]
    backup = tmp_path / "provider.db"

    returncode, took, _out, err = run_program(THREADS, backup, uid, ending)

    assert (code, True) == (returncode, took < BOUND), err
    assert "Exception ignored" not in err
    assert "WARNING" not in err  # (was: releasing <id> at provider-...: it was stopped)
    assert ["camera"] == unloads(backup)
    assert [] == held_ids(backup, f"provider-{uid}")  # its backup, written after the release


@pytest.mark.parametrize("isolation", ["process", "thread"])
@pytest.mark.parametrize(("ending", "code"), [("raises", 1), ("returns", 0)])
def test_a_program_that_leaves_a_supervisor_running_ends_its_consumer_first_then_the_managers(
    tmp_path: Path, ending: str, code: int, isolation: str
) -> None:
    uid = uuid.uuid4().hex[:8]
    backup = tmp_path / "provider.db"

    returncode, took, out, err = run_program(SUPERVISED, backup, uid, ending, isolation)

    _query_id, pid = out.split()
    assert (code, True) == (returncode, took < BOUND), err
    assert "Exception ignored" not in err
    assert "WARNING" not in err  # (was: releasing <id> at provider-...: no registrar named)
    assert ["camera"] == unloads(backup)
    assert [] == wait_gone([int(pid)] if isolation == "process" else [])
    assert [] == held_ids(backup, f"provider-{uid}")
