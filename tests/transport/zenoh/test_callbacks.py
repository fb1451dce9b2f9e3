"""Zenoh's callback threads and rr_actors' threads that call Zenoh
(`rr_actors._transport.zenoh.callbacks`): counted while they live, and ended before the
interpreter finalizes, so that none takes the GIL then (on CPython < 3.14 glibc aborts
the process: "FATAL: exception not rethrown").

The exit tests run a program in its own interpreter: a callback declared from a daemon
thread (as an actor's: its thread is a daemon too) runs as the program ends, held until
the interpreter's `atexit` (at most `HOLD` s); or a thread of rr_actors (an outbox's
writer, the presence thread) calls Zenoh on and on as the network closes (for `BUSY` s).
Before the fix, every such program was killed by SIGABRT.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import uuid
from collections.abc import Iterator

import pytest

pytest.importorskip("zenoh")

import zenoh

from rr_actors._core.serial import SerialExecutor
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.ops.config import session_config

RUNS = 3
"""Programs run per ending (each aborted before the fix, not by chance: the callback is
held across the session's close)."""

HOLD = 0.3
"""Seconds the program's callback is held at most: well under `callbacks.END_TIMEOUT`, so
that a loaded machine still ends the thread within the close's wait (without the wait,
the held callback is released at once by the `atexit` hook, during finalization)."""

PROGRAM = textwrap.dedent(
    """
    import atexit, sys, threading
    import rr_actors as rr
    from rr_actors._transport.zenoh.callbacks import tracked

    system, ending, hold = sys.argv[1], sys.argv[2], float(sys.argv[3])
    net = rr.ZenohNetwork(system=system, tls=None)
    session, key = net.services().session, f"rr/{system}/obs/test/delta"
    inside, finalizing = threading.Event(), threading.Event()
    atexit.register(finalizing.set)  # (the last Python before the interpreter finalizes)

    def held(sample):
        inside.set()
        finalizing.wait(hold)

    declared = []  # on a daemon thread, as an actor's: the callback's thread is a daemon
    thread = threading.Thread(
        target=lambda: declared.append(session.declare_subscriber(key, tracked(session, held))),
        daemon=True,
    )
    thread.start()
    thread.join(10)
    session.put(key, b"x")
    assert inside.wait(10), "the callback was not called"
    if ending == "close":
        net.close()
    print("ending", flush=True)  # "open": the exit hook closes the network
    """
)


@pytest.mark.parametrize("ending", ["close", "open"])
def test_a_program_whose_zenoh_callback_runs_as_it_ends_exits_without_an_abort(
    ending: str,
) -> None:
    results = []
    for _ in range(RUNS):
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", PROGRAM, f"cb-{uuid.uuid4().hex[:8]}", ending, str(HOLD)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        results.append((done.returncode, "not rethrown" in done.stderr, done.stdout))

    assert [(0, False, "ending\n")] * RUNS == results, done.stderr


CALLING_RUNS = 2
"""Programs run per thread and ending (each aborted before the fix, not by chance: 40 of
40 did; each takes `BUSY` s more than a program of the first test)."""

BUSY = 1.0
"""Seconds the program's thread of rr_actors calls Zenoh on and on from when the network
begins to close: well under `callbacks.END_TIMEOUT`, so that a loaded machine still ends
it within the close's wait, and longer than a close that does not wait for it takes to
reach the interpreter's end (so the thread is inside a Zenoh call then)."""

CALLING = textwrap.dedent(
    """
    import sys, threading, time
    import rr_actors as rr
    from rr_actors.errors import RegistrarStoppedError

    system, thread, ending, busy = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    net = rr.ZenohNetwork(system=system, tls=None)
    carrier = net.link()
    session, key = carrier.session, f"rr/{system}/obs/test/delta"
    inside = threading.Event()

    def calling(*_):  # a task of one of rr_actors' threads that calls Zenoh, `busy` s long
        inside.set()
        deadline = time.monotonic() + busy
        while time.monotonic() < deadline:
            try:
                session.put(key, b"x")
            except Exception:  # (the session closed meanwhile)
                pass
        print("done", flush=True)

    if thread == "writer":  # an outbox's writer, retired as it runs (its destination went)
        outbox = carrier.outbox(key)
        outbox.run(calling)
        assert inside.wait(10), "the writer did not run the task"
        carrier.retire(outbox, RegistrarStoppedError("gone"))
    else:  # the presence thread, as it runs what a process's end calls for
        carrier.process_gone = calling
        session.liveliness().declare_token(carrier.keys.proc("abc123")).undeclare()
        assert inside.wait(10), "the presence thread did not hear the process go"
    if ending == "close":
        net.close()
    print("ending", flush=True)  # "open": the exit hook closes the network
    """
)


@pytest.mark.parametrize("ending", ["close", "open"])
@pytest.mark.parametrize("thread", ["writer", "presence"])
def test_a_program_whose_thread_calls_zenoh_as_its_network_closes_exits_without_an_abort(
    thread: str, ending: str
) -> None:
    results = []
    for _ in range(CALLING_RUNS):
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [
                sys.executable,
                "-c",
                CALLING,
                f"zc-{uuid.uuid4().hex[:8]}",
                thread,
                ending,
                str(BUSY),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        results.append((done.returncode, "FATAL" in done.stderr, done.stdout))

    ended = "done\nending\n" if ending == "close" else "ending\ndone\n"  # (joined by the close)
    assert [(0, False, ended)] * CALLING_RUNS == results, done.stderr


LATE = textwrap.dedent(
    """
    import sys, threading, time
    import rr_actors as rr
    from rr_actors._core.serial import SerialExecutor
    from rr_actors._transport.zenoh import callbacks

    system, busy = sys.argv[1], float(sys.argv[2])
    net = rr.ZenohNetwork(system=system, tls=None)
    session = net.link().session
    key, inside, closed = f"rr/{system}/obs/test/delta", threading.Event(), threading.Event()

    def calling():  # a task of a thread of rr_actors that calls Zenoh, `busy` s long
        inside.set()
        deadline = time.monotonic() + busy
        while time.monotonic() < deadline:
            try:
                session.put(key, b"x")
            except Exception:  # (the session closed)
                pass
        print("done", flush=True)

    late = SerialExecutor("rr-test-late")
    late.submit(calling)
    assert inside.wait(10), "the worker did not run its task"
    registering = threading.Thread(  # held until the session closed: registered after
        target=lambda: closed.wait(10) and print(callbacks.worker(session, late), flush=True),
        daemon=True,
    )
    registering.start()
    net.close()
    closed.set()
    registering.join(10)
    print("ending", flush=True)
    """
)


def test_a_program_whose_worker_is_registered_after_its_session_closed_exits_without_an_abort() -> (
    None
):
    results = []
    for _ in range(CALLING_RUNS):
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", LATE, f"zl-{uuid.uuid4().hex[:8]}", str(BUSY)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        results.append((done.returncode, "FATAL" in done.stderr, done.stdout))

    # (refused, and joined at once: its task ended before the registration returned)
    assert [(0, False, "done\nFalse\nending\n")] * CALLING_RUNS == results, done.stderr


def test_a_worker_registered_after_its_session_closed_is_refused_and_joined_at_once() -> None:
    opened = zenoh.open(session_config("peer", [], [], 1.0))
    late, ran, go = SerialExecutor("rr-test-late"), threading.Event(), threading.Event()
    late.submit(ran.set)
    assert ran.wait(5)  # (its thread runs, and waits for tasks)
    registered: list[bool] = []
    registering = threading.Thread(
        target=lambda: go.wait(10) and registered.append(callbacks.worker(opened, late)),
        daemon=True,
    )
    registering.start()  # (held by `go` until the close waited for the session's workers)
    opened.close()  # type: ignore[no-untyped-call]
    assert [] == callbacks.wait_ended(opened, 5)

    go.set()
    registering.join(10)

    assert [False] == registered
    assert late.closed
    assert late.join(0)
    assert not late.submit(ran.set)


CALLERS = textwrap.dedent(
    """
    import atexit, sys, threading
    import rr_actors as rr

    system, threads, ending = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    net = rr.ZenohNetwork(system=system, tls=None)
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=net)
    started, ended = threading.Barrier(threads + 1), threading.Event()
    foreign = set()  # the calls that went on as the program ended: not rr_actors' errors

    def calling():  # a program's own thread, in call after call (each asks the network)
        started.wait()
        while True:
            try:
                app.call("nobody", "camera", {"device": 0}, timeout=1.0)
            except Exception as exc:
                if ended.is_set() and not isinstance(exc, rr.RrError):
                    foreign.add(repr(exc))

    for _ in range(threads):
        threading.Thread(target=calling, daemon=True).start()
    started.wait()
    if ending == "close":
        net.close()  # (its registrar left running: the calls go on)
    ended.set()
    atexit.register(  # (after the exit hook)
        lambda: print(sorted(foreign), flush=True)
    )
    print("ending", flush=True)  # the exit hook stops the registrar ("open": then the network)
    """
)

CALLER_RUNS = 3
"""Programs run per ending (a guard, not forced: 1 of 40 such programs aborted before the
calls were counted, 0 of 40 after; with the network closed by the program and its
registrar left running, "close", 1 to 2 of 40 before its carrier record let go of its
Zenoh objects at the stop, 0 of 40 after: benchmarks/NOTES.md, 2026-11-26; the forced
test is test_carrier.py's `..._registrar_outlives_its_networks_close_...`)."""


@pytest.mark.parametrize("ending", ["open", "close"])
def test_a_program_whose_threads_are_in_calls_as_it_ends_exits_without_an_abort(
    ending: str,
) -> None:
    """The exit hook stops the registrar, then closes the network ("open"; "close": the
    program closed it, the registrar left running): every call that went on failed with
    an error of rr_actors (the stop's, or the network's); none aborted the process."""
    results = []
    for _ in range(CALLER_RUNS):
        done = subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
            [sys.executable, "-c", CALLERS, f"zu-{uuid.uuid4().hex[:8]}", "8", ending],
            capture_output=True,
            text=True,
            timeout=60,
        )
        results.append((done.returncode, "FATAL" in done.stderr, done.stdout))

    assert [(0, False, "ending\n[]\n")] * CALLER_RUNS == results, done.stderr


def test_a_call_under_way_is_waited_for_by_the_close_and_one_after_the_wait_refused() -> None:
    opened = zenoh.open(session_config("peer", [], [], 1.0))
    inside, release = threading.Event(), threading.Event()

    def call() -> None:  # (a program's thread in a call: nothing joins it)
        with callbacks.calling(opened):
            inside.set()
            release.wait(10)

    caller = threading.Thread(target=call, daemon=True)
    caller.start()
    assert inside.wait(5)
    opened.close()  # type: ignore[no-untyped-call]

    assert ["1 Zenoh calls of other threads"] == callbacks.wait_ended(opened, 0.1)
    release.set()
    caller.join(5)
    assert [] == callbacks.wait_ended(opened, 5)
    with pytest.raises(callbacks.SessionEndedError), callbacks.calling(opened):
        pytest.fail("a call began after the close waited")


def test_calls_on_an_open_session_are_neither_waited_for_nor_refused(
    session: zenoh.Session,
) -> None:
    with callbacks.calling(session):
        assert [] == callbacks.wait_ended(session, 0)
    with callbacks.calling(session):
        pass


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    opened = zenoh.open(session_config("peer", [], [], 1.0))
    yield opened
    opened.close()  # type: ignore[no-untyped-call]


def test_a_callback_thread_is_counted_until_its_subscriber_is_undeclared(
    session: zenoh.Session,
) -> None:
    before = callbacks.live(session)
    got = threading.Event()
    subscriber = session.declare_subscriber(
        "test/counted", callbacks.tracked(session, lambda _: got.set())
    )
    session.put("test/counted", b"x")
    assert got.wait(5)

    assert before + 1 == callbacks.live(session)
    subscriber.undeclare()  # type: ignore[no-untyped-call]
    assert [] == callbacks.wait_ended(session, 5)
    assert before == callbacks.live(session)


def test_every_callback_thread_of_a_closed_session_is_ended_and_joined() -> None:
    opened = zenoh.open(session_config("peer", [], [], 1.0))
    before = set(threading.enumerate())
    for n in range(3):  # (declared from a daemon thread: their threads are daemons)
        declaring = threading.Thread(
            target=opened.declare_subscriber,
            args=(f"test/closed/{n}", callbacks.tracked(opened, lambda _: None)),
            daemon=True,
        )
        declaring.start()
        declaring.join(5)
    made = {t for t in set(threading.enumerate()) - before if "pyo3-closure" in t.name}  # (Zenoh's)
    assert 3 == len(made)
    assert all(thread.daemon for thread in made)

    opened.close()  # type: ignore[no-untyped-call]

    assert [] == callbacks.wait_ended(opened, 5)
    assert 0 == callbacks.live(opened)
    assert [] == [thread for thread in made if thread.is_alive()]


def test_a_worker_is_joined_once_closed_and_named_while_it_runs_past_the_wait(
    session: zenoh.Session,
) -> None:
    inside, release = threading.Event(), threading.Event()
    held = SerialExecutor("rr-test-held")
    callbacks.worker(session, held)
    held.submit(lambda: (inside.set(), release.wait(10)))
    assert inside.wait(5)
    held.close(timeout=0)

    assert ["rr-test-held"] == callbacks.wait_ended(session, 0.1)
    release.set()
    callbacks.worker(session, held)
    assert [] == callbacks.wait_ended(session, 5)
    assert held.join(0)


def test_a_declaration_that_fails_leaves_nothing_to_wait_for(session: zenoh.Session) -> None:
    with pytest.raises(zenoh.ZError):
        session.declare_subscriber("test//bad", callbacks.tracked(session, lambda _: None))

    assert [] == callbacks.wait_ended(session, 5)
    assert 0 == callbacks.live(session)
