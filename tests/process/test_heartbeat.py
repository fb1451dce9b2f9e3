"""The heartbeat's judgement (`rr_actors._process.heartbeat`): hung, or only starved.

Real manager processes, real signals, real starvation. A manager is *starved* here by the
kernel's scheduler, not by a mock: every thread of it gets the `SCHED_IDLE` policy and is
pinned to one CPU that a busy loop at nice -20 holds, so it stays runnable but runs only
when that CPU has nothing else to do (never, while the loop runs). A *stopped* one gets
`SIGSTOP`, a *stuck* one has its registrar actor blocked on an event. What waits for a
judgement waits on the heartbeat's own log lines (a handler that sets an event), bounded.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._platform.base import CpuSample
from rr_actors._process.control import Events, Ping, Pong, Ready, Stop, mp_context, start_forkserver
from rr_actors._process.heartbeat import PACE, STARVED_LIMIT, Hang, Heartbeat, Late, Look, Pace
from rr_actors._process.manager import ManagerProcess
from rr_actors.testing import SharedObjects, run_on_actor
from tests.support.starving import busy_cpu, pinned, starved
from tests.support.supervising import bare_manager, linux_trick, pid_of, process

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux scheduling")


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


# -- helpers ------------------------------------------------------------------------------------


class _Heard(logging.Handler):
    """Sets `event` at the first record of the `rr_actors` log that contains one of `texts`."""

    def __init__(self, texts: tuple[str, ...]) -> None:
        super().__init__(logging.DEBUG)
        self.texts = texts
        self.event = threading.Event()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if any(text in record.getMessage() for text in self.texts):
            self.records.append(record)
            self.event.set()


@contextlib.contextmanager
def heard(*texts: str) -> Iterator[_Heard]:
    """The `rr_actors` log lines that contain one of `texts`, from now on."""
    handler = _Heard(texts)
    log = logging.getLogger("rr_actors")
    log.addHandler(handler)
    try:
        yield handler
    finally:
        log.removeHandler(handler)


# -- hung: stopped, stuck -----------------------------------------------------------------------


def test_a_stopped_manager_is_killed_as_hung_and_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=0.5)]).start()
    old = pid_of(sup, name)

    os.kill(old, signal.SIGSTOP)
    info = sup.wait_restarted(name, timeout=15.0)

    assert info.last_exit is not None
    assert (True, True) == (info.last_exit.startswith("hung"), info.pid != old)


@linux_trick
def test_a_stopped_manager_is_told_stopped_and_killed_even_while_its_cpu_is_busy(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    # Its CPU is shared with a busy loop (it still gets half of it: SIGSTOP takes effect),
    # so some of its threads may wait for it; a stopped process is hung all the same.
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=0.5)]).start()
    old = pid_of(sup, name)

    with busy_cpu() as cpu, pinned(old, cpu):
        os.kill(old, signal.SIGSTOP)
        info = sup.wait_restarted(name, timeout=15.0)

    assert info.last_exit is not None
    assert info.last_exit.startswith("hung: no heartbeat answer for")
    assert "(stopped: SIGSTOP or a debugger)" in info.last_exit


def _block_actor(gate: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def block(registrar: rr.ResourceRegistrar) -> None:
        run_on_actor(registrar, lambda: gate.wait(30))  # its mailbox waits behind this

    return block


def test_a_manager_whose_registrar_is_stuck_is_killed_as_hung_although_its_cpu_is_busy(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    # Its registrar sleeps on an event (a deadlock, say): no thread of it waits for a CPU,
    # so the busy CPU it is pinned to excuses nothing.
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=0.5)]).start()
    old = pid_of(sup, name)
    gate = process_helpers.event()

    with busy_cpu() as cpu, pinned(old, cpu), heard("hangs") as hangs:
        sup.run_in(name, _block_actor(gate))
        assert hangs.event.wait(15.0)
        info = sup.wait_restarted(name, timeout=15.0)
    gate.set()

    assert info.last_exit is not None
    assert info.last_exit.startswith("hung: no heartbeat answer for")
    assert "stopped" not in info.last_exit


# -- starved: not hung --------------------------------------------------------------------------


@linux_trick
def test_a_starved_manager_is_not_killed_as_hung(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"erm-{uid}"
    # (a bound of 2 s, not 0.5: once freed, a manager at CI load was silent 0.73 s, 0.002 s
    # of it waiting for a CPU, and was killed as hung; what is judged here is the starving)
    sup = supervisors([process(name, heartbeat=0.2, heartbeat_timeout=2.0)]).start()
    app = sup.registrar(f"app-{uid}")
    pid = pid_of(sup, name)

    with heard("could run for only", "hangs") as judged, starved(pid):
        # its silence passes the bound (2 s) while it waits for the CPU
        assert judged.event.wait(30.0), "no judgement of its silence within 30 s"
    answered = app.call(name, "echo", "after", timeout=15.0)

    assert ["WARNING"] == [r.levelname for r in judged.records], judged.records[0].getMessage()
    assert f"manager {name} has not answered its heartbeat" in judged.records[0].getMessage()
    info = sup.child(name)
    assert (pid, 0, "after") == (info.pid, info.restarts, answered.response)


@linux_trick
def test_a_manager_starved_for_the_limit_is_killed_as_hung_all_the_same(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    # 10 times its bound of 0.2 s: 2 s of a silence spent waiting for a CPU
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=0.05, heartbeat_timeout=0.2)]).start()
    pid = pid_of(sup, name)

    with heard("hangs") as hangs, starved(pid):
        assert hangs.event.wait(30.0)  # (then the CPU is freed: a starved process dies slowly)
    info = sup.wait_restarted(name, timeout=15.0)

    assert info.last_exit is not None
    assert info.last_exit.startswith("hung: no heartbeat answer for")
    assert f"waiting for a CPU ({STARVED_LIMIT:g}x its bound)" in info.last_exit
    silent = float(info.last_exit.split("for ")[1].split(" s")[0])
    assert silent >= STARVED_LIMIT * 0.2


# -- the watcher's own delays -------------------------------------------------------------------

HELD_PING = 2
"""The ping whose answer the manager double sends right behind a batch of events."""


def answers_behind_events(conn: Connection) -> None:
    """A manager process's double: ready, then it answers every ping at once; the answer
    to ping `HELD_PING` comes right behind an `Events` batch, and ping `HELD_PING + 2`
    is told by one more batch, `"later"`."""
    conn.send(Ready(os.getpid()))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            os._exit(0)
        if isinstance(message, Stop):
            os._exit(0)
        if isinstance(message, Ping):
            if message.number == HELD_PING:
                conn.send(Events(["hold"]))
            if message.number == HELD_PING + 2:
                conn.send(Events(["later"]))
            conn.send(Pong(message.number))


class _Scripted:
    """What `ManagerProcess.start` takes a spare for: a running process (here the double
    `answers_behind_events`) and its control pipe."""

    def __init__(self) -> None:
        ctx = mp_context()
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=answers_behind_events, args=(child,), daemon=True)  # type: ignore[attr-defined]
        self.process.start()
        child.close()

    def take(self, *_args: Any, **_kwargs: Any) -> bool:
        return True


def test_an_answer_that_came_while_the_watcher_was_held_up_is_read_before_any_judgement(
    uid: str,
) -> None:
    # The watcher thread hands each batch of events to `on_events`; this one holds it up
    # for twice the bound (as a starved supervisor's process would hold it: waiting for a
    # CPU, for the GIL) while the answer to the ping in flight waits in the pipe. That
    # answer counts: the manager answered at once.
    bound = 0.5
    outcome = threading.Event()  # (set at its exit too)

    def on_events(batch: list[Any]) -> None:
        if "hold" in batch:
            threading.Event().wait(2 * bound)  # a duration held, not a synchronisation
        if "later" in batch:
            outcome.set()  # two more pings were answered since

    with bare_manager(
        f"held-{uid}",
        heartbeat=0.1,
        heartbeat_timeout=bound,
        exited=outcome,
        spare=_Scripted(),
        forward_events=True,
        on_events=on_events,
    ) as (_, exits, _):
        assert outcome.wait(20.0)
        assert [] == exits


# -- the judgement's arithmetic -----------------------------------------------------------------


class _Samples:
    """A `CpuWatch` that reads what the test put in `next`."""

    def __init__(self) -> None:
        self.next = CpuSample(stopped=False, waited=0.0)

    def sample(self) -> CpuSample | None:
        return self.next

    def close(self) -> None:
        pass


def test_only_the_silence_a_manager_could_run_in_counts_against_it() -> None:
    cpu = _Samples()
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0)
    assert 1 == beat.tick(0.25)  # ping 1
    beat.sent(0.25)
    assert beat.tick(0.5) is None  # late: the watch is read (0.25 s counted whole)

    cpu.next = CpuSample(stopped=False, waited=0.875)  # waited 0.875 s of the next 1 s
    starved = beat.tick(1.5)
    cpu.next = CpuSample(stopped=False, waited=0.9375)  # then 0.0625 s of 0.5 s

    assert starved is None  # 0.25 + 0.125 counted
    assert Hang(silent=1.75, waited=0.9375) == beat.tick(2.0)  # 0.25 + 0.125 + 0.4375


def test_after_a_late_answer_the_next_silence_is_watched_from_its_ping() -> None:
    cpu = _Samples()
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0)
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    assert beat.tick(0.5) is None  # a late answer: looked at
    assert beat.answered(1, 0.625)
    assert 2 == beat.tick(0.625)
    beat.sent(0.625)  # read at once: waited 0.0 then

    cpu.next = CpuSample(stopped=False, waited=0.875)  # waited 0.875 s of 1 s
    assert beat.tick(1.625) is None  # 0.125 s counted (not 0.25 + 0.125 as above)
    cpu.next = CpuSample(stopped=False, waited=1.125)  # then 0.25 s of 1 s

    assert Hang(silent=2.0, waited=1.125) == beat.tick(2.625)  # 0.125 + 0.75 counted


def test_a_stopped_manager_is_hung_once_past_the_bound_whatever_it_waited() -> None:
    cpu = _Samples()
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0)
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    assert beat.tick(0.5) is None
    cpu.next = CpuSample(stopped=True, waited=0.5)

    assert (None, Hang(silent=1.0, waited=0.5, stopped=True)) == (
        beat.tick(0.75),
        beat.tick(1.25),
    )


def test_without_a_cpu_watch_the_whole_silence_counts() -> None:
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=None, now=0.0)
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)

    assert (None, Hang(silent=0.875)) == (beat.tick(0.75), beat.tick(1.125))


def test_the_time_its_registrar_was_seen_working_does_not_count_against_it() -> None:
    cpu = _Samples()  # (no time waiting for a CPU: only the probes' answers excuse)
    lates: list[Late] = []
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0, probes=True)
    beat.on_late = lates.append
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    assert Look(1) == beat.tick(0.5)  # late: a probe
    beat.progress(1, pinged=10, handled=14, queued=300, now=0.5)  # busy since the ping
    assert beat.tick(0.625) is None  # (woken by the pipe: not due)
    assert Look(1) == beat.tick(0.75)  # 0.0 s counted
    beat.progress(1, pinged=10, handled=20, queued=200, now=0.75)  # busy: 0.5 s in all
    assert Look(1) == beat.tick(1.0)  # 0.25 s counted
    beat.progress(1, pinged=10, handled=20, queued=200, now=1.0)  # stuck from here on

    assert beat.answered(1, 1.125)  # (it answered after all: excused, reported)
    assert [Late(silent=0.875, bound=0.75, excused=0.5, waited=0.0, busy=0.5, queued=200)] == lates
    assert 2 == beat.tick(1.25)
    beat.sent(1.25)  # (the previous answer was late: watched from its ping)
    assert Look(2) == beat.tick(1.5)
    beat.progress(2, pinged=21, handled=21, queued=250, now=1.5)  # stuck: counts
    assert Look(2) == beat.tick(1.75)
    beat.progress(2, pinged=21, handled=21, queued=250, now=1.75)
    assert Look(2) == beat.tick(2.0)  # 0.75 s counted: not over the bound yet
    assert Hang(silent=1.0, waited=0.0) == beat.tick(2.25)
    assert 1 == len(lates)


def test_a_manager_that_works_and_waits_for_a_cpu_in_turns_is_excused_for_both() -> None:
    # every other probe shows work (1.0 s of the 2.0 s silence at the end), and it waited
    # for a CPU 1.0 s in all, spread over it: 1.0 + 1.0 x (1 - 1.0 / 2.0) excused, 0.5 s
    # counted (the larger of the two alone would count 1.0 s: hung at 0.75)
    cpu = _Samples()
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0, probes=True)
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    handled, verdicts = 0, []
    for look, now in enumerate([0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0, 2.25]):
        cpu.next = CpuSample(stopped=False, waited=0.5 * (now - 0.25))
        verdicts.append(beat.tick(now))
        handled += 3 if look % 2 == 0 else 0
        beat.progress(1, pinged=0, handled=handled, queued=9, now=now)

    assert [Look(1)] * 8 == verdicts


def test_the_first_probe_credits_at_most_one_step_of_work_since_the_ping() -> None:
    # its registrar handled one message after the ping, then got stuck; the probe's answer
    # was read 2.0 s after the ping (a watcher held up): it gains one `step`, not 2.0 s
    lates: list[Late] = []
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=None, now=0.0, probes=True)
    beat.on_late = lates.append
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    assert Look(1) == beat.tick(0.5)
    beat.progress(1, pinged=10, handled=11, queued=0, now=2.25)

    assert beat.answered(1, 2.25)
    assert [0.25] == [late.busy for late in lates]


def test_a_busy_registrars_warning_does_not_hide_a_starved_ones() -> None:
    # two late silences within a minute, the first excused as busy, the second as waiting
    # for a CPU: each kind is warned (a throttle shared by both would drop the second)
    cpu = _Samples()
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=cpu, now=0.0, probes=True)
    assert 1 == beat.tick(0.25)
    beat.sent(0.25)
    with heard("has not answered its heartbeat") as warned:
        for handled, now in enumerate([0.5, 0.75, 1.0, 1.25], 1):
            beat.tick(now)  # busy all along: 0.25 s counted at 1.25
            beat.progress(1, pinged=0, handled=5 * handled, queued=9, now=now)
        assert beat.answered(1, 1.25)
        assert 2 == beat.tick(1.25)
        beat.sent(1.25)  # (watched from its ping)
        for now in [1.5, 1.75, 2.0, 2.25]:
            cpu.next = CpuSample(stopped=False, waited=now - 1.25)  # waited all along
            assert beat.tick(now) in (None, Look(2))

    assert [
        ("registrar was busy" in r.getMessage(), "waited for a CPU" in r.getMessage())
        for r in warned.records
    ] == [(True, False), (False, True)], warned.records


def test_a_silence_starts_when_its_ping_was_written_and_ends_with_its_answer() -> None:
    beat = Heartbeat("m", period=0.25, bound=0.75, cpu=None, now=0.0)
    assert 1 == beat.tick(0.25)
    beat.sent(0.625)  # the watcher took 0.375 s to write it

    assert beat.tick(1.25) is None  # 0.625 s since it was written
    assert (False, True) == (beat.answered(7, 1.25), beat.answered(1, 1.25))
    assert 2 == beat.tick(1.25)  # the next ping: a period has passed since the last


# -- the heartbeat --------------------------------------------------------------------------------


def block_actor(gate: Any, survived: Any, seconds: float | None) -> Callable[[Any], None]:
    """Run in a manager: make its registrar actor's thread block (a stuck registrar).

    The actor waits on `gate` (at most `seconds`), then sets `survived`: a manager killed as
    hung never gets there. The process itself keeps running; only the actor is stuck.
    """

    def fn(registrar: rr.ResourceRegistrar) -> None:
        from rr_actors.testing import run_on_actor  # noqa: PLC0415 - runs in the manager

        def op() -> None:
            gate.wait(seconds)
            survived.set()

        run_on_actor(registrar, op)

    return fn


def test_a_manager_whose_registrar_actor_is_stuck_counts_as_hung_and_is_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    name = f"erm-{uid}"
    gate, survived = process_helpers.event(), process_helpers.event()
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=1.0)]).start()
    old = sup.child(name).pid
    sup.run_in(name, block_actor(gate, survived, None), timeout=10.0)
    try:
        info = sup.wait_restarted(name, timeout=15.0)
    finally:
        gate.set()

    assert (True, True) == ((info.last_exit or "").startswith("hung"), info.pid != old)


def test_a_manager_slower_than_the_heartbeat_period_but_within_its_timeout_is_not_hung(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    name = f"erm-{uid}"
    gate, survived = process_helpers.event(), process_helpers.event()
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=5.0)]).start()
    old = sup.child(name).pid
    sup.run_in(name, block_actor(gate, survived, 1.0), timeout=10.0)  # 10 periods, 1/5 timeout

    assert survived.wait(10.0), "killed as hung before its heartbeat_timeout ran out"
    assert (old, 0) == (sup.child(name).pid, sup.child(name).restarts)


# -- busy: not hung (issue 53) --------------------------------------------------------------------


class _Overloads:
    """The tree's `ManagerOverloaded` events (`seen`); `busy` is set at the first that
    excused time its registrar was seen busy (`busy_s > 0`)."""

    def __init__(self) -> None:
        self.seen: list[events.ManagerOverloaded] = []
        self.busy = threading.Event()

    def __call__(self, event: events.Event) -> None:  # (the subscriber's thread)
        if isinstance(event, events.ManagerOverloaded):
            self.seen.append(event)
            if event.busy_s > 0.0:
                self.busy.set()


@contextlib.contextmanager
def overloads(sup: rr.Supervisor) -> Iterator[_Overloads]:
    """The tree's `ManagerOverloaded` events, from now on."""
    heard = _Overloads()
    subscription = sup.subscribe(heard)
    try:
        yield heard
    finally:
        subscription.close()


