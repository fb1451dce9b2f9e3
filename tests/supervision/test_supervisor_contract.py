"""Supervisor behaviours that no other test pinned down (found by a mutation audit).

Each test here fails when one clause of the supervisor's contract (issue 4) is broken:
the order siblings stop and restart in, a permanent child after a normal exit, one crash
counting once, the order of a give-up, the nested supervisor's injected clock and timer,
`count_children`, the spec's `shutdown`, the injected jitter, the heartbeat of a stuck
registrar and its `heartbeat_timeout`, the death watch at every provider, and no orphans
when a stuck manager's owner is killed.

Waits are bounded and event-driven (events, `wait_restarted`, a manual timer, pidfds);
managers that must be processes are real processes, killed with real signals.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects, actor_ref, start_forkserver
from tests.support.supervising import (
    FakeClock,
    ManualTimer,
    alive,
    crash,
    echo_setup,
    killed_owner,
    linux_trick,
    process,
    sigkill,
    wait_gone,
)

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


# -- helpers ----------------------------------------------------------------------------------


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


@pytest.fixture
def log_provider(uid: str) -> Iterator[tuple[rr.ResourceRegistrar, list[str]]]:
    """An unsupervised provider `log-<uid>` whose server "log" records `unload <name>`."""
    events: list[str] = []
    provider = rr.ResourceRegistrar.start(f"log-{uid}")
    provider.register_server(
        "log", load=lambda r: r, unload=lambda r, _: events.append(f"unload {r}")
    )
    yield provider, events
    provider.stop()


def logging_consumer(provider: str, events: list[str]) -> Callable[[rr.ResourceRegistrar], None]:
    """A thread manager's setup: note `start <name>`, then load `<name>` from `provider`.

    The manager's clean stop unloads what it holds, so the provider notes `unload <name>`
    when (and in the order that) the supervisor stops it.
    """

    def setup(reg: rr.ResourceRegistrar) -> None:
        events.append(f"start {reg.name}")
        reg.call(provider, "log", reg.name)

    return setup


# -- ordered start, reverse-ordered stop ----------------------------------------------------------


def test_a_failed_start_stops_the_children_already_started_in_reverse_order(
    supervisors: Callable[..., rr.Supervisor],
    uid: str,
    log_provider: tuple[rr.ResourceRegistrar, list[str]],
) -> None:
    provider, events = log_provider
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"

    def broken(_: rr.ResourceRegistrar) -> None:
        raise ValueError("no camera")

    setup = logging_consumer(provider.name, events)
    sup = supervisors(
        [rr.ManagerSpec(a, setup), rr.ManagerSpec(b, setup), rr.ManagerSpec(c, broken)]
    )

    with pytest.raises(rr.SupervisorGaveUpError, match="no camera"):
        sup.start()
    assert [f"start {a}", f"start {b}", f"unload {b}", f"unload {a}"] == events


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


# -- introspection --------------------------------------------------------------------------------


def test_count_children_counts_only_running_children_as_active_and_kinds_apart(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    t = f"t-{uid}"
    inner = rr.SupervisorSpec(f"inner-{uid}", (rr.ManagerSpec(f"x-{uid}"),))
    sup = supervisors(
        [rr.ManagerSpec(f"a-{uid}"), rr.ManagerSpec(t, restart="temporary"), inner],
        clock=FakeClock(),
    ).start()
    crash(sup, t)
    with pytest.raises(rr.RegistrarUnavailableError):
        sup.wait_restarted(t, timeout=5.0)  # returns once t settled as exited

    assert rr.ChildCounts(specs=3, active=2, supervisors=1, managers=2) == sup.count_children()


def test_wait_restarted_waits_for_the_restart_count_it_is_given(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([rr.ManagerSpec(name)], clock=FakeClock()).start()
    for _ in range(2):
        crash(sup, name)
        sup.wait_restarted(name, timeout=5.0)

    # restarts=1 was reached long ago: no wait for a third restart
    assert 2 == sup.wait_restarted(name, timeout=2.0, restarts=1).restarts
    with pytest.raises(rr.CallTimeoutError, match="2 restarts"):
        sup.wait_restarted(name, timeout=0.2, restarts=3)  # there were only two


# -- shutdown timeout, then kill ------------------------------------------------------------------


def test_a_process_manager_is_killed_once_its_own_shutdown_ran_out(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"erm-{uid}"
    sup = supervisors([process(name, heartbeat=None, shutdown=0.5)]).start()
    pid = sup.child(name).pid
    assert pid is not None  # never os.kill(0, ...): that signals this test's process group
    os.kill(pid, signal.SIGSTOP)  # it cannot stop cleanly
    started = time.monotonic()
    sup.stop()
    took = time.monotonic() - started

    assert ("killed", False) == ((sup.child(name).last_exit or "")[:6], alive(pid))
    assert took < 4.0, f"stop took {took:.2f} s with shutdown=0.5"


def test_a_thread_manager_stuck_past_its_shutdown_is_told_to_crash(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    release = threading.Event()

    def setup(reg: rr.ResourceRegistrar) -> None:
        reg.register_server("res", load=lambda r: r, unload=lambda r, _: release.wait(30.0))

    sup = supervisors([rr.ManagerSpec(name, setup, shutdown=0.5)], clock=FakeClock()).start()
    registrar = sup.run_in(name, lambda r: r)
    sup.run_in(name, lambda reg: reg.call(name, "res", "x"))  # its clean stop must unload it
    try:
        sup.stop()
    finally:
        release.set()
    assert actor_ref(registrar).actor_stopped.wait(10.0)

    assert "killed" == (sup.child(name).last_exit or "")[:6]
    with pytest.raises(rr.RegistrarUnavailableError):  # it died; a clean stop would say so
        registrar.call(name, "res", "y", timeout=5.0)


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


# -- death watch: every provider ------------------------------------------------------------------


def unload_flag(unloaded: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("res", load=lambda r: r, unload=lambda r, s: unloaded.set())

    return setup


def consumer_of(*providers: str) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        if not registrar.client_queries():
            for provider in providers:
                registrar.call(provider, "res", "camera", timeout=10.0)

    return setup


def test_a_temporary_consumer_that_dies_has_its_ids_released_at_every_provider(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    p1, p2, c = f"p1-{uid}", f"p2-{uid}", f"c-{uid}"
    unloaded1, unloaded2 = process_helpers.event(), process_helpers.event()
    sup = supervisors(
        [
            process(p1, unload_flag(unloaded1)),
            process(p2, unload_flag(unloaded2)),
            process(c, consumer_of(p1, p2), restart="temporary"),
        ]
    ).start()
    sigkill(sup, c)

    assert [True, True] == [unloaded1.wait(10.0), unloaded2.wait(10.0)]
    held = [sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0) for p in (p1, p2)]
    assert [[], []] == held


def test_a_temporary_consumer_that_dies_is_released_at_a_provider_in_a_nested_supervisor(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    p, c = f"p-{uid}", f"c-{uid}"
    unloaded = process_helpers.event()
    inner = rr.SupervisorSpec(f"inner-{uid}", (process(p, unload_flag(unloaded)),))
    sup = supervisors([inner, process(c, consumer_of(p), restart="temporary")]).start()
    sigkill(sup, c)

    assert unloaded.wait(10.0)
    assert [] == sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0)


def test_a_consumer_process_whose_supervisor_gave_up_for_good_is_released_at_its_provider(
    supervisors: Callable[..., rr.Supervisor], uid: str, process_helpers: SharedObjects
) -> None:
    p, c = f"p-{uid}", f"c-{uid}"
    unloaded = process_helpers.event()
    inner = rr.SupervisorSpec(
        f"inner-{uid}", (process(c, consumer_of(p)),), max_restarts=0, restart="temporary"
    )
    sup = supervisors([process(p, unload_flag(unloaded)), inner]).start()
    sigkill(sup, c)  # c is permanent, but its supervisor gives up for good

    assert unloaded.wait(10.0)
    assert [] == sup.run_in(p, lambda r: r.server_queries("res"), timeout=10.0)


# -- no orphans -----------------------------------------------------------------------------------


@linux_trick
def test_killing_the_main_process_also_ends_a_manager_too_stuck_to_read_its_pipe(
    uid: str, tmp_path: Path
) -> None:
    pids: list[int] = []
    try:
        with killed_owner(uid, tmp_path, heartbeat=False) as pids:
            os.kill(pids[0], signal.SIGSTOP)  # stuck: it will never see EOF on its pipe

        assert [] == wait_gone(pids)
    finally:
        for pid in pids:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
