"""Shared fixtures: leak checks, pickling by value, the session's helper processes.

The registrar tests' placements (threads, manager processes over AF_UNIX or Zenoh, the
async API) and recording servers are `tests/registrar/conftest.py`'s.

The autouse `no_leftovers` fixture fails any test that leaves pykka actors or child
processes running (in either placement), or a simulation run going: that one also ends
its process (a pytest-xdist worker is replaced), since no later test could run in it.
"""

from __future__ import annotations

import collections
import contextlib
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import hypothesis
import pykka
import pytest

import rr_actors as rr
from rr_actors._core import runtime
from rr_actors.testing import (
    RemoteRegistrar,
    SharedObjects,
    System,
    start_forkserver,
)
from tests.support.waiting import wait_for

pytest_plugins = ["tests.support.carriers"]  # the transport tests' fixtures

LEAK_GRACE = 5.0
"""Seconds a test's actors and child processes get to finish stopping after it ended."""

SIMULATION_GRACE = 120.0
"""Seconds a simulation run's thread gets to end after its test did: a run cancelled by
the test's timeout unwinds its greenlets after `simulation.run` stopped waiting for it
(`CANCEL_TIMEOUT`), slowly on a loaded machine, and the process stays simulated until
it has."""

_poisoned: list[str] = []
"""Why this process can run no further test (a simulation that never ended): the worker
ends after the test's report, and pytest-xdist starts a fresh one for the tests left."""

_HELPER_PIDS: set[int] = set()
"""Session-long helper processes (the `SharedObjects` manager), not leaks of a test."""

# Hypothesis's two clocks (a 200 ms deadline per example, "input generation is slow" after
# about 1 s) assert speed, which a loaded machine does not have: the property tests assert
# outcomes only (test_catalog.py failed its health check beside two busy loops).
hypothesis.settings.register_profile(
    "suite", deadline=None, suppress_health_check=[hypothesis.HealthCheck.too_slow]
)
hypothesis.settings.load_profile("suite")


def pytest_configure(config: pytest.Config) -> None:
    # A suite started in the background (`command &` in a script) inherits SIGINT ignored,
    # and Python then keeps it ignored: the Ctrl-C tests need Python's own handler here,
    # and the processes they start need SIGINT not ignored (an ignored signal is inherited).
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # pytest-xdist hands files out in the order `pytest_collection_modifyitems` gives them
    # (`FIRST`), not re-sorted by their count of tests: that put `core/test_base.py`, one test
    # that takes minutes, at the very end of the suite.
    if hasattr(config.option, "loadscopereorder"):  # (pytest-xdist is installed)
        config.option.loadscopereorder = False
    config.addinivalue_line(
        "markers",
        "thread_only(reason): run this registrar test in the thread placement only",
    )
    config.addinivalue_line(
        "markers",
        "not_zenoh(reason): run this registrar test in every placement but the zenoh one",
    )
    config.addinivalue_line(
        "markers",
        "across_processes(reason): run this registrar test in every placement but the thread one",
    )
    config.addinivalue_line(
        "markers",
        "both_apis: run these registrar tests against the async API too",
    )
    config.addinivalue_line(
        "markers",
        "blocking_api_only(reason): not against the async API (in a both_apis class)",
    )


FIRST = (
    "core/test_base.py",  # 504 s: the process tests again, on the portable platform
    "test_benchmarks.py",  # 393 s
    "test_docs.py",  # 193 s
    "simulation/test_supervision.py",  # 281 s of CPU: four sweeps of simulated trees
    "mission/test_hosts.py",  # 117 s
    "store/test_saver.py",  # 104 s (as test_sqlite.py, which the save policies joined)
    "experiments/test_plans.py",  # 102 s
    "multihost/test_zenoh_tls.py",  # 98 s
    "experiments/test_check.py",  # 91 s
    "experiments/test_cli.py",  # 87 s
)
"""Test files that run first, longest first, so that under pytest-xdist they run beside
the rest, not after it (the last file handed out sets when the suite ends). The seconds
are the sum of their tests among the suite's 80 slowest (`--durations=80` at a load
average of 15 to 25, 2026-11-24, the whole suite 31 min): a lower bound, lowest for the
files of many tests (`test_docs.py`: a test per page)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The `FIRST` files' tests to the front, in that order; then the other files, those
    with the most tests first (the order pytest-xdist itself would give them); a file's
    tests keep their order."""
    tests = Path(__file__).parent
    counts = collections.Counter(item.path for item in items)

    def rank(item: pytest.Item) -> tuple[int, int]:
        listed = item.path.relative_to(tests).as_posix() if item.path.is_relative_to(tests) else ""
        if listed in FIRST:
            return (0, FIRST.index(listed))
        return (1, -counts[item.path])

    items.sort(key=rank)  # (stable: the tests of one file keep their order)


