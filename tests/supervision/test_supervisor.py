"""The supervisor (`rr_actors._supervision.supervisor`) with thread managers: strategies,
restart types, intensity, backoff, and what its methods refuse.

No processes here: managers run in this process (a crash is `rr_actors.testing.crash`),
time is an injected clock and backoff delays go to a manual timer, so intensity and
backoff are tested without waiting for real time.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
import rr_actors_lab.observe as _lab_observe
from rr_actors import Supervisor, testing
from rr_actors.config import Backoff, ManagerSpec, SupervisorSpec
from tests.supervision.conftest import CallWithRetry
from tests.support.heard import events_of
from tests.support.supervising import (
    FakeClock,
    ManualTimer,
    crash,
    echo_setup,
)
from tests.support.waiting import wait_for


@pytest.fixture
def supervisors() -> Iterator[Callable[..., Supervisor]]:
    """Make supervisors (injected clock by default); every one is stopped at teardown."""
    made: list[Supervisor] = []

    def make(children: list[Any], **kwargs: Any) -> Supervisor:
        kwargs.setdefault("clock", FakeClock())
        sup = Supervisor(children, **kwargs)
        made.append(sup)
        return sup

    yield make
    for sup in reversed(made):
        sup.stop()


def handle(sup: Supervisor, name: str) -> rr.ResourceRegistrar:
    """The registrar of thread manager `name` (its current incarnation)."""
    registrar: rr.ResourceRegistrar = sup.run_in(name, lambda r: r)
    return registrar


def once_waiting(sup: Supervisor, monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """An event set when something (`call_with_retry`) starts to wait for a restart."""
    waiting = threading.Event()
    restart_wait = sup._restart_wait  # (the steps of every wait for a restart)

    def restart_wait_and_tell(*args: Any) -> Any:
        waiting.set()
        return restart_wait(*args)

    monkeypatch.setattr(sup, "_restart_wait", restart_wait_and_tell)
    return waiting


def recording_provider(
    unloaded: threading.Event,
) -> Callable[[rr.ResourceRegistrar], None]:
    """A setup with server "res" that sets `unloaded` when a resource is unloaded."""

    def setup(reg: rr.ResourceRegistrar) -> None:
        reg.register_server("res", load=lambda r: r, unload=lambda r, _: unloaded.set())

    return setup


def abandon(sup: Supervisor, name: str, query_id: str, origin: str) -> None:
    """What `call_with_retry` does with an id when its wait for a restart ran out."""
    sup._tree.abandon(sup._node, name, query_id, origin)


def restarts(sup: Supervisor) -> dict[str, int]:
    return {info.name: info.restarts for info in sup.which_children()}


# -- specs ----------------------------------------------------------------------------------


def test_a_name_used_twice_in_the_tree_is_a_config_error() -> None:
    inner = SupervisorSpec("inner", (ManagerSpec("erm"),))

    with pytest.raises(rr.ConfigError, match="'erm' is used twice"):
        Supervisor([ManagerSpec("erm"), inner])


def test_an_unknown_strategy_is_a_config_error() -> None:
    with pytest.raises(rr.ConfigError, match="strategy"):
        Supervisor([], strategy="one_for_some")  # type: ignore[arg-type]


def test_an_unknown_durability_is_a_config_error_naming_the_field() -> None:
    with pytest.raises(rr.ConfigError, match=r"^durability must be one of 'process', 'power'"):
        Supervisor([], durability="disk")  # type: ignore[arg-type]


def durabilities(sup: Supervisor, names: list[str]) -> dict[str, tuple[str, bool]]:
    """Each manager's durability, and whether it keeps a backup, asked where it runs."""
    return {
        name: sup.run_in(name, lambda r: (r.config.durability, r.config.backup_path is not None))
        for name in names
    }


def test_the_trees_durability_reaches_thread_process_and_nested_managers(
    supervisors: Callable[..., Supervisor], uid: str, tmp_path: Any
) -> None:
    names = [f"thread-{uid}", f"process-{uid}", f"nested-{uid}"]
    inner = SupervisorSpec(f"inner-{uid}", (ManagerSpec(names[2], isolation="process"),))
    sup = supervisors(
        [ManagerSpec(names[0]), ManagerSpec(names[1], isolation="process"), inner],
        state_dir=tmp_path,
        durability="power",
    )

    with sup:
        found = durabilities(sup, names)

    assert dict.fromkeys(names, ("power", True)) == found


def test_a_spec_with_its_own_config_gets_the_trees_durability_at_least(
    supervisors: Callable[..., Supervisor], uid: str, tmp_path: Any
) -> None:
    # The tree's level is a floor: a config that set other fields (its durability left at
    # the default "process") is raised to a "power" tree's; one that asked for "power" in
    # a "process" tree keeps it.
    names = [f"own-{uid}", f"strong-{uid}"]
    own = rr.RegistrarConfig(name=names[0], backup_path=tmp_path / "own.db", call_timeout=3.0)
    strong = rr.RegistrarConfig(name=names[1], backup_path=tmp_path / "s.db", durability="power")
    power = supervisors([ManagerSpec(names[0], config=own)], durability="power")
    default = supervisors([ManagerSpec(names[1], isolation="process", config=strong)])

    with power, default:
        found = {**durabilities(power, names[:1]), **durabilities(default, names[1:])}

    assert {names[0]: ("power", True), names[1]: ("power", True)} == found