def queue_slow_messages(count: int, seconds: float, done: Any) -> Callable[[Any], None]:
    """Run in a manager: put `count` messages in its registrar's mailbox, each of which
    holds the actor `seconds` (a handler waiting on I/O); the last one sets `done`."""

    def fn(registrar: rr.ResourceRegistrar) -> None:
        import threading  # noqa: PLC0415 - runs in the manager

        from rr_actors.testing import run_on_actor  # noqa: PLC0415 - runs in the manager

        for _ in range(count - 1):
            run_on_actor(registrar, lambda: threading.Event().wait(seconds))
        run_on_actor(registrar, done.set)

    return fn


def worked_through(done: Any, hangs: _Heard, timeout: float) -> None:
    """Wait (at most `timeout` seconds) until `done` is set; fail at once if the manager
    was judged hung meanwhile."""
    deadline = time.monotonic() + timeout
    while not done.wait(0.1):
        assert not hangs.event.is_set(), hangs.records[0].getMessage()
        assert time.monotonic() < deadline, f"not done within {timeout:g} s"


def test_a_manager_whose_registrar_works_through_a_long_mailbox_is_overloaded_not_hung(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    # 75 messages of 20 ms ahead of its pings: an answer comes ~1.5 s late (3 bounds; on
    # a loaded machine up to twice that, still well within the 5 s of `STARVED_LIMIT`),
    # the actor blocked (not waiting for a CPU: nothing excused that before) but handling
    # a message every 20 ms
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=0.1, heartbeat_timeout=0.5)]).start()
    pid = pid_of(sup, name)
    done = process_helpers.event()

    # (a late answer may be excused by its wait for a CPU alone, beside other tests: what
    # is asserted is that one was excused as busy, and the manager lived on)
    with overloads(sup) as overloaded, heard("hangs") as hangs:
        sup.run_in(name, queue_slow_messages(75, 0.02, done), timeout=10.0)
        worked_through(done, hangs, 30.0)
        answered = sup.registrar(f"app-{uid}").call(name, "echo", "after", timeout=15.0)
        assert overloaded.busy.wait(10.0), ("no ManagerOverloaded excused as busy", overloaded.seen)

    info = sup.child(name)
    assert not hangs.records, hangs.records[0].getMessage()
    assert (pid, 0, "after") == (info.pid, info.restarts, answered.response)
    late = overloaded.seen
    assert all(e.manager == name and e.pid == pid for e in late), late
    assert all(e.silent_s > e.bound_s == 0.5 for e in late), late


