"""Where rr_actors' supervisor used to depart from Erlang/OTP's (issue 16), case by case.

Ported from the ideas of OTP's `supervisor_SUITE`: a SIGTERM to a manager process is
OTP's `shutdown` (a clean exit for a `transient` child, as for systemd's `on-failure`); a
supervisor that gives up exits with `shutdown`; a give-up is reported once the tree has
settled; a group restart (one_for_all, rest_for_one) brings back a `transient` child that
had exited normally. Crashes are real: SIGKILL/SIGTERM for processes,
`rr_actors.testing.crash` for thread managers. Waits are bounded and event-driven.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects, start_forkserver
from tests.support.supervising import FakeClock, crash, echo_setup, pid_of, process

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