def test_a_consumer_registrar_of_a_power_tree_gets_its_durability(
    supervisors: Callable[..., Supervisor], uid: str, tmp_path: Any
) -> None:
    sup = supervisors([], durability="power")
    config = rr.RegistrarConfig(name=f"app-{uid}", backup_path=tmp_path / "app.db")

    with sup:
        found = sup.registrar(config).config.durability

    assert "power" == found


# -- start, stop, introspection -------------------------------------------------------------


def test_children_start_in_order_and_stop_in_reverse_order(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    released: list[Any] = []
    started: list[str] = []
    a, b, c = f"a-{uid}", f"b-{uid}", f"c-{uid}"

    def provider(reg: rr.ResourceRegistrar) -> None:
        started.append(reg.name)
        reg.register_server("log", load=lambda r: r, unload=lambda r, _: released.append(r))

    def consumer(reg: rr.ResourceRegistrar) -> None:
        started.append(reg.name)
        reg.call(a, "log", reg.name)

    sup = supervisors(
        [ManagerSpec(a, provider), ManagerSpec(b, consumer), ManagerSpec(c, consumer)]
    )
    sup.start()
    sup.stop()

    assert ([a, b, c], [c, b]) == (started, released)


def test_which_children_returns_immutable_snapshots(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    sup = supervisors([ManagerSpec(f"a-{uid}")]).start()
    info = sup.which_children()[0]

    assert (f"a-{uid}", "manager", "thread", "running", None, 0, None) == (
        info.name,
        info.kind,
        info.isolation,
        info.state,
        info.pid,
        info.restarts,
        info.last_exit,
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        info.state = "stopped"  # type: ignore[misc]


def test_count_children_counts_specs_running_supervisors_and_managers(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    inner = SupervisorSpec(f"inner-{uid}", (ManagerSpec(f"x-{uid}"),))
    sup = supervisors([ManagerSpec(f"a-{uid}"), inner]).start()

    assert rr.ChildCounts(specs=2, active=2, supervisors=1, managers=1) == sup.count_children()


def test_a_setup_that_raises_fails_start_and_stops_the_children_already_started(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    a = f"a-{uid}"

    def broken(_: rr.ResourceRegistrar) -> None:
        raise ValueError("no camera")

    sup = supervisors([ManagerSpec(a), ManagerSpec(f"b-{uid}", broken)])

    with pytest.raises(rr.SupervisorGaveUpError, match="no camera") as caught:
        sup.start()
    assert isinstance(caught.value.__cause__, ValueError)
    assert ["stopped", "stopped"] == [i.state for i in sup.which_children()]


def test_with_block_starts_the_children_and_stops_them_on_exit(uid: str) -> None:
    sup = Supervisor([ManagerSpec(f"a-{uid}")])

    with sup:
        running = sup.which_children()[0].state

    assert ("running", "stopped") == (running, sup.which_children()[0].state)


# -- strategies and restart types -----------------------------------------------------------


def three(uid: str, restart: str = "permanent") -> list[ManagerSpec]:
    return [ManagerSpec(f"{n}-{uid}", restart=restart) for n in "abc"]  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("strategy", "restarted"),
    [("one_for_one", "b"), ("one_for_all", "abc"), ("rest_for_one", "bc")],
    ids=[
        "one_for_one_restarts_only_the_crashed_child",
        "one_for_all_restarts_every_child",
        "rest_for_one_restarts_the_crashed_child_and_those_started_after_it",
    ],
)
def test_a_strategy_restarts_its_children_when_b_crashes(
    supervisors: Callable[..., Supervisor], uid: str, strategy: str, restarted: str
) -> None:
    sup = supervisors(three(uid), strategy=strategy).start()
    crash(sup, f"b-{uid}")
    sup.wait_restarted(f"{restarted[-1]}-{uid}", timeout=5.0)

    assert {f"{n}-{uid}": int(n in restarted) for n in "abc"} == restarts(sup)


def test_the_managers_of_a_nested_sibling_being_restarted_are_unavailable_not_stopped(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x, b = f"x-{uid}", f"b-{uid}"
    inner = SupervisorSpec(f"inner-{uid}", (ManagerSpec(x, echo_setup),))
    timer = ManualTimer()
    sup = supervisors(
        [inner, ManagerSpec(b)], strategy="one_for_all", backoff=Backoff(initial=1.0), timer=timer
    ).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, b)
    assert timer.wait_scheduled(1)  # the inner supervisor was stopped; its restart is due

    with pytest.raises(rr.RegistrarUnavailableError):
        app.call(x, "echo", "during", timeout=5)
    timer.fire()
    sup.wait_restarted(x, timeout=5.0)
    assert "after" == app.call(x, "echo", "after", timeout=5).response


def test_a_restarted_thread_manager_runs_its_setup_again_and_serves(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"erm-{uid}"

    def setup(reg: rr.ResourceRegistrar) -> None:
        reg.register_server("echo", load=lambda r: r, unload=lambda r, _: None)

    sup = supervisors([ManagerSpec(name, setup)]).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)
    sup.wait_restarted(name, timeout=5.0)

    assert "hi" == app.call(name, "echo", "hi").response


def test_a_temporary_child_is_never_restarted(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    sup = supervisors(three(uid, "temporary")).start()
    crash(sup, f"a-{uid}")

    with pytest.raises(rr.RegistrarUnavailableError, match="will not be restarted"):
        sup.wait_restarted(f"a-{uid}", timeout=5.0)
    assert ("exited", 0) == (sup.child(f"a-{uid}").state, sup.child(f"a-{uid}").restarts)


def test_a_transient_child_that_stops_normally_is_not_restarted(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    sup = supervisors(three(uid, "transient")).start()
    handle(sup, f"a-{uid}").stop()

    with pytest.raises(rr.RegistrarUnavailableError, match="normal"):
        sup.wait_restarted(f"a-{uid}", timeout=5.0)


def test_a_transient_child_that_crashes_is_restarted(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    sup = supervisors(three(uid, "transient")).start()
    crash(sup, f"a-{uid}")

    assert 1 == sup.wait_restarted(f"a-{uid}", timeout=5.0).restarts


def test_wait_restarted_waits_for_one_more_restart_each_time(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([ManagerSpec(name)], max_restarts=5).start()
    crash(sup, name)
    first = sup.wait_restarted(name, timeout=5.0).restarts
    crash(sup, name)
    second = sup.wait_restarted(name, timeout=5.0).restarts

    assert (1, 2) == (first, second)


def test_last_exit_says_why_the_child_went_down(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([ManagerSpec(name)]).start()
    crash(sup, name)

    assert "crashed" in (sup.wait_restarted(name, timeout=5.0).last_exit or "")


# -- intensity, escalation, backoff ---------------------------------------------------------


def test_more_restarts_than_the_intensity_allows_makes_the_supervisor_give_up(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    sup = supervisors([ManagerSpec(name), ManagerSpec(f"b-{uid}")], max_restarts=2).start()
    for _ in range(2):
        crash(sup, name)
        sup.wait_restarted(name, timeout=5.0)
    crash(sup, name)

    with pytest.raises(rr.SupervisorGaveUpError, match="more than 2 restart"):
        sup.wait_restarted(name, timeout=5.0)
    assert ["stopped", "stopped"] == [i.state for i in sup.which_children()]


def test_crashes_spread_wider_than_the_period_never_exhaust_the_intensity(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    clock = FakeClock()
    sup = supervisors([ManagerSpec(name)], max_restarts=1, period=5.0, clock=clock).start()
    for _ in range(4):
        crash(sup, name)
        sup.wait_restarted(name, timeout=5.0)
        clock.now += 6.0

    assert (None, 4) == (sup.gave_up, sup.child(name).restarts)


def test_leaving_the_with_block_of_a_supervisor_that_gave_up_raises(uid: str) -> None:
    name = f"a-{uid}"
    sup = Supervisor([ManagerSpec(name)], max_restarts=0, clock=FakeClock())

    def crash_inside_with_block() -> None:
        with sup:
            crash(sup, name)
            with pytest.raises(rr.SupervisorGaveUpError):
                sup.wait_restarted(name, timeout=5.0)

    with pytest.raises(rr.SupervisorGaveUpError):
        crash_inside_with_block()


def test_a_nested_supervisor_that_gives_up_is_restarted_by_its_parent(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x = f"x-{uid}"
    inner = SupervisorSpec(f"inner-{uid}", (ManagerSpec(x),), max_restarts=0)
    sup = supervisors([ManagerSpec(f"a-{uid}"), inner], max_restarts=3).start()
    crash(sup, x)
    info = sup.wait_restarted(f"inner-{uid}", timeout=5.0)

    assert (1, "running", None) == (info.restarts, sup.child(x).state, sup.gave_up)
    assert "gave up" in (info.last_exit or "")


def test_escalation_reaches_the_top_when_the_parent_runs_out_of_restarts_too(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x = f"x-{uid}"
    inner = SupervisorSpec(f"inner-{uid}", (ManagerSpec(x),), max_restarts=0)
    sup = supervisors([inner], max_restarts=0).start()
    crash(sup, x)

    with pytest.raises(rr.SupervisorGaveUpError):
        sup.wait_restarted(f"inner-{uid}", timeout=5.0)
    assert sup.gave_up is not None


def test_backoff_delays_each_restart_in_the_window_longer(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    timer = ManualTimer()
    backoff = Backoff(initial=0.1, factor=2.0, max=1.0, jitter=0.0)
    sup = supervisors([ManagerSpec(name)], max_restarts=5, backoff=backoff, timer=timer).start()
    for n in (1, 2, 3):
        crash(sup, name)
        assert timer.wait_scheduled(n)
        assert "restarting" == sup.child(name).state
        timer.fire()
        sup.wait_restarted(name, timeout=5.0)

    assert [0.1, 0.2, 0.4] == [round(d, 9) for d in timer.delays]


def test_stopping_a_supervisor_cancels_a_pending_restart(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name)], backoff=Backoff(initial=1.0), timer=timer).start()
    crash(sup, name)
    assert timer.wait_scheduled(1)
    sup.stop()
    cancelled = [handle.cancelled for _, _, handle in timer.pending]
    timer.fire()

    assert ([True], "stopped") == (cancelled, sup.child(name).state)


def test_a_restart_whose_setup_fails_counts_as_another_crash(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    runs: list[int] = []

    def setup(_: rr.ResourceRegistrar) -> None:
        runs.append(1)
        if len(runs) > 1:
            raise RuntimeError("disk full")

    sup = supervisors([ManagerSpec(name, setup)], max_restarts=2).start()
    crash(sup, name)

    with pytest.raises(rr.SupervisorGaveUpError, match="failed to start"):
        sup.wait_restarted(name, timeout=5.0)
    assert 3 == len(runs)


def test_a_restart_whose_setup_calls_sys_exit_counts_as_another_crash(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    """A careless thread manager's `setup` that calls `sys.exit()` (a `BaseException`)
    fails its start as one that raises does: at the first start that is the start's
    error; at a restart it must count as another crash and be restarted, not leave the
    child "starting" for ever with nobody told."""
    name = f"a-{uid}"
    runs: list[int] = []

    def setup(_: rr.ResourceRegistrar) -> None:
        runs.append(1)
        if len(runs) == 2:
            sys.exit(3)

    sup = supervisors([ManagerSpec(name, setup)], max_restarts=3).start()
    crash(sup, name)
    info = sup.wait_restarted(name, timeout=5.0)

    assert ("running", 3) == (info.state, len(runs))


# -- death watch and retries ----------------------------------------------------------------


def provider_and_consumer(
    uid: str, consumer_restart: str
) -> tuple[list[ManagerSpec], list[Any], threading.Event]:
    """A provider `p-<uid>` with server "res", and a consumer `c-<uid>` that loads from it."""
    unloads: list[Any] = []
    unloaded = threading.Event()

    def provider(reg: rr.ResourceRegistrar) -> None:
        def unload(request: Any, _: Any) -> None:
            unloads.append(request)
            unloaded.set()

        reg.register_server("res", load=lambda r: r, unload=unload)

    def consumer(reg: rr.ResourceRegistrar) -> None:
        if not reg.client_queries():
            reg.call(f"p-{uid}", "res", "camera")

    specs = [
        ManagerSpec(f"p-{uid}", provider),
        ManagerSpec(f"c-{uid}", consumer, restart=consumer_restart),  # type: ignore[arg-type]
    ]
    return specs, unloads, unloaded


def test_a_temporary_consumer_that_dies_has_its_consumer_ids_released(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    specs, unloads, unloaded = provider_and_consumer(uid, "temporary")
    sup = supervisors(specs).start()
    crash(sup, f"c-{uid}")

    assert unloaded.wait(5.0)
    assert (["camera"], []) == (unloads, handle(sup, f"p-{uid}").server_queries("res"))


def test_a_consumer_that_will_be_restarted_keeps_its_consumer_ids(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    specs, unloads, _ = provider_and_consumer(uid, "permanent")
    timer = ManualTimer()
    sup = supervisors(specs, backoff=Backoff(initial=1.0), timer=timer).start()
    crash(sup, f"c-{uid}")
    assert timer.wait_scheduled(1)

    held = handle(sup, f"p-{uid}").server_queries("res")
    assert ([], [f"c-{uid}"]) == (unloads, [q.origin_rr for q in held])


def test_a_consumer_whose_supervisor_gave_up_has_its_consumer_ids_released(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    specs, unloads, unloaded = provider_and_consumer(uid, "permanent")
    inner = SupervisorSpec(f"inner-{uid}", (specs[1],), max_restarts=0, restart="temporary")
    sup = supervisors([specs[0], inner]).start()
    crash(sup, f"c-{uid}")

    assert unloaded.wait(5.0)
    assert ["camera"] == unloads


def test_call_with_retry_waits_for_the_restart_and_loads_once(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    loads: list[Any] = []
    name = f"p-{uid}"

    def provider(reg: rr.ResourceRegistrar) -> None:
        reg.register_server("res", load=lambda r: loads.append(r) or r, unload=lambda r, _: None)

    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name, provider)], backoff=Backoff(initial=1.0), timer=timer)
    sup.start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)
    assert timer.wait_scheduled(1)
    waiting = once_waiting(sup, monkeypatch)
    result: list[rr.Query] = []
    caller = threading.Thread(
        target=lambda: result.append(
            call_with_retry(sup, app, name, "res", "camera", timeout=10.0, query_id="q-1")
        )
    )
    caller.start()
    assert waiting.wait(5.0)  # its first attempt failed: the restart is what it waits for
    timer.fire()
    caller.join(10.0)

    assert (["camera"], "q-1") == (loads, result[0].id)
    assert ["q-1"] == [q.id for q in handle(sup, name).server_queries("res")]


def unavailable_at_send(app: rr.ResourceRegistrar, name: str, times: int) -> list[Any]:
    """Fail `app`'s next `times` loads as unavailable as they leave (the loads, listed):
    this process does not see `name` served yet (across hosts: its token is on its way),
    or it was killed and its tree has not seen it yet."""
    refused: list[Any] = []

    def refuse(load: Any) -> None:
        if len(refused) < times:
            refused.append(load)
            raise rr.RegistrarUnavailableError(f"{name!r} cannot be reached (forced)")

    testing.intercept(app, "send_load", before=refuse)
    return refused


def test_call_with_retry_after_a_restart_before_it_began_tries_again_at_once(
    supervisors: Callable[..., Supervisor], uid: str, call_with_retry: CallWithRetry
) -> None:
    name = f"p-{uid}"
    sup = supervisors([ManagerSpec(name, echo_setup)], backoff=Backoff(initial=0.0)).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)
    sup.wait_restarted(name, timeout=10.0)  # (restarted before the call reads the count)
    refused = unavailable_at_send(app, name, 1)

    query = call_with_retry(sup, app, name, "echo", "camera", timeout=10.0)

    assert ("camera", 1) == (query.response, len(refused))  # no second restart waited for


def test_call_with_retry_tries_at_once_once_then_waits_for_the_next_restart(
    supervisors: Callable[..., Supervisor], uid: str, call_with_retry: CallWithRetry
) -> None:
    name = f"p-{uid}"
    sup = supervisors([ManagerSpec(name, echo_setup)]).start()
    app = sup.registrar(f"app-{uid}")
    refused = unavailable_at_send(app, name, 1000)  # (its tree never sees it gone)

    with pytest.raises(rr.CallTimeoutError, match="restarting"):
        call_with_retry(sup, app, name, "echo", "camera", timeout=1.0)
    assert 2 == len(refused)  # not a spin until the timeout: the tree's restart is awaited


def test_call_with_retry_gives_up_at_once_when_the_provider_will_not_come_back(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
) -> None:
    name = f"p-{uid}"
    sup = supervisors([ManagerSpec(name, restart="temporary")]).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)

    with pytest.raises(rr.RegistrarUnavailableError):
        call_with_retry(sup, app, name, "res", "camera", timeout=5.0)


def test_call_with_retry_gives_up_at_once_when_a_restarting_provider_is_stopped_for_good(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
) -> None:
    """Restarting when the call failed, the provider is waited for until it runs with the
    restarts it counted (0); stopped for good instead, with that count unchanged, the
    wait ends at once as unavailable. It used to wait its whole timeout."""
    name = f"p-{uid}"
    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name)], backoff=Backoff(initial=1.0), timer=timer).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)
    assert timer.wait_scheduled(1)  # (the restart is held: the provider stays restarting)
    outcome: list[BaseException] = []

    def call() -> None:
        try:
            call_with_retry(sup, app, name, "res", "camera", timeout=30.0)
        except BaseException as exc:
            outcome.append(exc)

    thread = threading.Thread(target=call)
    thread.start()
    assert wait_for(lambda: bool(sup._tree.watchers), timeout=30.0)  # the retry waits
    sup.stop()
    thread.join(60.0)

    assert [rr.RegistrarUnavailableError] == [type(exc) for exc in outcome], outcome


def test_call_with_retry_that_times_out_while_restarting_raises_call_timeout(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
) -> None:
    name = f"p-{uid}"
    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name)], backoff=Backoff(initial=1.0), timer=timer).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, name)
    assert timer.wait_scheduled(1)
    withdrawn, seen, on_event = events_of(rr.events.CallWithdrawn)
    with app.subscribe(on_event):
        with pytest.raises(rr.CallTimeoutError):
            call_with_retry(sup, app, name, "res", "camera", timeout=0.2, query_id="q-1")
        assert seen.wait(10.0)  # (issue 68 item 8: the check's `timed-out` rule reads it)

    assert [("q-1", name, "timeout")] == [(e.query_id, e.serving_rr, e.reason) for e in withdrawn]
    assert withdrawn[0].at - withdrawn[0].started >= 0.2 - 0.05  # (wall clock stamps)


def test_call_with_retry_whose_wait_for_the_restart_fails_withdraws_its_call(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
) -> None:
    """The wait ended by an error other than its timeout (here: the restarting provider
    stopped for good) withdraws the call as a cancel does: its id abandoned, its
    `CallWithdrawn` ("interrupted"). It published none: the outcome rule found the
    call's last try's `CallFailed` only."""
    name = f"p-{uid}"
    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name)], backoff=Backoff(initial=1.0), timer=timer).start()
    app = rr.ResourceRegistrar.start(f"app-{uid}")  # (not the tree's: it outlives its stop)
    try:
        withdrawn, seen, on_event = events_of(rr.events.CallWithdrawn)
        app.subscribe(on_event)  # (closed with the registrar)
        crash(sup, name)
        assert timer.wait_scheduled(1)  # (the restart is held: the provider stays restarting)
        outcome: list[BaseException] = []

        def call() -> None:
            try:
                call_with_retry(sup, app, name, "res", "camera", timeout=30.0, query_id="q-1")
            except BaseException as exc:
                outcome.append(exc)

        thread = threading.Thread(target=call)
        thread.start()
        assert wait_for(lambda: bool(sup._tree.watchers), timeout=30.0)  # the retry waits
        sup.stop()
        thread.join(60.0)

        assert [rr.RegistrarUnavailableError] == [type(exc) for exc in outcome], outcome
        assert seen.wait(10.0)
        assert [("q-1", name, "interrupted")] == [
            (e.query_id, e.serving_rr, e.reason) for e in withdrawn
        ]
    finally:
        app.stop()


def test_call_with_retry_withdrawn_while_restarting_carries_its_callers_trace(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
) -> None:
    """The retry's `CallWithdrawn` names the call's CLIENT span under its caller's span, as
    a call's other end events do (`trace`, `caller_span`): it had neither."""
    from opentelemetry import trace as api  # noqa: PLC0415 - (a span makes calls traced)

    name = f"p-{uid}"
    timer = ManualTimer()
    sup = supervisors([ManagerSpec(name)], backoff=Backoff(initial=1.0), timer=timer).start()
    app = sup.registrar(f"app-{uid}")
    withdrawn, seen, on_event = events_of(rr.events.CallWithdrawn)
    app.subscribe(on_event)  # (closed with the registrar)
    crash(sup, name)
    assert timer.wait_scheduled(1)
    trace_id, span_id = 0x5EED_0000_0000_0000_0000_0000_0000_0068, 0xCA11_E500_0000_0001
    caller = api.SpanContext(trace_id, span_id, is_remote=False, trace_flags=api.TraceFlags(1))

    with api.use_span(api.NonRecordingSpan(caller)), pytest.raises(rr.CallTimeoutError):
        call_with_retry(sup, app, name, "res", "camera", timeout=0.2, query_id="q-1")

    assert seen.wait(10.0)
    [gone] = withdrawn
    assert (gone.trace[:36], gone.trace[52:], gone.caller_span) == (
        f"00-{trace_id:032x}-",
        "-01",
        f"{span_id:016x}",
    ), gone


def test_an_id_abandoned_while_its_provider_runs_is_released_at_once(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    """`call_with_retry` abandons an id when its wait runs out; the provider may be back."""
    name = f"p-{uid}"
    unloaded = threading.Event()
    sup = supervisors([ManagerSpec(name, recording_provider(unloaded))]).start()
    app = sup.registrar(f"app-{uid}")
    app.call(name, "res", "camera", query_id="q-1")
    abandon(sup, name, "q-1", app.name)

    assert unloaded.wait(5.0)
    assert [] == handle(sup, name).server_queries("res")


def test_a_manager_that_failed_to_start_is_released_by_the_death_watch_when_it_dies_later(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"c-{uid}"

    def broken(_: rr.ResourceRegistrar) -> None:
        raise ValueError("no camera")

    with pytest.raises(rr.SupervisorGaveUpError):
        supervisors([ManagerSpec(name, broken)]).start()
    unloaded = threading.Event()
    provider = rr.ResourceRegistrar.start(f"p-{uid}")
    try:
        recording_provider(unloaded)(provider)
        consumer = rr.ResourceRegistrar.start(name)  # the same name, now unsupervised
        consumer.call(provider.name, "res", "camera")
        testing.crash(consumer)

        assert unloaded.wait(5.0)
    finally:
        provider.stop()


def test_stop_with_a_timeout_bounds_a_shutdown_that_would_take_longer(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    name = f"a-{uid}"
    release = threading.Event()

    def setup(reg: rr.ResourceRegistrar) -> None:
        reg.register_server("res", load=lambda r: r, unload=lambda r, _: release.wait(30.0))

    sup = supervisors([ManagerSpec(name, setup, shutdown=30.0)]).start()
    app = sup.registrar(f"app-{uid}")
    sup.run_in(name, lambda reg: reg.call(name, "res", "x"))  # its stop must unload it
    started = time.monotonic()
    try:
        sup.stop(timeout=0.5)
    finally:
        release.set()

    quick = time.monotonic() - started < 15.0  # not the 30 s of its shutdown

    assert (True, "killed", False) == (
        quick,
        (sup.child(name).last_exit or "")[:6],
        app.is_alive(),
    )


# -- stop() asked for by code the supervisor itself runs (a thread manager's setup) --------------


def stop_from_setup_on_restart(
    box: dict[str, Any], answered: threading.Event
) -> Callable[[rr.ResourceRegistrar], None]:
    """A thread manager's setup that, at its second run (a restart), calls `box["sup"].stop()`
    and sets `answered` once that call returned or raised."""
    runs: list[int] = []

    def setup(_: rr.ResourceRegistrar) -> None:
        runs.append(1)
        if len(runs) == 2:
            try:
                box["sup"].stop()
            finally:
                answered.set()

    return setup


@pytest.mark.parametrize("nested", [False, True], ids=["its-own", "a-nested-supervisors"])
def test_stop_called_from_a_setup_the_tree_runs_never_keeps_a_later_stop_from_stopping_it(
    supervisors: Callable[..., Supervisor], uid: str, nested: bool
) -> None:
    """A careless `setup` that stops the whole tree (a manager that finds its device gone
    and shuts everything down) runs on a supervisor's own thread. Its `stop()` may do the
    stop or refuse it, but it must answer, and the owner's own `stop()` afterwards must
    still stop every manager: none may be left serving with nobody supervising it."""
    a, b = f"a-{uid}", f"b-{uid}"
    box: dict[str, Any] = {}
    answered = threading.Event()
    b_spec = ManagerSpec(b, stop_from_setup_on_restart(box, answered))
    children: list[Any] = [ManagerSpec(a, echo_setup)]
    children.append(SupervisorSpec(f"inner-{uid}", (b_spec,)) if nested else b_spec)
    sup = box["sup"] = supervisors(children, clock=None).start()
    first_a = handle(sup, a)
    crash(sup, b)  # its restart runs the setup that calls stop()

    stop_answered = answered.wait(10.0)
    sup.stop()

    assert (True, False) == (stop_answered, first_a.is_alive())


# -- nested supervisors: escalation seen from a child below -----------------------------------


def nested(uid: str, setup: Any = None, **inner: Any) -> list[ManagerSpec | SupervisorSpec]:
    """`a-<uid>`, then `inner-<uid>` (max_restarts=0 unless given) holding `x-<uid>`."""
    inner.setdefault("max_restarts", 0)
    return [
        ManagerSpec(f"a-{uid}"),
        SupervisorSpec(f"inner-{uid}", (ManagerSpec(f"x-{uid}", setup),), **inner),
    ]


def test_wait_restarted_on_a_child_waits_while_its_parent_restarts_its_supervisor(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x = f"x-{uid}"
    sup = supervisors(nested(uid), max_restarts=3).start()
    crash(sup, x)
    info = sup.wait_restarted(x, timeout=5.0)

    assert (1, "running", None) == (info.restarts, info.state, sup.gave_up)


def test_a_child_of_a_nested_supervisor_being_restarted_is_reported_restarting(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x = f"x-{uid}"
    timer = ManualTimer()
    sup = supervisors(nested(uid), backoff=Backoff(initial=1.0), timer=timer).start()
    crash(sup, x)
    assert timer.wait_scheduled(1)  # the parent holds the restart of inner

    assert ("restarting", None) == (sup.child(x).state, sup.child(x).pid)


def test_call_with_retry_to_a_child_waits_out_its_supervisors_restart_by_the_parent(
    supervisors: Callable[..., Supervisor],
    uid: str,
    call_with_retry: CallWithRetry,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    x = f"x-{uid}"
    timer = ManualTimer()
    unloaded = threading.Event()
    specs = nested(uid, recording_provider(unloaded))
    sup = supervisors(specs, backoff=Backoff(initial=1.0), timer=timer).start()
    app = sup.registrar(f"app-{uid}")
    crash(sup, x)
    assert timer.wait_scheduled(1)
    waiting = once_waiting(sup, monkeypatch)
    result: list[Any] = []

    def call() -> None:
        try:
            result.append(call_with_retry(sup, app, x, "res", "camera", timeout=10.0).response)
        except Exception as exc:
            result.append(exc)

    caller = threading.Thread(target=call)
    caller.start()
    assert waiting.wait(5.0)
    timer.fire()
    caller.join(10.0)

    assert ["camera"] == result


def test_an_id_abandoned_while_a_nested_supervisor_restarts_is_released_when_it_is_back(
    supervisors: Callable[..., Supervisor], uid: str, tmp_path: Any
) -> None:
    x = f"x-{uid}"
    timer = ManualTimer()
    unloaded = threading.Event()
    specs = nested(uid, recording_provider(unloaded))
    sup = supervisors(specs, backoff=Backoff(initial=1.0), timer=timer, state_dir=tmp_path)
    sup.start()
    app = sup.registrar(f"app-{uid}")
    app.call(x, "res", "camera", query_id="q-1")
    crash(sup, x)
    assert timer.wait_scheduled(1)
    abandon(sup, x, "q-1", app.name)  # what a timed-out call_with_retry does
    timer.fire()
    sup.wait_restarted(x, timeout=5.0)

    assert unloaded.wait(5.0)


def test_a_nested_give_up_is_raised_when_no_supervisor_above_restarts_it(
    supervisors: Callable[..., Supervisor], uid: str
) -> None:
    x, inner = f"x-{uid}", f"inner-{uid}"
    sup = supervisors(nested(uid, restart="temporary")).start()
    crash(sup, x)

    with pytest.raises(rr.SupervisorGaveUpError, match=inner):
        sup.wait_restarted(x, timeout=5.0)
    assert None is sup.gave_up


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


def _erm(sup: rr.Supervisor) -> str:
    return sup.which_children()[0].name


class TestBadArguments:
    """`Supervisor.call_with_retry`, `subscribe`, `observe`, `run_in`, `child` and
    `wait_restarted` given what they cannot use.

    Each is a `ConfigError` naming the argument, raised before anything is sent: no id is
    abandoned at the provider for a call never made, no subscription logs a `TypeError` per
    event for ever, no `AttributeError` from the observer's error path.
    """

    @pytest.fixture
    def sup(self) -> Iterator[rr.Supervisor]:
        """A started tree of one manager in a thread, `erm-<hex>`, serving `echo`."""
        with rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)]) as started:
            yield started  # (`with` started it)

    @pytest.mark.parametrize(
        ("arguments", "named"),
        [
            ({"consumer": "app"}, "consumer"),
            ({"consumer": None}, "consumer"),
            ({"target_rr": 5}, "target_rr"),
            ({"server": None}, "server"),
            ({"timeout": -1}, "timeout"),
            ({"timeout": float("nan")}, "timeout"),
            ({"query_id": ""}, "query_id"),
        ],
        ids=[
            "consumer-str",
            "consumer-None",
            "target-int",
            "server-None",
            "timeout-neg",
            "nan",
            "qid",
        ],
    )
    def test_call_with_retry_with_an_argument_it_cannot_use_is_a_config_error_naming_it(
        self,
        sup: rr.Supervisor,
        call_with_retry: CallWithRetry,
        arguments: dict[str, Any],
        named: str,
    ) -> None:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
        call: dict[str, Any] = {"consumer": app, "target_rr": _erm(sup), "server": "echo"}
        call.update(arguments)

        with pytest.raises(rr.ConfigError, match=named):
            call_with_retry(
                sup, call.pop("consumer"), call.pop("target_rr"), call.pop("server"), "x", **call
            )

        assert [] == sup.run_in(_erm(sup), lambda erm: erm.server_queries("echo"), timeout=10)

    def test_subscribe_with_a_callback_that_is_not_callable_is_a_config_error(
        self,
        sup: rr.Supervisor,
    ) -> None:
        with pytest.raises(rr.ConfigError, match="callback"):
            sup.subscribe(42)  # type: ignore[arg-type]

    def test_observe_with_a_sock_that_is_not_a_socket_is_a_config_error_naming_it(
        self,
        sup: rr.Supervisor,
    ) -> None:
        pytest.importorskip("uvicorn")
        with pytest.raises(rr.ConfigError, match="sock"):
            _lab_observe.observe(sup, sock="127.0.0.1:8080")  # type: ignore[arg-type]

    def test_subscribe_after_stop_is_a_config_error_not_a_subscription_that_never_hears(
        self,
    ) -> None:
        sup = rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)])
        sup.start()
        sup.stop()

        with pytest.raises(rr.ConfigError, match="was stopped"):
            sup.subscribe(print)

    @pytest.mark.parametrize(
        ("method", "named"),
        [
            (lambda sup, erm: sup.run_in(erm, lambda r: r.name, timeout=-1), "timeout"),
            (lambda sup, erm: sup.run_in(erm, "not callable"), "fn"),
            (lambda sup, erm: sup.run_in([erm], lambda r: r.name), "name"),
            (lambda sup, erm: sup.child([erm]), "name"),
            (lambda sup, erm: sup.wait_restarted([erm], timeout=1), "name"),
            (lambda sup, erm: sup.wait_restarted(erm, timeout=-1), "timeout"),
            (lambda sup, erm: sup.wait_restarted(erm, timeout=1, restarts="1"), "restarts"),
            (lambda sup, erm: sup.wait_restarted(erm, timeout=1, restarts=[1]), "restarts"),
        ],
        ids=[
            "run_in-timeout",
            "run_in-fn",
            "run_in-name",
            "child",
            "wait_restarted",
            "wait-timeout",
            "wait-restarts-str",
            "wait-restarts-list",
        ],
    )
    def test_run_in_child_and_wait_restarted_refuse_what_they_cannot_use_naming_it(
        self, sup: rr.Supervisor, method: Callable[[rr.Supervisor, str], object], named: str
    ) -> None:
        with pytest.raises(rr.ConfigError, match=named):
            method(sup, _erm(sup))

        assert "running" == sup.child(_erm(sup)).state

    # -- the traps a new user fell into (issue 44, item 5) ---------------------------------------

    def test_child_before_the_start_says_the_supervisor_is_not_started(self) -> None:
        sup = rr.Supervisor([rr.ManagerSpec("erm", echo_setup)])

        with pytest.raises(rr.ConfigError, match="is not started: its child 'erm' is not running"):
            sup.child("erm")
        assert "stopped" == sup.snapshot("erm").state  # (what the observer shows before it)

    def test_one_spec_alone_is_a_tree_of_that_one_child(self) -> None:
        name = f"erm-{uuid.uuid4().hex[:8]}"

        with rr.Supervisor(rr.ManagerSpec(name, echo_setup)) as sup:
            assert [name] == [c.name for c in sup.which_children()]
            assert "running" == sup.child(name).state

    @pytest.mark.parametrize("children", ["erm", 5, None])
    def test_children_that_are_not_specs_are_a_config_error_saying_a_list(
        self, children: Any
    ) -> None:
        with pytest.raises(rr.ConfigError, match="children must be a list of ManagerSpec"):
            rr.Supervisor(children)

    def test_call_with_retry_with_a_name_first_says_the_consumer_comes_first(
        self,
        sup: rr.Supervisor,
        call_with_retry: CallWithRetry,
    ) -> None:
        with pytest.raises(
            rr.ConfigError,
            match=r"call_with_retry\(consumer, target_rr, server, request\): the consumer comes "
            "first",
        ):
            call_with_retry(sup, _erm(sup), "echo", 0)

    def test_call_with_retry_without_a_request_says_it_is_missing(
        self, sup: rr.Supervisor, call_with_retry: CallWithRetry
    ) -> None:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")

        with pytest.raises(rr.ConfigError, match="request is missing"):
            call_with_retry(sup, app, _erm(sup), "echo")

    def test_a_second_with_on_a_stopped_supervisor_says_make_a_new_one(self) -> None:
        sup = rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)])
        with sup:
            pass

        with pytest.raises(rr.ConfigError, match="cannot be restarted: make a new one"), sup:
            pass

    def test_starting_a_running_supervisor_says_it_is_running(self, sup: rr.Supervisor) -> None:
        with pytest.raises(rr.ConfigError, match="is already started \\(it is running\\)"):
            sup.start()