def _os_children() -> list[int]:
    """Pids of this process's living (non-zombie) children, read from /proc (Linux)."""
    pids: set[int] = set()
    for task in Path(f"/proc/{os.getpid()}/task").glob("*"):
        try:
            pids.update(int(p) for p in (task / "children").read_text().split())
        except (OSError, ValueError):
            continue
    living = []
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state != "Z":
            living.append(pid)
    return living


def _command_line(pid: int) -> str:
    """A process's command line, for a leak's message ("?" once it is gone)."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return "?"
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()[:200]


def _is_session_helper(pid: int) -> bool:
    """Whether `pid` is `multiprocessing`'s forkserver or its resource tracker: the first
    test that starts a process manager (or a forkserver of its own) starts them, and they
    serve every later test (session-long helpers, not leaks; which test comes first
    depends on the order a worker runs them)."""
    command = _command_line(pid)
    return (
        "from multiprocessing.forkserver import main" in command
        or "from multiprocessing.resource_tracker import main" in command
    )


def _test_children() -> list[multiprocessing.process.BaseProcess]:
    return [p for p in multiprocessing.active_children() if p.pid not in _HELPER_PIDS]


@pytest.fixture(autouse=True)
def no_leftovers() -> Iterator[None]:
    """Fail the test if pykka actors or child processes outlive it (after a bounded wait)."""
    children_before = set(_os_children())
    yield
    _no_simulation_left()
    deadline = time.monotonic() + LEAK_GRACE
    for ref in pykka.ActorRegistry.get_all():
        ref.actor_stopped.wait(max(0.0, deadline - time.monotonic()))
    actors = pykka.ActorRegistry.get_all()
    for child in _test_children():
        # (a manager's process object may be closed by its supervisor meanwhile: reaped)
        with contextlib.suppress(ValueError):
            child.join(max(0.0, deadline - time.monotonic()))
    processes = _test_children()
    strays = set(_os_children()) - children_before - {p.pid for p in processes} - _HELPER_PIDS
    strays = {pid for pid in strays if not _is_session_helper(pid)}  # once, session-long
    if actors:
        pykka.ActorRegistry.stop_all(block=True, timeout=LEAK_GRACE)
    for child in processes:
        with contextlib.suppress(ValueError):  # closed meanwhile: reaped
            child.kill()
            child.join(LEAK_GRACE)
    problems = []
    if actors:
        problems.append(f"actors left running: {[a.actor_class.__name__ for a in actors]}")
    if processes:
        problems.append(f"child processes left running: {processes}")
    if strays:
        problems.append(
            "child processes (by pid) left running: "
            + ", ".join(f"{pid} ({_command_line(pid)})" for pid in sorted(strays))
        )
    if problems:
        pytest.fail("; ".join(problems))


def _no_simulation_left() -> None:
    """Wait (up to `SIMULATION_GRACE` seconds) for a simulation run the test left going to
    end; fail the test, and end this process after its report, if it does not. A process
    whose runtime stays simulated fails every later test that starts a process or a
    simulation (stop 74: one run that outlived its test's timeout failed 85 more)."""
    if not runtime.simulated():
        return
    deadline = time.monotonic() + SIMULATION_GRACE
    runs = [t for t in threading.enumerate() if t.name.startswith("rr-simulation-")]
    for thread in runs:
        thread.join(max(0.0, deadline - time.monotonic()))
    if not runtime.simulated():
        return
    frames = sys._current_frames()
    stacks = "".join(
        f"{thread.name}:\n" + "".join(traceback.format_stack(frames[thread.ident]))
        for thread in runs
        if thread.ident in frames
    )
    _poisoned.append(f"a simulation run outlived its test by {SIMULATION_GRACE:g} s")
    pytest.fail(
        f"a simulation run did not end within {SIMULATION_GRACE:g} s of its test's end; "
        f"this process stays simulated and ends after this test:\n{stacks}"
    )


@pytest.hookimpl(trylast=True)
def pytest_runtest_logfinish(nodeid: str) -> None:
    """End a process no test can run in any more (`_poisoned`), once `nodeid`'s reports
    are out: under pytest-xdist a fresh worker takes the tests left; alone, the session
    ends here with the reason."""
    if not _poisoned:
        return
    sys.stderr.write(f"\nthe process ends after {nodeid}: {_poisoned[0]}\n")
    sys.stderr.flush()
    os._exit(3)


@pytest.fixture(scope="module")
def by_value(request: pytest.FixtureRequest) -> Iterator[None]:
    """The test module is pickled by value (cloudpickle) for its module; the forkserver runs.

    For modules whose callbacks run in manager processes they start by hand (`setup=` of a
    `RemoteRegistrar` or a `ManagerSpec`): those processes cannot import the test modules.
    Use it as `pytestmark = pytest.mark.usefixtures("by_value")`.
    """
    start_forkserver()
    cloudpickle.register_pickle_by_value(request.module)
    yield
    cloudpickle.unregister_pickle_by_value(request.module)


@pytest.fixture(scope="session")
def forkserver() -> None:
    """The forkserver alone, started before a test's leak check counts this process's
    children (managers start from it: a process with a Zenoh session must not fork)."""
    start_forkserver()


@pytest.fixture(scope="session")
def process_helpers() -> Iterator[SharedObjects]:
    """The forkserver, the resource tracker and the `SharedObjects` helper, for the session.

    Started before any test's leak check counts this process's children (a session
    fixture is set up before the function-scoped autouse `no_leftovers`).
    """
    start_forkserver()
    shared = SharedObjects().start()
    assert shared.pid is not None
    _HELPER_PIDS.add(shared.pid)
    yield shared
    shared.close()
    _HELPER_PIDS.discard(shared.pid)


@pytest.fixture
def managers(request: pytest.FixtureRequest) -> Iterator[Callable[..., RemoteRegistrar]]:
    """`managers(config, setup)`: a registrar in a manager process of a fresh `System`,
    whatever the placement (the test module's functions are pickled by value); the living
    ones stop at teardown, newest first. For tests that kill and restart registrars by
    hand, with their backups."""
    start_forkserver()
    cloudpickle.register_pickle_by_value(request.module)
    system = System.create()
    started: list[RemoteRegistrar] = []

    def start(config: rr.RegistrarConfig, setup: Any) -> RemoteRegistrar:
        registrar = RemoteRegistrar.start(config, system, setup=setup)
        started.append(registrar)
        return registrar

    yield start
    for registrar in reversed(started):
        if registrar.is_alive():
            registrar.stop()
    system.close()


@pytest.fixture
def started() -> Iterator[list[rr.ResourceRegistrar]]:
    """Registrars a test starts by hand (append them); stopped newest first at teardown."""
    registrars: list[rr.ResourceRegistrar] = []
    yield registrars
    for registrar in reversed(registrars):
        if registrar.is_alive():
            registrar.stop()


@pytest.fixture
def uid() -> str:
    """A fragment that makes this test's registrar names unique."""
    return uuid.uuid4().hex[:8]


@pytest.fixture
def supervisors() -> Iterator[Callable[..., rr.Supervisor]]:
    """Make supervisors; every one is stopped at teardown (newest first)."""
    made: list[rr.Supervisor] = []

    def make(children: list[Any], **kwargs: Any) -> rr.Supervisor:
        sup = rr.Supervisor(children, **kwargs)
        made.append(sup)
        return sup

    yield make
    for sup in reversed(made):
        sup.stop()


@pytest.fixture
def drawn(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[Any]]:
    """The matplotlib figures a test's plots draw, kept open (not closed after saving) to be
    read back; closed at teardown."""
    import matplotlib.pyplot as plt  # noqa: PLC0415 - the plot tests' (an extra)

    figures: list[Any] = []
    close = plt.close
    monkeypatch.setattr(plt, "close", figures.append)
    yield figures
    for figure in figures:
        close(figure)


@pytest.fixture
def eventually() -> Callable[..., bool]:
    """`eventually(predicate, timeout=5.0)`: bounded wait for a condition other actors make true."""
    return wait_for


@pytest.hookimpl(trylast=True)
def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """With `-q` and xdist workers, name each failure as it happens (issue 44): the
    progress line shows only `F`, and the names came when the last worker ended."""
    failed = report.failed and (report.when == "call" or not report.passed)
    if not failed or not hasattr(report, "node"):  # (in the controller: node is the worker)
        return
    sys.stderr.write(f"\nFAILED {report.nodeid} ({report.when})\n")
    sys.stderr.flush()
