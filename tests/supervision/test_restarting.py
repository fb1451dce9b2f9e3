"""Restart decisions (`rr_actors._supervision.restarting`): which siblings go down and come
back and in which order, the intensity window (its pure `RestartIntensity` too) and the
give-up, the backoff; and what a restart must give back.

Where rr_actors' supervisor used to depart from Erlang/OTP's (issue 16), case by case:
ported from the ideas of OTP's `supervisor_SUITE`: a SIGTERM to a manager process is
OTP's `shutdown` (a clean exit for a `transient` child, as for systemd's `on-failure`); a
supervisor that gives up exits with `shutdown`; a give-up is reported once the tree has
settled; a group restart (one_for_all, rest_for_one) brings back a `transient` child that
had exited normally. Crashes are real: SIGKILL/SIGTERM for processes,
`rr_actors.testing.crash` for thread managers. Waits are bounded and event-driven.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import signal
import sqlite3
import sys
import threading
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import testing
from rr_actors._catalog import Changes, ClientRecord
from rr_actors._store.files import read_backup
from rr_actors._store.sqlite import SqliteStore
from rr_actors._supervision.restarting import RestartIntensity
from rr_actors.testing import (
    SharedObjects,
    catalog_snapshot,
    expect_restart,
    start_forkserver,
)
from tests.support.gating import GatedLoad
from tests.support.supervising import (
    FakeClock,
    ManualTimer,
    crash,
    echo_setup,
    logging_consumer,
    pid_of,
    process,
)

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


# -- SIGTERM is a request to stop (OTP's `shutdown`) ----------------------------------------------


def test_a_transient_manager_process_ended_by_sigterm_is_not_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"t-{uid}"
    sup = supervisors([process(name, restart="transient")]).start()
    os.kill(pid_of(sup, name), signal.SIGTERM)

    with pytest.raises(rr.RegistrarUnavailableError, match="will not be restarted"):
        sup.wait_restarted(name, timeout=10.0)
    info = sup.child(name)
    assert ("exited", "shutdown (SIGTERM)", 0) == (info.state, info.last_exit, info.restarts)


def test_a_permanent_manager_process_ended_by_sigterm_is_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"p-{uid}"
    sup = supervisors([process(name)]).start()
    os.kill(pid_of(sup, name), signal.SIGTERM)

    info = sup.wait_restarted(name, timeout=10.0)
    assert ("running", "shutdown (SIGTERM)") == (info.state, info.last_exit)


def unload_flag(unloaded: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("res", load=lambda r: r, unload=lambda r, s: unloaded.set())

    return setup


def consumer_of(provider: str) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        if not registrar.client_queries():
            registrar.call(provider, "res", "camera", timeout=10.0)

    return setup


def test_a_transient_consumer_ended_by_sigterm_has_its_ids_released_at_its_provider(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    # A SIGTERM ends the process without a clean stop of its registrar: it is down for
    # good, and nobody but the death watch gives back what it held.
    p, c = f"p-{uid}", f"c-{uid}"
    unloaded = process_helpers.event()
    sup = supervisors(
        [process(p, unload_flag(unloaded)), process(c, consumer_of(p), restart="transient")]
    ).start()
    os.kill(pid_of(sup, c), signal.SIGTERM)

    assert unloaded.wait(10.0)
    assert [] == sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0)


# -- a supervisor that gives up exits with `shutdown` ---------------------------------------------


def test_a_transient_nested_supervisor_that_gives_up_is_not_restarted_by_its_parent(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    x, inner = f"x-{uid}", f"inner-{uid}"
    spec = rr.SupervisorSpec(inner, (rr.ManagerSpec(x),), max_restarts=0, restart="transient")
    sup = supervisors([rr.ManagerSpec(f"a-{uid}"), spec], clock=FakeClock()).start()
    crash(sup, x)

    with pytest.raises(rr.SupervisorGaveUpError, match=inner):
        sup.wait_restarted(inner, timeout=5.0)
    info = sup.child(inner)
    assert ("exited", 0, None) == (info.state, info.restarts, sup.gave_up)
    assert "running" == sup.child(f"a-{uid}").state


def test_a_permanent_nested_supervisor_that_gives_up_is_still_restarted_by_its_parent(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    x, inner = f"x-{uid}", f"inner-{uid}"
    spec = rr.SupervisorSpec(inner, (rr.ManagerSpec(x),), max_restarts=0, restart="permanent")
    sup = supervisors([spec], clock=FakeClock()).start()
    crash(sup, x)

    assert 1 == sup.wait_restarted(inner, timeout=5.0).restarts


# -- the give-up is reported once the tree has settled --------------------------------------------


def test_a_give_up_is_not_reported_while_an_earlier_sibling_is_still_stopping(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"
    stopping, release = threading.Event(), threading.Event()

    def slow_to_stop(reg: rr.ResourceRegistrar) -> None:
        def unload(_request: Any, _response: Any) -> None:
            stopping.set()
            release.wait(10.0)

        reg.register_server("res", load=lambda r: r, unload=unload)

    sup = supervisors(
        [rr.ManagerSpec(a, slow_to_stop), rr.ManagerSpec(b), rr.ManagerSpec(c)],
        max_restarts=0,
        clock=FakeClock(),
    ).start()
    sup.run_in(a, lambda reg: reg.call(a, "res", "x"))  # its clean stop must unload it
    try:
        crash(sup, b)  # the give-up stops c, then b is down, then a (stopped last)
        assert stopping.wait(5.0), "a was not stopped"
        with pytest.raises(rr.CallTimeoutError):
            sup.wait_restarted(b, timeout=0.3)  # a still stops: nothing is settled yet
        assert None is sup.gave_up
    finally:
        release.set()

    with pytest.raises(rr.SupervisorGaveUpError):
        sup.wait_restarted(b, timeout=5.0)
    assert sup.gave_up is not None
    assert ["stopped"] * 3 == [i.state for i in sup.which_children()]


# -- a group restart brings back a transient child that had exited normally (as OTP) -------------


@pytest.mark.parametrize("strategy", ["one_for_all", "rest_for_one"])
def test_a_group_restart_also_restarts_a_transient_child_that_had_exited_normally(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    strategy: str,
    eventually: Callable[..., bool],
) -> None:
    b, t = f"b-{uid}", f"t-{uid}"
    sup = supervisors(
        [rr.ManagerSpec(b), rr.ManagerSpec(t, echo_setup, restart="transient")],
        strategy=strategy,
        clock=FakeClock(),
    ).start()
    with contextlib.suppress(rr.RegistrarStoppedError):
        sup.run_in(t, lambda r: r.stop())  # code in the manager stops it: a normal exit
    assert eventually(lambda: "exited" == sup.child(t).state)
    crash(sup, b)

    info = sup.wait_restarted(t, timeout=5.0, restarts=1)
    assert ("running", 1) == (info.state, info.restarts)


@pytest.mark.parametrize("strategy", ["one_for_all", "rest_for_one"])
def test_a_group_restart_leaves_a_temporary_child_that_had_exited_down(
    supervisors: Callable[..., rr.Supervisor], uid: str, strategy: str
) -> None:
    b, t = f"b-{uid}", f"t-{uid}"
    sup = supervisors(
        [rr.ManagerSpec(b), rr.ManagerSpec(t, restart="temporary")],
        strategy=strategy,
        clock=FakeClock(),
    ).start()
    crash(sup, t)
    with pytest.raises(rr.RegistrarUnavailableError):
        sup.wait_restarted(t, timeout=5.0)
    crash(sup, b)
    sup.wait_restarted(b, timeout=5.0)

    assert ("exited", 0) == (sup.child(t).state, sup.child(t).restarts)


def test_wait_restarted_on_a_transient_child_that_exited_waits_for_its_group_restart(
    supervisors: Callable[..., rr.Supervisor], uid: str, eventually: Callable[..., bool]
) -> None:
    # Under one_for_all it is down only until a sibling's crash restarts the group: not
    # "will not be restarted" (under one_for_one it is: see test_supervisor.py).
    b, t = f"b-{uid}", f"t-{uid}"
    sup = supervisors(
        [rr.ManagerSpec(b), rr.ManagerSpec(t, echo_setup, restart="transient")],
        strategy="one_for_all",
        clock=FakeClock(),
    ).start()
    with contextlib.suppress(rr.RegistrarStoppedError):
        sup.run_in(t, lambda r: r.stop())
    assert eventually(lambda: "exited" == sup.child(t).state)

    with pytest.raises(rr.CallTimeoutError):
        sup.wait_restarted(t, timeout=0.3)


# -- strategies: which siblings, in which order -------------------------------------------------


@pytest.mark.parametrize("strategy", ["one_for_all", "rest_for_one"])
def test_siblings_stop_in_reverse_start_order_and_restart_in_start_order(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    log_provider: tuple[rr.ResourceRegistrar, list[str]],
    strategy: str,
) -> None:
    provider, events = log_provider
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"
    setup = logging_consumer(provider.name, events)
    sup = supervisors(
        [rr.ManagerSpec(n, setup) for n in (a, b, c)], strategy=strategy, clock=FakeClock()
    ).start()
    del events[:]
    crash(sup, a)
    for name in (a, b, c):
        sup.wait_restarted(name, timeout=5.0)

    # a crashed (it keeps its id: it is expected back); c then b are stopped, newest first
    assert [f"unload {c}", f"unload {b}", f"start {a}", f"start {b}", f"start {c}"] == events


def test_rest_for_one_starts_a_child_whose_backoff_ran_out_only_after_the_earlier_siblings(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    """rest_for_one: the children after a crashed one depend on it, so they come back only
    after it. `c` crashed and waits out its backoff; then `a` crashes, which takes `b` and
    `c` down with it. When `c`'s own backoff runs out first, `c` must not be started while
    `a` and `b` are still down (nor be left out of the group's restart after them)."""
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"
    starts: list[str] = []

    def setup(registrar: rr.ResourceRegistrar) -> None:
        starts.append(registrar.name)

    timer = ManualTimer()
    sup = supervisors(
        [rr.ManagerSpec(n, setup) for n in (a, b, c)],
        strategy="rest_for_one",
        backoff=rr.Backoff(initial=1.0),
        clock=FakeClock(),
        timer=timer,
    ).start()
    del starts[:]
    crash(sup, c)
    assert timer.wait_scheduled(1)  # c's restart, after its backoff
    crash(sup, a)
    assert timer.wait_scheduled(2)  # a, b, c's, after a longer one
    timer.fire()  # both ran out, c's first
    for name in (a, b):
        sup.wait_restarted(name, timeout=5.0)
    sup.wait_restarted(c, timeout=5.0)

    assert (c, True) == (starts[-1], {a, b} <= set(starts[:-1])), starts


def test_a_permanent_child_that_exits_normally_is_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([rr.ManagerSpec(name, echo_setup)], clock=FakeClock()).start()
    with contextlib.suppress(rr.RegistrarStoppedError):
        sup.run_in(name, lambda r: r.stop())  # code in the manager stops it cleanly

    info = sup.wait_restarted(name, timeout=5.0)
    assert ("running", 1, "normal") == (info.state, info.restarts, info.last_exit)


def test_a_permanent_manager_process_that_exits_normally_is_restarted(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([process(name)]).start()
    old = sup.child(name).pid
    with contextlib.suppress(rr.RegistrarStoppedError, rr.RegistrarUnavailableError):
        sup.run_in(name, stop_own_registrar, timeout=10.0)

    info = sup.wait_restarted(name, timeout=15.0)
    assert ("running", 1, "normal", True) == (
        info.state,
        info.restarts,
        info.last_exit,
        info.pid not in (None, old),
    )


def stop_own_registrar(registrar: rr.ResourceRegistrar) -> str:
    registrar.stop()
    return "stopped"


# -- a restart that fails while the supervisor stops --------------------------------------------


def test_a_restart_that_fails_while_the_supervisor_stops_does_not_start_the_child_after_the_stop(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    """A restart whose `setup` raises reports the failure as the child's exit. When
    `stop()` was queued meanwhile, that report is about a child the stop already put down
    for good: the child must stay stopped (OTP: a terminating supervisor restarts nothing),
    not be started once more after `stop()` returned, unsupervised."""
    name = f"a-{uid}"
    runs: list[int] = []
    restarting, stop_queued = threading.Event(), threading.Event()

    def setup(_: rr.ResourceRegistrar) -> None:
        runs.append(1)
        if len(runs) == 2:  # the restart: fails once the owner's stop() is queued
            restarting.set()
            assert stop_queued.wait(10.0)
            raise RuntimeError("device gone")

    sup = supervisors([rr.ManagerSpec(name, setup)]).start()
    mailbox = sup._node._mailbox  # (the supervisor's thread: its stop is queued there)
    submit = mailbox.submit

    def submit_and_tell(task: Any, **kwargs: Any) -> bool:
        queued = submit(task, **kwargs)
        if threading.current_thread().name == "stopper":
            stop_queued.set()
        return queued

    mailbox.submit = submit_and_tell  # type: ignore[method-assign]
    crash(sup, name)
    assert restarting.wait(10.0)
    stopper = threading.Thread(target=sup.stop, name="stopper")
    stopper.start()
    stopper.join(30.0)

    assert (False, 2, "stopped") == (stopper.is_alive(), len(runs), sup.child(name).state)


# -- RestartIntensity: the intensity window on an injected clock (pure) ---------------------------


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def test_intensity_allows_max_restarts_within_the_period_and_not_one_more(
    clock: FakeClock,
) -> None:
    intensity = RestartIntensity(max_restarts=3, period=5.0, clock=clock)

    assert [True, True, True, False] == [intensity.add() for _ in range(4)]


def test_restarts_older_than_the_period_no_longer_count(clock: FakeClock) -> None:
    intensity = RestartIntensity(max_restarts=2, period=5.0, clock=clock)
    intensity.add()
    intensity.add()
    clock.now += 5.0

    assert (True, 1) == (intensity.add(), intensity.recent)


def test_zero_max_restarts_gives_up_at_the_first_crash(clock: FakeClock) -> None:
    assert not RestartIntensity(max_restarts=0, period=5.0, clock=clock).add()


# -- intensity ------------------------------------------------------------------------------------


def test_one_crash_counts_once_against_the_intensity_under_one_for_all(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    names = [f"{n}-{uid}" for n in "abc"]
    sup = supervisors(
        [rr.ManagerSpec(n) for n in names],
        strategy="one_for_all",
        max_restarts=2,
        clock=FakeClock(),
    ).start()
    for _ in range(2):  # two crashes: two restarts, within max_restarts=2
        crash(sup, names[0])
        for name in names:
            sup.wait_restarted(name, timeout=5.0)

    assert (None, [2, 2, 2]) == (sup.gave_up, [i.restarts for i in sup.which_children()])


def test_a_supervisor_that_gives_up_stops_its_children_in_reverse_start_order(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    log_provider: tuple[rr.ResourceRegistrar, list[str]],
) -> None:
    provider, events = log_provider
    a, b, c, d = f"a-{uid}", f"b-{uid}", f"c-{uid}", f"d-{uid}"
    setup = logging_consumer(provider.name, events)
    sup = supervisors(
        [rr.ManagerSpec(n, setup) for n in (a, b, c, d)], max_restarts=0, clock=FakeClock()
    ).start()
    del events[:]
    crash(sup, b)
    with pytest.raises(rr.SupervisorGaveUpError, match="more than 0 restart"):
        sup.wait_restarted(a, timeout=5.0)  # a stops last: settled only once all stopped

    stops = [e for e in events if e != f"unload {b}"]  # b's own id is released by death watch
    assert [f"unload {d}", f"unload {c}", f"unload {a}"] == stops


def test_waiting_on_the_crashed_child_of_a_supervisor_that_gives_up_raises_the_give_up(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    names = [f"{n}-{uid}" for n in "abcd"]
    sup = supervisors([rr.ManagerSpec(n) for n in names], max_restarts=0, clock=FakeClock())
    sup.start()
    crash(sup, names[1])  # a sibling started before it is stopped after it

    with pytest.raises(rr.SupervisorGaveUpError, match="more than 0 restart"):
        sup.wait_restarted(names[1], timeout=5.0)


def test_a_nested_supervisor_counts_its_intensity_on_the_injected_clock(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    x, inner = f"x-{uid}", f"inner-{uid}"
    clock = FakeClock()
    spec = rr.SupervisorSpec(inner, (rr.ManagerSpec(x),), max_restarts=1, period=5.0)
    sup = supervisors([spec], clock=clock).start()
    for _ in range(3):  # one crash per (fake) 6 s: never two within the inner period
        crash(sup, x)
        sup.wait_restarted(x, timeout=5.0)
        clock.now += 6.0

    assert (0, 3) == (sup.child(inner).restarts, sup.child(x).restarts)


def test_a_nested_supervisors_backoff_goes_through_the_injected_timer(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    x, inner = f"x-{uid}", f"inner-{uid}"
    timer = ManualTimer()
    spec = rr.SupervisorSpec(
        inner, (rr.ManagerSpec(x),), backoff=rr.Backoff(initial=0.5, jitter=0.0)
    )
    sup = supervisors([spec], clock=FakeClock(), timer=timer).start()
    crash(sup, x)

    assert timer.wait_scheduled(1)
    assert ([0.5], "restarting") == (timer.delays, sup.child(x).state)
    timer.fire()
    assert 1 == sup.wait_restarted(x, timeout=5.0).restarts


def test_the_timers_of_backoff_restarts_that_ran_are_not_kept(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    """A flaky manager restarted after a backoff, within the intensity, for months: each
    restart's timer (a `threading.Timer` by default: a thread object, its locks, the
    restart it posts) must be let go once it ran, not kept until the supervisor stops."""
    name = f"a-{uid}"
    clock, timer = FakeClock(), ManualTimer()
    sup = supervisors(
        [rr.ManagerSpec(name, echo_setup)],
        backoff=rr.Backoff(initial=1.0),
        clock=clock,
        timer=timer,
    ).start()
    for crashes in range(1, 6):
        crash(sup, name)
        assert timer.wait_scheduled(crashes)
        timer.fire()
        sup.wait_restarted(name, timeout=5.0)
        clock.now += 10.0  # out of the intensity window: it never gives up

    assert len(sup._node.restarts._timers) <= 1


# -- backoff: the injected jitter -----------------------------------------------------------------


@pytest.mark.parametrize(("random", "delay"), [(0.0, 0.5), (0.999999, 1.5)])
def test_the_supervisor_spreads_backoff_delays_with_its_injected_random(
    supervisors: Callable[..., rr.Supervisor], uid: str, random: float, delay: float
) -> None:
    name = f"a-{uid}"
    timer = ManualTimer()
    backoff = rr.Backoff(initial=1.0, factor=2.0, max=10.0, jitter=0.5)
    sup = supervisors(
        [rr.ManagerSpec(name)],
        backoff=backoff,
        timer=timer,
        random=lambda: random,
        clock=FakeClock(),
    ).start()
    crash(sup, name)

    assert timer.wait_scheduled(1)
    assert delay == pytest.approx(timer.delays[0], abs=1e-5)


def _name(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


class SensorError(Exception):
    """An application exception that knows nothing of rr_actors."""


class TestWhatARestartGivesBack:
    """What a restart must give back, clause by clause (rules 11, 15 and 16).

    Each test here covers a clause that a mutation audit found unguarded: breaking it failed
    no other test.

    - Rule 15: a backup that cannot be read raises `CatalogCorruptError` naming the file in
      its message (not only in its `path` attribute).
    - Rules 12 and 16, the consumer's side: a consumer registrar killed after its provider
      answered a call, but before it committed the answer, leaves a pending client record in
      its backup while the provider holds the consumer id. The death watch does not release
      a consumer that will be restarted, so the restarted registrar must give that id back;
      otherwise the resource leaks at the provider for good.
    - Rule 11: `set_status_callback` re-attaches a callback to a query restored after a
      restart, and statuses reach it.
    - Rules 4 and 16 (from a review): a sub-call that a failed load's thread sends after the
      failure has no owner; a durable agent that crashes before its answer gives it back
      after the restart, and so does a restart that finds a dependency whose resource is
      gone.
    """

    def test_catalog_corrupt_error_names_the_file_in_its_message(self, tmp_path: Path) -> None:
        path = tmp_path / "garbage.db"
        path.write_bytes(b"this is not an SQLite database, not at all" * 100)

        with pytest.raises(rr.CatalogCorruptError) as raised:
            rr.ResourceRegistrar.start(rr.RegistrarConfig(name=_name("P"), backup_path=path))

        assert str(path) in str(raised.value)

    def test_a_restarted_consumer_gives_back_an_id_its_provider_answered_but_it_never_committed(
        self,
        tmp_path: Path,
    ) -> None:
        path = tmp_path / "consumer.db"
        unloads: list[Any] = []
        unloaded = threading.Event()

        def unload(request: Any, _response: Any) -> None:
            unloads.append(request)
            unloaded.set()

        provider = rr.ResourceRegistrar.start(_name("P"))
        consumer_config = rr.RegistrarConfig(name=_name("C"), backup_path=path, save_on_modify=True)
        consumer = rr.ResourceRegistrar.start(consumer_config)
        restarted: rr.ResourceRegistrar | None = None
        with expect_restart(consumer.name):  # as a supervisor does: no death watch
            try:
                provider.register_server("leaf", load=lambda r: {"pid": r}, unload=unload)
                query = consumer.call(provider.name, "leaf", "camera", timeout=5)
                testing.crash(consumer)
                assert [query.id] == [
                    q.id for q in provider.server_queries("leaf")
                ]  # kept: restart
                # The kill came after the provider answered and before the consumer committed the
                # answer: its backup holds the record as written before the load went out.
                store = SqliteStore.open(path)
                try:
                    pending = ClientRecord(query.with_response(None), None, loaded=False)
                    store.write(Changes({}, {query.id: pending}))
                finally:
                    store.close(erase=False)
                assert [False] == [c.loaded for c in read_backup(path).clients]

                restarted = rr.ResourceRegistrar.start(consumer_config)

                assert unloaded.wait(5), "the provider still holds the id of the lost call"
                assert (["camera"], [], []) == (
                    unloads,
                    provider.server_queries("leaf"),
                    restarted.client_queries(),
                )
            finally:
                if restarted is not None:
                    restarted.stop()
                provider.stop()

    def test_set_status_callback_reattaches_a_callback_to_a_query_restored_after_a_restart(
        self,
        tmp_path: Path,
    ) -> None:
        """Rule 11: after a restart the consumer re-attaches its callback; status reaches it."""
        path = tmp_path / "consumer.db"
        updates: list[Any] = []
        got = threading.Event()

        def on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
            updates.append((query.id, update.query_id, update.status))
            got.set()

        provider = rr.ResourceRegistrar.start(_name("P"))
        consumer_config = rr.RegistrarConfig(name=_name("C"), backup_path=path, save_on_modify=True)
        consumer = rr.ResourceRegistrar.start(consumer_config)
        restarted: rr.ResourceRegistrar | None = None
        with expect_restart(consumer.name):
            try:
                provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
                query = consumer.call(provider.name, "leaf", "camera", timeout=5)
                testing.crash(consumer)
                restarted = rr.ResourceRegistrar.start(consumer_config)

                restarted.set_status_callback(query.id, on_status)
                provider.send_status(query.id, rr.Status.ERROR, "lost", timeout=5)

                assert got.wait(5)
                assert [(query.id, query.id, rr.Status.ERROR)] == updates
            finally:
                if restarted is not None:
                    restarted.stop()
                provider.stop()

    def test_a_sub_call_written_down_after_its_load_failed_is_given_back_after_a_crash(
        self,
        tmp_path: Path,
    ) -> None:
        # A durable agent writes a call down before sending it. A sub-call that goes out
        # after its load failed has no owner any more: a crash before its answer must still
        # leave the restarted agent able to give the id back (rules 4 and 16).
        config = rr.RegistrarConfig(
            name=_name("A"), backup_path=tmp_path / "a.db", save_on_modify=True
        )
        provider = rr.ResourceRegistrar.start(_name("P"))
        agent = rr.ResourceRegistrar.start(config)
        consumer = rr.ResourceRegistrar.start(_name("C"))
        restarted: rr.ResourceRegistrar | None = None
        with expect_restart(config.name):  # as a supervisor does: no death watch
            failed, started, gate, unloaded = (threading.Event() for _ in range(4))
            pool = ThreadPoolExecutor(1)
            try:
                leaf = GatedLoad(gate, started)
                provider.register_server("leaf", load=leaf, unload=lambda r, s: unloaded.set())

                def sub_call(request: Any) -> rr.Query:
                    assert failed.wait(10)
                    return agent.call(provider.name, "leaf", request, timeout=10)

                def composite(request: Any) -> Any:
                    pool.submit(contextvars.copy_context().run, sub_call, request)
                    raise SensorError("failed before its sub-call went out")

                agent.register_server("composite", load=composite, unload=lambda r, s: None)
                with pytest.raises(rr.ResourceLoadError):
                    consumer.call(agent.name, "composite", "x")
                failed.set()
                assert started.wait(10)  # the sub-call is at the provider: written down before
                agent.client_queries()  # the agent handled (and committed) what came before
                testing.crash(agent)

                restarted = rr.ResourceRegistrar.start(config)
                gate.set()

                assert unloaded.wait(10), "the provider still holds the sub-call's id"
                assert [] == provider.server_queries("leaf")
                assert ((), ()) == (
                    catalog_snapshot(restarted).resources,
                    catalog_snapshot(restarted).clients,
                )
            finally:
                gate.set()
                failed.set()
                pool.shutdown()
                for registrar in (consumer, restarted, provider):
                    if registrar is not None:
                        registrar.stop()

    def test_a_restart_gives_back_a_dependency_whose_resource_is_gone(self, tmp_path: Path) -> None:
        # A backup may hold a dependency whose resource is not there (written by an older
        # version, which recorded a sub-call that outlived its failed load): nothing else
        # would ever release it, so the restart gives it back at its provider.
        path = tmp_path / "a.db"
        config = rr.RegistrarConfig(name=_name("A"), backup_path=path, save_on_modify=True)
        provider = rr.ResourceRegistrar.start(_name("P"))
        agent = rr.ResourceRegistrar.start(config)
        restarted: rr.ResourceRegistrar | None = None
        with expect_restart(config.name):
            unloaded = threading.Event()
            try:
                provider.register_server(
                    "leaf", load=lambda r: r, unload=lambda r, s: unloaded.set()
                )
                query = agent.call(provider.name, "leaf", "camera", timeout=5)
                testing.crash(agent)
                with contextlib.closing(sqlite3.connect(tmp_path / "a.db")) as db, db:
                    db.execute(
                        "UPDATE clients SET parent = 'a-resource-that-is-gone' WHERE query_id = ?",
                        (query.id,),
                    )
                assert ["a-resource-that-is-gone"] == [c.parent for c in read_backup(path).clients]

                restarted = rr.ResourceRegistrar.start(config)

                assert unloaded.wait(5), "the provider still holds the orphaned dependency"
                assert [] == provider.server_queries("leaf")
                assert () == catalog_snapshot(restarted).clients
            finally:
                for registrar in (restarted, provider):
                    if registrar is not None:
                        registrar.stop()