def burning_setup(seconds: float) -> Callable[[rr.ResourceRegistrar], None]:
    """A manager's setup: server `burn`, whose `load` keeps its worker's CPU (and the GIL,
    in turns) busy for `seconds` of that thread's CPU time."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        import time  # noqa: PLC0415 - runs in the manager

        def load(request: Any) -> Any:
            until = time.thread_time() + seconds
            while time.thread_time() < until:
                pass
            return request

        registrar.register_server("burn", load=load, unload=lambda r, s: None)

    return setup


async def flood(app: rr.ResourceRegistrar, name: str, workers: int, callers: int) -> None:
    """For 4 s: `workers` awaited callers keep each worker of `name/burn` busy (new
    requests, one after another), and `callers` more call its loaded request `"hot"` (a
    dedup hit: no work, but a message for its registrar each)."""
    numbers = itertools.count()
    until = time.monotonic() + 4.0

    async def loading() -> None:
        while time.monotonic() < until:
            await app.acall(name, "burn", next(numbers), timeout=30.0)

    async def hitting() -> None:
        while time.monotonic() < until:
            with contextlib.suppress(rr.CallTimeoutError):
                await app.acall(name, "burn", "hot", timeout=5.0)

    await asyncio.gather(*(loading() for _ in range(workers)), *(hitting() for _ in range(callers)))


@linux_trick  # (CPU-bound loads starve its registrar of the GIL: the run-queue watch excuses it)
def test_a_manager_saturated_with_loads_and_calls_is_overloaded_not_hung(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    # CPU-bound loads on all 16 of its workers and 300 callers of a loaded resource, for
    # 4 s (8 bounds): its pings wait behind the calls in its mailbox, its registrar waits
    # for the GIL behind its workers (a wait the kernel counts as sleep: not excused)
    name = f"erm-{uid}"
    config = rr.RegistrarConfig(name, max_workers=16)
    spec = process(name, burning_setup(0.1), config=config, heartbeat=0.1, heartbeat_timeout=0.5)
    sup = supervisors([spec]).start()
    pid = pid_of(sup, name)
    app = sup.registrar(f"app-{uid}")

    app.call(name, "burn", "hot", timeout=15.0)
    with overloads(sup) as overloaded, heard("hangs") as hangs:
        asyncio.run(flood(app, name, 16, 300))
        answered = app.call(name, "burn", "after", timeout=15.0)
        assert overloaded.busy.wait(10.0), ("no ManagerOverloaded excused as busy", overloaded.seen)

    info = sup.child(name)
    assert not hangs.records, hangs.records[0].getMessage()
    assert (pid, 0, "after") == (info.pid, info.restarts, answered.response)
    late = overloaded.seen
    assert all(e.manager == name and e.silent_s > e.bound_s for e in late), late


# -- the pace: a process's pings at most `rate` a second ----------------------------------------


def paced(count: int, period: float, rate: float, until: float) -> list[tuple[float, int]]:
    """A scripted watcher's pings (when, which) to `count` heartbeats that answer at once,
    their turns taken at their `wake_at`s on a clock that runs to `until`."""
    pace = Pace(rate)
    beats = [Heartbeat(f"m{i}", period, 3 * period, None, 0.0, pace=pace) for i in range(count)]
    pings: list[tuple[float, int]] = []
    while (now := min(beat.wake_at for beat in beats)) < until:
        which = min(range(count), key=lambda i: beats[i].wake_at)
        number = beats[which].tick(now)
        if isinstance(number, int):
            beats[which].sent(now)
            assert beats[which].answered(number, now)
            pings.append((now, which))
    for beat in beats:
        beat.close()
    assert (0, 0.0) == (pace.beats, pace.asked)  # (each left it)
    return pings


def test_pings_within_the_pace_keep_their_period_and_those_beyond_it_share_the_rate() -> None:
    with heard("heartbeats ask for") as warned:
        within = paced(count=10, period=0.1, rate=200.0, until=10.0)  # 100 a second asked
    with heard("heartbeats ask for") as beyond_warned:
        beyond = paced(count=10, period=0.1, rate=50.0, until=10.0)  # 100 asked, 50 go

    def per_beat(pings: list[tuple[float, int]]) -> set[int]:
        return set(collections.Counter(which for _, which in pings).values())

    assert ([], {99, 100}) == (warned.records, per_beat(within))  # every 0.1 s from 0.1 s
    assert {49, 50} == per_beat(beyond)  # every 0.2 s each: 10 / 50
    gaps = [later - earlier for (earlier, _), (later, _) in itertools.pairwise(beyond)]
    assert min(gaps) >= 1 / 50.0 - 1e-9  # spread, not a burst of ten at each period
    assert [
        "10 managers' heartbeats ask for 100 pings a second, more than the 50 this process "
        "writes: each is pinged every 0.20 s instead"
    ] == [r.getMessage().split(", and", 1)[0] for r in beyond_warned.records]


def test_a_join_racing_the_first_warning_does_not_make_it_warn_twice() -> None:
    """A manager joins the pace (another thread) as its watcher's slot warns first: one
    warning. (The join read `warned` before the slot set it and wrote it back after: the
    next slot warned again.) Forced: a join that reads `warned` is held there until a slot
    ran, the value it read kept."""
    reading, slotted, joiner = threading.Event(), threading.Event(), threading.Thread()

    class Held(Pace):
        @property
        def warned(self) -> int:
            value = self.__dict__["held_warned"]
            if threading.current_thread() is joiner and not slotted.is_set():
                reading.set()
                slotted.wait(10.0)
            return value  # type: ignore[no-any-return]

        @warned.setter
        def warned(self, value: int) -> None:
            self.__dict__["held_warned"] = value

    pace = Held(10.0)
    pace.join(0.01)  # 100 pings a second asked, 10 go
    joiner = threading.Thread(target=lambda: (pace.join(0.01), reading.set()))
    with heard("heartbeats ask for") as warned:
        joiner.start()
        assert reading.wait(10.0)  # (held where it read `warned`, or joined)
        pace.slot(0.0)
        slotted.set()
        joiner.join(10.0)
        pace.slot(1.0)
        pace.slot(2.0)

    assert ["2 managers' heartbeats ask for 200 pings"] == [
        r.getMessage()[:40] for r in warned.records
    ]


def test_a_join_while_the_pace_warns_does_not_wait_on_the_log() -> None:
    """A manager joins the pace (another thread) while its warning is being logged: the
    join does not wait for the log's handlers (a slow handler, a file or a socket, held
    every join and `close` of the process's heartbeats: the warning was logged under the
    pace's lock). Forced: a handler that waits, bounded, on such a join."""
    pace, joined, waited = Pace(10.0), threading.Event(), []

    class Joining(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            threading.Thread(target=lambda: (pace.join(0.01), joined.set())).start()
            waited.append(joined.wait(10.0))  # (False: the join waited on this log)

    pace.join(0.01)
    pace.join(0.01)  # 200 pings a second asked, 10 go
    handler, log = Joining(), logging.getLogger("rr_actors")
    log.addHandler(handler)
    try:
        pace.slot(0.0)
    finally:
        log.removeHandler(handler)

    assert ([True], 3) == (waited, pace.beats)


def test_the_pace_warns_again_once_the_beats_doubled_since_its_last_warning() -> None:
    """Each warning says how often each manager is pinged; once the beats doubled that is
    half as often (a hang found twice as late), so it is said again: at 2, 4, 8 managers
    paced here, not at each join between (a growing tree's log). Once none beats, the
    next tree past the rate is told again."""
    pace = Pace(10.0)
    said: list[int] = []
    with heard("heartbeats ask for") as warned:
        for joined in range(1, 14):
            pace.join(0.1)  # 10 pings a second each: past the rate from 2 managers
            pace.slot(float(joined))
            said.extend(int(r.getMessage().split()[0]) for r in warned.records[len(said) :])
        for _ in range(13):
            pace.join(0.1, -1)
        pace.join(0.1)
        pace.join(0.1)
        pace.slot(20.0)
        said.extend(int(r.getMessage().split()[0]) for r in warned.records[len(said) :])

    assert [2, 4, 8, 2] == said


def record_pings(monkeypatch: pytest.MonkeyPatch, want: int) -> tuple[list[Any], threading.Event]:
    """The `Ping`s the watcher writes from now on (whose, when), and an event set at the
    `want`th."""
    pings: list[tuple[str, float]] = []
    enough = threading.Event()
    send = ManagerProcess._send

    def recording(self: ManagerProcess, message: Any) -> bool:
        if isinstance(message, Ping):
            pings.append((self.name, time.monotonic()))
            if len(pings) >= want:
                enough.set()
        return send(self, message)

    monkeypatch.setattr(ManagerProcess, "_send", recording)
    return pings, enough


@pytest.mark.timeout(240)  # (sixteen manager processes start, twice, on a loaded machine too)
@pytest.mark.parametrize(("rate", "period"), [(250.0, 0.1), (80.0, 0.05)])
def test_many_managers_are_pinged_at_their_period_or_at_the_pace_said_once(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    monkeypatch: pytest.MonkeyPatch,
    rate: float,
    period: float,
) -> None:
    count, rounds = 16, 10
    monkeypatch.setattr(PACE, "rate", rate)
    monkeypatch.setattr(PACE, "warned", 0)
    pings, enough = record_pings(monkeypatch, count * (rounds + 1))
    names = [f"m{i}-{uid}" for i in range(count)]
    with heard("heartbeats ask for") as warned:
        supervisors([process(name, heartbeat=period) for name in names]).start()
        assert enough.wait(60.0)
    window = pings[count : count * (rounds + 1)]  # (its first round: the start's spread)
    each = collections.Counter(name for name, _ in window)
    by_name = {name: [at for n, at in pings if n == name] for name in names}
    intervals = [b - a for times in by_name.values() for a, b in itertools.pairwise(times)]
    stretched = count / rate > period

    assert (set(names), True) == (set(each), max(each.values()) - min(each.values()) <= 2)
    assert min(intervals) >= period  # never more often than its period
    assert (len(window) - 1) / (window[-1][1] - window[0][1]) <= 1.05 * min(rate, count / period)
    expected = [
        f"{count} managers' heartbeats ask for {count / period:.0f} pings a second, more than "
        f"the {rate:g} this process writes: each is pinged every {count / rate:.2f} s instead"
    ]
    assert (expected if stretched else []) == [
        r.getMessage().split(", and", 1)[0] for r in warned.records
    ]


def test_a_hung_manager_among_many_is_found_within_its_bound_while_the_pace_stretches_pings(
    supervisors: Callable[..., rr.Supervisor], uid: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    bound = 0.6
    monkeypatch.setattr(PACE, "rate", 80.0)  # 16 managers: each pinged every 0.2 s, not 0.05
    many = [f"m{i}-{uid}" for i in range(16)]
    sup = supervisors([process(n, heartbeat=0.05, heartbeat_timeout=bound) for n in many])
    sup.start()
    before = {name: pid_of(sup, name) for name in many}
    os.kill(before[many[7]], signal.SIGSTOP)
    info = sup.wait_restarted(many[7], timeout=30.0)
    after = {name: pid_of(sup, name) for name in many}

    assert info.last_exit is not None
    assert info.last_exit.startswith("hung: no heartbeat answer")
    silent = float(info.last_exit.split(" for ", 1)[1].split(" s", 1)[0])
    assert bound < silent < 2 * bound  # found within its bound (and a look's step), paced
    assert {n: p for n, p in before.items() if n != many[7]} == {
        n: p for n, p in after.items() if n != many[7]
    }
