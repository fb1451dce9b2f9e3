"""Pools (`rr_actors._supervision.pool`): a nested supervisor in an OS process of its own,
`SupervisorSpec(isolation="process")`, its thread managers restarted alone inside it, the
process one child of its parent.

Real processes and real SIGKILLs; a crash inside a pool is `rr_actors.testing.crash` run
there (`run_in`); what happens inside a pool is seen from its events.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events, testing
from rr_actors.config import Steps
from tests.support.heard import Heard
from tests.support.waiting import wait_for

BOUND = 30.0  # seconds: generous, the machine is loaded


def echo_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)


def fifo_setup(registrar: rr.ResourceRegistrar) -> None:
    """A server whose load tells a FIFO it started (the request is its path), then hangs."""

    def load(path: str) -> None:
        with open(path, "w") as fifo:
            fifo.write("x")
        threading.Event().wait()

    registrar.register_server("hang", load=load, unload=lambda r, s: None)


def unique_setup(registrar: rr.ResourceRegistrar) -> None:
    """A server whose every load answers a value of its own (equal requests shared: one)."""
    registrar.register_server("echo", load=lambda r: uuid.uuid4().hex, unload=lambda r, s: None)


def never_shared(_stored: Any, _request: Any, _loading: Any, _failed: Any) -> bool:
    return False


def pool(name: str, size: int, setup: Any = echo_setup, **kwargs: Any) -> rr.SupervisorSpec:
    managers = tuple(rr.ManagerSpec(f"{name}-m{i}", setup) for i in range(size))
    return rr.SupervisorSpec(name, managers, isolation="process", **kwargs)


def served_ids(sup: rr.Supervisor, name: str) -> list[str]:
    """The query ids manager `name` serves on "echo", asked where it runs."""
    ids: list[str] = sup.run_in(
        name, lambda r: sorted(q.id for q in r.server_queries("echo")), timeout=BOUND
    )
    return ids


@pytest.fixture
def state(tmp_path: Path) -> str:
    return str(tmp_path / "state")


@pytest.fixture
def tree(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str
) -> Iterator[tuple[rr.Supervisor, Heard, str]]:
    """Two pools `a<uid>` and `b<uid>` of two echo managers each, started, watched."""
    sup = supervisors([pool(f"a{uid}", 2), pool(f"b{uid}", 2)], state_dir=state)
    seen = Heard()
    with sup.subscribe(seen):
        sup.start()
        yield sup, seen, uid


def test_a_pool_is_one_supervisor_child_in_its_own_process_and_its_managers_share_its_pid(
    tree: tuple[rr.Supervisor, Heard, str],
) -> None:
    sup, _, uid = tree
    a, b = sup.which_children()
    assert ("supervisor", "process", "running") == (a.kind, a.isolation, a.state)
    assert a.pid is not None
    assert b.pid is not None
    assert len({os.getpid(), a.pid, b.pid}) == 3
    assert [a.pid, a.pid, b.pid] == [
        sup.child(n).pid for n in (f"a{uid}-m0", f"a{uid}-m1", f"b{uid}-m0")
    ]
    assert a.pid == sup.run_in(f"a{uid}-m1", lambda r: os.getpid(), timeout=BOUND)


def test_a_pool_s_managers_serve_calls_from_this_process_and_from_another_pool(
    tree: tuple[rr.Supervisor, Heard, str],
) -> None:
    sup, _, uid = tree
    app = sup.registrar(f"app{uid}")
    assert {"x": 1} == app.call(f"a{uid}-m1", "echo", {"x": 1}).response
    target = f"a{uid}-m0"
    answer = sup.run_in(  # from a manager of the other pool, in its process
        f"b{uid}-m1", lambda r: r.call(target, "echo", 2).response, timeout=BOUND
    )
    assert 2 == answer


def test_a_supervisors_steps_reach_the_managers_of_its_pools(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    """`Supervisor(steps=)` is the tree's: a pool's managers, in a process of their own,
    run them too (they ran their own: the pool's supervisor was made without them)."""
    name = f"s{uid}-m0"
    sup = supervisors([pool(f"s{uid}", 1, unique_setup)], steps=Steps(shares=never_shared))
    sup.start()
    app = sup.registrar(f"app-{uid}")

    first = app.call(name, "echo", "x", timeout=BOUND).response
    second = app.call(name, "echo", "x", timeout=BOUND).response

    assert first != second  # an equal request loaded again: the tree's `shares` said so


def test_a_crash_of_one_manager_in_a_pool_restarts_only_that_one_with_its_catalog(
    tree: tuple[rr.Supervisor, Heard, str],
) -> None:
    sup, seen, uid = tree
    name, sibling = f"a{uid}-m1", f"a{uid}-m0"
    app = sup.registrar(f"app{uid}")
    held = app.call(name, "echo", "kept")
    pool_pid = sup.child(f"a{uid}").pid

    with contextlib.suppress(rr.RegistrarUnavailableError):  # (the answer may go with it)
        sup.run_in(name, testing.crash, timeout=BOUND)  # its registrar actor dies, in the pool

    assert seen.wait(lambda e: isinstance(e, events.ChildRestarted) and e.child == name)
    (restarted,) = seen.of(events.ChildRestarted, child=name)
    assert (f"a{uid}", pool_pid) == (restarted.supervisor, restarted.pid)
    assert [held.id] == served_ids(sup, name)  # its catalog, restored
    assert pool_pid == sup.child(f"a{uid}").pid  # the pool's process lives on
    assert [] == seen.of(events.ChildExited, child=sibling)
    assert [] == seen.of(events.ChildExited, child=f"a{uid}")
    assert "kept" == app.call(name, "echo", "kept").response


def test_a_restart_inside_a_pool_counts_in_the_parent_s_restarts_of_that_manager_only(
    tree: tuple[rr.Supervisor, Heard, str],
) -> None:
    sup, _, uid = tree
    name, sibling = f"a{uid}-m1", f"a{uid}-m0"
    pool_pid = sup.child(f"a{uid}").pid

    for restarts in (1, 2):
        with contextlib.suppress(rr.RegistrarUnavailableError):  # (the answer may go with it)
            sup.run_in(name, testing.crash, timeout=BOUND)
        info = sup.wait_restarted(name, timeout=BOUND, restarts=restarts)
        assert ("running", restarts, pool_pid) == (info.state, info.restarts, info.pid)

    assert 2 == sup.child(name).restarts
    assert (0, 0) == (sup.child(sibling).restarts, sup.child(f"a{uid}").restarts)


def test_a_hung_thread_manager_in_a_pool_is_detected_and_its_pool_restarted_with_catalogs(
    supervisors: Callable[..., rr.Supervisor],
    state: str,
    uid: str,
    process_helpers: testing.SharedObjects,
) -> None:
    # Its registrar actor blocks (a stuck callback on the actor): the pool's process lives
    # and answers its own heartbeat, so only the pool's watch of each manager sees it. A
    # thread cannot be killed: the pool's process ends and its parent restarts the pool.
    name, sibling = f"h{uid}-m1", f"h{uid}-m0"
    managers = tuple(
        rr.ManagerSpec(n, echo_setup, heartbeat=0.1, heartbeat_timeout=1.0) for n in (sibling, name)
    )
    sup = supervisors(
        [rr.SupervisorSpec(f"h{uid}", managers, isolation="process")], state_dir=state
    )
    seen = Heard()
    gate = process_helpers.event()
    with sup.subscribe(seen):
        sup.start()
        app = sup.registrar(f"app{uid}")
        held = app.call(name, "echo", "kept")
        pool_pid = sup.child(f"h{uid}").pid

        sup.run_in(name, _block_actor(gate), timeout=BOUND)
        try:
            info = sup.wait_restarted(name, timeout=BOUND)
        finally:
            gate.set()

        assert ("running", 1) == (info.state, info.restarts)
        assert info.pid not in (None, pool_pid)
        (exited,) = seen.of(events.ChildExited, child=f"h{uid}")
        assert exited.reason.startswith("hung"), exited.reason
        assert [held.id] == served_ids(sup, name)  # its catalog, restored
        assert "again" == app.call(name, "echo", "again").response
        assert "also" == app.call(sibling, "echo", "also").response


def _block_actor(gate: Any) -> Callable[[rr.ResourceRegistrar], None]:
    """Run in a manager: its registrar actor's thread blocks on `gate` (a stuck registrar)."""

    def block(registrar: rr.ResourceRegistrar) -> None:
        from rr_actors.testing import run_on_actor  # noqa: PLC0415 - runs in the pool

        run_on_actor(registrar, lambda: gate.wait(60))

    return block


def test_a_sigkill_of_a_pool_restarts_only_its_managers_each_restoring_its_catalog(
    tree: tuple[rr.Supervisor, Heard, str],
) -> None:
    sup, seen, uid = tree
    app = sup.registrar(f"app{uid}")
    held = {n: app.call(n, "echo", n).id for n in (f"a{uid}-m0", f"a{uid}-m1", f"b{uid}-m0")}
    other = sup.child(f"b{uid}")
    killed = sup.child(f"a{uid}").pid
    assert killed is not None

    os.kill(killed, signal.SIGKILL)

    assert "still" == app.call(f"b{uid}-m0", "echo", "still").response  # the other pool serves
    for name in (f"a{uid}-m0", f"a{uid}-m1"):
        info = sup.wait_restarted(name, timeout=BOUND)
        assert ("running", 1) == (info.state, info.restarts)
        assert info.pid not in (None, killed)
        assert [held[name]] == served_ids(sup, name)
    assert (other.pid, 0) == (sup.child(f"b{uid}").pid, sup.child(f"b{uid}").restarts)
    assert 0 == sup.child(f"b{uid}-m0").restarts
    assert [] == seen.of(events.ChildExited, child=f"b{uid}")
    (exited,) = seen.of(events.ChildExited, child=f"a{uid}")
    assert "killed by SIGKILL" == exited.reason


def test_a_call_in_flight_to_a_pool_s_manager_fails_at_once_when_its_pool_is_killed(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str, tmp_path: Path
) -> None:
    sup = supervisors([pool(f"h{uid}", 1, fifo_setup)], state_dir=state)
    sup.start()
    app = sup.registrar(f"app{uid}")
    fifo = str(tmp_path / "started")
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
    outcome: list[BaseException] = []
    done = threading.Event()

    def call() -> None:
        try:
            app.call(f"h{uid}-m0", "hang", fifo, timeout=600.0)
        except rr.RrError as exc:
            outcome.append(exc)
        finally:
            done.set()

    caller = threading.Thread(target=call)
    caller.start()
    try:
        assert select.select([reader], [], [], BOUND)[0]  # its load runs, in the pool
        os.kill(sup.child(f"h{uid}").pid or 0, signal.SIGKILL)
        assert done.wait(BOUND)  # long before the call's timeout
    finally:
        os.close(reader)
        caller.join(BOUND)
    assert [rr.RegistrarUnavailableError] == [type(e) for e in outcome]


def test_a_pool_whose_supervisor_gives_up_is_restarted_by_its_parent(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str
) -> None:
    sup = supervisors([pool(f"g{uid}", 2, max_restarts=0)], state_dir=state)
    sup.start()
    first = sup.child(f"g{uid}").pid

    with contextlib.suppress(rr.RegistrarUnavailableError):  # (the process may end first)
        sup.run_in(f"g{uid}-m1", testing.crash, timeout=BOUND)

    info = sup.wait_restarted(f"g{uid}", timeout=BOUND)
    assert ("its supervisor gave up", 1) == (info.last_exit, info.restarts)
    assert info.pid not in (None, first)
    assert 1 == sup.child(f"g{uid}-m0").restarts


@pytest.mark.parametrize("inside", ["manager", "supervisor"])
def test_a_process_child_inside_a_pool_is_refused_in_one_line(inside: str) -> None:
    child: rr.ManagerSpec | rr.SupervisorSpec = (
        rr.ManagerSpec("m", echo_setup, isolation="process")
        if inside == "manager"
        else rr.SupervisorSpec("inner", (rr.ManagerSpec("m"),), isolation="process")
    )
    with pytest.raises(rr.ConfigError) as caught:
        rr.SupervisorSpec("p", (child,), isolation="process")
    message = str(caught.value)
    assert "\n" not in message
    assert "isolation='process' inside supervisor 'p'" in message


def test_a_pool_s_isolation_must_be_thread_or_process() -> None:
    with pytest.raises(rr.ConfigError, match="isolation must be one of"):
        rr.SupervisorSpec("p", (), isolation="silo")  # type: ignore[arg-type]


def test_a_transient_pool_that_gives_up_stays_down_as_otp_s_shutdown(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str
) -> None:
    sup = supervisors([pool(f"t{uid}", 2, max_restarts=0, restart="transient")], state_dir=state)
    seen = Heard()
    with sup.subscribe(seen):
        sup.start()
        with contextlib.suppress(rr.RegistrarUnavailableError):  # (the process may end first)
            sup.run_in(f"t{uid}-m1", testing.crash, timeout=BOUND)

        assert seen.wait(lambda e: isinstance(e, events.ChildExited) and e.child == f"t{uid}")
    with pytest.raises(rr.RegistrarUnavailableError, match="will not be restarted"):
        sup.wait_restarted(f"t{uid}", timeout=BOUND)  # (returns once it is settled)
    info = sup.child(f"t{uid}")
    assert ("exited", "its supervisor gave up", None) == (info.state, info.last_exit, info.pid)
    assert "exited" == sup.child(f"t{uid}-m0").state


def test_a_pool_restarted_with_its_group_stops_its_managers_and_restores_their_catalogs(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str
) -> None:
    solo = rr.ManagerSpec(f"s{uid}", echo_setup, isolation="process")
    sup = supervisors([pool(f"a{uid}", 2), solo], state_dir=state, strategy="one_for_all")
    seen = Heard()
    with sup.subscribe(seen):
        sup.start()
        app = sup.registrar(f"app{uid}")
        held = app.call(f"a{uid}-m1", "echo", "kept")
        first = sup.child(f"a{uid}").pid

        os.kill(sup.child(f"s{uid}").pid or 0, signal.SIGKILL)  # its sibling

        info = sup.wait_restarted(f"a{uid}-m1", timeout=BOUND)
        assert info.pid not in (None, first)
        assert [held.id] == served_ids(sup, f"a{uid}-m1")
        (stopped,) = seen.of(events.ChildExited, child=f"a{uid}")
        assert (True, "shutdown") == (stopped.stopped, stopped.reason)
        assert seen.wait(  # the pool stopped its managers itself, in order, not killed
            lambda e: isinstance(e, events.ChildExited) and e.child == f"a{uid}-m0"
        )


def unsaved(tmp_path: Path, name: str) -> rr.RegistrarConfig:
    """A backup that keeps nothing done after the start (flushed once an hour)."""
    return rr.RegistrarConfig(
        name=name, backup_path=str(tmp_path / f"{name}.db"), save_interval=3600.0
    )


def held_at(sup: rr.Supervisor, holder: str) -> list[str]:
    """The query ids registrar `holder` holds, asked where it runs."""
    ids: list[str] = sup.run_in(
        holder, lambda r: sorted(q.id for q in r.client_queries()), timeout=BOUND
    )
    return ids


def none_held(sup: rr.Supervisor, holder: str) -> bool:
    """Whether `holder` comes to hold no id within the bound."""
    return wait_for(lambda: [] == held_at(sup, holder), BOUND)


def test_a_holder_in_another_process_hears_a_pool_s_manager_restart_without_its_ids(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str, tmp_path: Path
) -> None:
    # (a pool's supervisor restarts its manager inside the pool's process: its
    # announcement went to that process only, and the holder kept the id for good)
    provider, holder = f"p{uid}-m0", f"h{uid}"
    inner = rr.ManagerSpec(provider, echo_setup, config=unsaved(tmp_path, provider))
    sup = supervisors(
        [
            rr.SupervisorSpec(f"p{uid}", (inner,), isolation="process"),
            rr.ManagerSpec(holder, echo_setup, isolation="process"),
        ],
        state_dir=state,
    )
    seen = Heard()
    with sup.subscribe(seen):
        sup.start()
        sup.run_in(holder, lambda r: r.call(provider, "echo", "camera").id, timeout=BOUND)
        assert 1 == len(held_at(sup, holder))

        with contextlib.suppress(rr.RegistrarUnavailableError):
            sup.run_in(provider, testing.crash, timeout=BOUND)  # restored without the id
        assert seen.wait(lambda e: isinstance(e, events.ChildRestarted) and e.child == provider)

        assert none_held(sup, holder)
        assert [] == served_ids(sup, provider)


def test_a_pool_s_manager_hears_a_process_manager_restart_without_its_ids(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str, tmp_path: Path
) -> None:
    provider, holder = f"prov{uid}", f"q{uid}-m0"
    sup = supervisors(
        [
            rr.ManagerSpec(
                provider, echo_setup, isolation="process", config=unsaved(tmp_path, provider)
            ),
            pool(f"q{uid}", 1),
        ],
        state_dir=state,
    )
    with sup:
        sup.run_in(holder, lambda r: r.call(provider, "echo", "camera").id, timeout=BOUND)
        assert 1 == len(held_at(sup, holder))
        killed = sup.child(provider).pid

        os.kill(killed or 0, signal.SIGKILL)  # restored without the id

        assert sup.wait_restarted(provider, timeout=BOUND).pid not in (None, killed)
        assert none_held(sup, holder)


def sockets_of(pid: int) -> int:
    """The sockets process `pid` has open (`/proc/<pid>/fd`)."""
    count = 0
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):  # (closed meanwhile)
            count += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
    return count


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="reads /proc (Linux)")
def test_a_pool_s_manager_restart_links_its_process_to_no_registrar_it_has_no_business_with(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str, tmp_path: Path
) -> None:
    # (its pool's process told every registrar of the system itself, one link each:
    # the holder, named last, is told last)
    provider, holder = f"p{uid}-m0", f"z{uid}"
    inner = rr.ManagerSpec(provider, echo_setup, config=unsaved(tmp_path, provider))
    bystanders = [
        rr.ManagerSpec(f"b{uid}-{i}", echo_setup, isolation="process", heartbeat=None)
        for i in range(6)
    ]
    sup = supervisors(
        [
            rr.SupervisorSpec(f"p{uid}", (inner,), isolation="process"),
            *bystanders,
            rr.ManagerSpec(holder, echo_setup, isolation="process"),
        ],
        state_dir=state,
    )
    with sup:
        sup.run_in(holder, lambda r: r.call(provider, "echo", "camera").id, timeout=BOUND)
        pool_pid = sup.child(f"p{uid}").pid or 0
        before = sockets_of(pool_pid)

        with contextlib.suppress(rr.RegistrarUnavailableError):
            sup.run_in(provider, testing.crash, timeout=BOUND)  # restored without the id

        assert none_held(sup, holder)
        assert sockets_of(pool_pid) < before + len(bystanders), before


def test_a_pool_s_manager_hears_the_death_watch_of_a_provider_gone_for_good(
    supervisors: Callable[..., rr.Supervisor], state: str, uid: str
) -> None:
    provider, holder = f"gone{uid}", f"w{uid}-m0"
    sup = supervisors(
        [
            rr.ManagerSpec(provider, echo_setup, isolation="process", restart="temporary"),
            pool(f"w{uid}", 1),
        ],
        state_dir=state,
    )
    with sup:
        sup.run_in(holder, lambda r: r.call(provider, "echo", "camera").id, timeout=BOUND)
        assert 1 == len(held_at(sup, holder))

        os.kill(sup.child(provider).pid or 0, signal.SIGKILL)  # nobody restarts it

        assert none_held(sup, holder)
