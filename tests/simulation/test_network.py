"""The simulated carrier: frames after seeded delays, in order per link; partitions that
fail what waits across them, and heals after which both sides carry on."""

from __future__ import annotations

import contextlib
import gc
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from typing import Any, Literal

import pytest

import rr_actors as rr
from rr_actors import simulation
from rr_actors._core import runtime
from rr_actors.simulation import _run
from rr_actors.simulation._network import DELAY, _SimulatedHub, _Wire
from rr_actors.simulation._run import running_scheduler
from rr_actors.testing.memory import MemoryNetwork
from tests.support import simulated
from tests.support.simulated import Interrupted, interrupted_when

pytest.importorskip("greenlet")  # (the simulation extra)


def leaf_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: f"leaf {r}", unload=lambda *_: None)


def test_frames_on_one_wire_arrive_in_order_each_after_its_delay() -> None:
    def main() -> list[tuple[int, float, float]]:
        network = simulation.SimulatedNetwork()
        try:
            hub = network._hub
            assert isinstance(hub, _SimulatedHub)
            wire = _Wire(hub, running_scheduler().root, "wire")
            arrived: list[tuple[int, float, float]] = []
            for number in range(30):
                sent = simulation.now()
                wire.put(lambda n=number, s=sent: arrived.append((n, s, simulation.now())))
                simulation.sleep(0.001 * (number % 3))
            simulation.sleep(1.0)
            return arrived
        finally:
            network.close()

    for seed in range(10):
        arrived = simulation.run(main, seed=seed, preempt=0.1).value
        assert list(range(30)) == [n for n, _, _ in arrived], f"seed {seed}"
        assert all(DELAY[0] <= at - sent <= DELAY[1] for _, sent, at in arrived)
        assert len({round(at - sent, 9) for _, sent, at in arrived}) > 10  # (drawn)


def with_provider(
    body: Callable[[rr.Supervisor, rr.ResourceRegistrar, Any], Any],
    lease: float | None = None,
    heartbeat: float | None = 0.25,
    restart: Literal["permanent", "transient", "temporary"] = "permanent",
    resolve: Any = "first_served",
) -> Any:
    """A scenario: a process manager `provider` (backed up) under a supervisor on a
    simulated network, a consumer `app` in the supervisor's process."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-network-")
        network = simulation.SimulatedNetwork(lease=lease, resolve=resolve)
        try:
            manager = rr.ManagerSpec(
                "provider",
                setup=leaf_setup,
                isolation="process",
                heartbeat=heartbeat,
                restart=restart,
            )
            supervisor = rr.Supervisor(manager, state_dir=folder, network=network, name="root")
            supervisor.start()
            app = supervisor.registrar("app")
            try:
                return body(supervisor, app, network)
            finally:
                supervisor.stop()
                app.stop()
        finally:
            network.close()
            shutil.rmtree(folder, ignore_errors=True)

    return scenario


def test_a_call_across_processes_takes_the_time_of_its_frames() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        began = simulation.now()
        query = app.call("provider", "leaf", "x")
        return query.response, simulation.now() - began

    response, took = simulation.run(with_provider(body), seed=1).value

    assert "leaf x" == response
    assert took >= 2 * DELAY[0]  # (there and back)


def test_a_cut_fails_calls_across_it_and_after_the_heal_both_sides_hold_what_they_held() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        held = app.call("provider", "leaf", "x")
        network.partition([supervisor.child("provider").pid])
        try:
            app.call("provider", "leaf", "y", timeout=5.0)
        except rr.RegistrarUnavailableError:
            during = "unavailable"
        else:
            during = "answered"
        simulation.sleep(2.0)
        network.heal()
        simulation.sleep(1.0)  # (the heal's reconciliation)
        after = app.call("provider", "leaf", "z").response
        served = supervisor.run_in(
            "provider", lambda r: sorted(q.request for q in r.server_queries("leaf")), timeout=5.0
        )
        return during, after, served, [q.id for q in app.client_queries()].count(held.id)

    for seed in range(20):
        run = simulation.run(with_provider(body), seed=seed, preempt=0.1)
        assert ("unavailable", "leaf z", ["x", "z"], 1) == run.value, f"seed {seed}"
        assert () == run.errors


def test_a_reply_waiting_across_a_cut_fails_when_it_is_cut() -> None:
    def slow_setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            simulation.sleep(3.0)
            return request

        registrar.register_server("slow", load=load, unload=lambda *_: None)

    def scenario() -> Any:
        network = simulation.SimulatedNetwork()
        try:
            manager = rr.ManagerSpec("provider", setup=slow_setup, isolation="process")
            supervisor = rr.Supervisor(manager, network=network, name="root")
            supervisor.start()
            app = supervisor.registrar("app")
            outcome: list[Any] = []

            def call() -> None:
                try:
                    app.call("provider", "slow", "x", timeout=10.0)
                except rr.RegistrarUnavailableError:
                    outcome.append(("unavailable", simulation.now()))

            from rr_actors._core import runtime  # noqa: PLC0415

            caller = runtime.Thread(target=call, name="caller")
            caller.start()
            simulation.sleep(1.0)
            network.partition([supervisor.child("provider").pid])
            caller.join()
            network.heal()
            supervisor.stop()
            app.stop()
            return outcome
        finally:
            network.close()

    ((what, when),) = simulation.run(scenario, seed=5).value

    assert "unavailable" == what
    assert when < 1.1  # (at the cut, not at the call's timeout)


def test_a_process_stopped_past_its_lease_cannot_be_reached_until_it_runs_again() -> None:
    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        held = app.call("provider", "leaf", "x")
        pid = supervisor.child("provider").pid
        simulation.kill(pid, signal.SIGSTOP)
        simulation.sleep(0.5)  # (within its lease: a call waits for it)
        try:
            app.call("provider", "leaf", "y", timeout=0.5)
        except rr.CallTimeoutError:
            within = "waits"
        simulation.sleep(1.0)  # (past it)
        began = simulation.now()
        try:
            app.call("provider", "leaf", "y", timeout=5.0)
        except rr.RegistrarUnavailableError:
            past = ("unavailable", simulation.now() - began < 0.1)
        simulation.kill(pid, signal.SIGCONT)
        simulation.sleep(1.0)  # (heard again; its consumers reconcile)
        after = app.call("provider", "leaf", "z").response
        return within, past, after, [q.id for q in app.client_queries()].count(held.id)

    for seed in range(10):
        run = simulation.run(with_provider(body, lease=1.0, heartbeat=None), seed=seed)
        assert ("waits", ("unavailable", True), "leaf z", 1) == run.value, f"seed {seed}"


def test_a_name_served_on_both_sides_of_a_cut_is_kept_on_one_after_the_heal() -> None:
    """Rule 22 on the simulated carrier: a second server of `provider` beyond a cut
    serves its side; at the heal the one served first is kept and the other yields
    (`Messenger.served_elsewhere`, as over Zenoh): what it held is released ("name
    yielded") and unloaded, and the consumer's id there is FATAL and forgotten; what
    the consumer held at the one kept was forgotten when it met the new one, and the
    heal's reconcile releases it there (docs/explanation/failure-semantics.md)."""

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        held = app.call("provider", "leaf", "x")
        first = supervisor.child("provider").pid
        network.partition([first])
        folder = tempfile.mkdtemp(prefix="rr-sim-beyond-")
        spec = rr.ManagerSpec(
            "provider", setup=leaf_setup, isolation="process", restart="temporary"
        )
        beyond = rr.Supervisor(spec, state_dir=folder, network=network, name="beyond")
        seen: list[str] = []

        def record(event: Any) -> None:
            if isinstance(event, rr.events.ConsumerReleased | rr.events.ResourceUnloaded):
                seen.append(getattr(event, "reason", "unloaded"))

        subscription = beyond.subscribe(record)
        try:
            beyond.start()
            second = beyond.child("provider").pid
            during = app.call("provider", "leaf", "y", timeout=5.0)  # (the one on its side)
            simulation.sleep(1.0)
            network.heal()
            simulation.sleep(2.0)  # (the yield, the reconcile)
            after = app.call("provider", "leaf", "z").response
            served = supervisor.run_in(
                "provider",
                lambda r: sorted(q.request for q in r.server_queries("leaf")),
                timeout=5.0,
            )
            ids = [q.id for q in app.client_queries()]
            subscription.wait_delivered()
            return (
                second != first,
                during.response,
                beyond.child("provider").state,
                seen,
                after,
                served,
                (held.id in ids, during.id in ids),
            )
        finally:
            subscription.close()
            beyond.stop()
            shutil.rmtree(folder, ignore_errors=True)

    for seed in range(10):
        run = simulation.run(with_provider(body), seed=seed, preempt=0.1)
        assert (
            True,
            "leaf y",
            "exited",
            ["name yielded", "unloaded"],
            "leaf z",
            ["z"],
            (False, False),
        ) == run.value, f"seed {seed}"
        assert () == run.errors


def lone_host_cut(
    supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any
) -> tuple[str, str, list[str], tuple[bool, bool]]:
    """Finding 9 of issue 51 on three simulated hosts: `provider`'s process is cut off
    the other two (the consumer's and a newcomer's); the newcomer serves the majority
    side during the cut, the heal shows both. What is left: the original's and the
    newcomer's state, what the one kept serves, whether the consumer still holds its
    id from before the cut and its id from during it."""
    held = app.call("provider", "leaf", "x")
    network.partition([supervisor.child("provider").pid])
    folder = tempfile.mkdtemp(prefix="rr-sim-beyond-")
    spec = rr.ManagerSpec("provider", setup=leaf_setup, isolation="process", restart="temporary")
    beyond = rr.Supervisor(spec, state_dir=folder, network=network, name="beyond")
    try:
        beyond.start()
        during = app.call("provider", "leaf", "y", timeout=5.0)  # (the newcomer's)
        simulation.sleep(1.0)
        network.heal()
        simulation.sleep(2.0)  # (the yield, the reconcile)
        app.call("provider", "leaf", "z")
        states = (supervisor.child("provider").state, beyond.child("provider").state)
        kept = beyond if states[1] == "running" else supervisor
        served = kept.run_in(
            "provider", lambda r: sorted(q.request for q in r.server_queries("leaf")), timeout=5.0
        )
        ids = [q.id for q in app.client_queries()]
        return (*states, served, (held.id in ids, during.id in ids))
    finally:
        beyond.stop()
        shutil.rmtree(folder, ignore_errors=True)


FIRST_KEPT = ("running", "exited", ["z"], (False, False))
"""The lone host's registrar kept: what the majority side loaded during the cut is
undone (its consumer's id there FATAL and forgotten)."""
NEWCOMER_KEPT = ("exited", "running", ["y", "z"], (False, True))
"""The majority side's newcomer kept: what the lone host held is undone (the consumer
forgot its id there when it met the newcomer); what was loaded during the cut stays."""


def keep_the_second(first: rr.Claimant, second: rr.Claimant) -> rr.Claimant:
    return second


def raise_instead(first: rr.Claimant, second: rr.Claimant) -> rr.Claimant:
    raise RuntimeError("a bug in the user's function")


@pytest.mark.parametrize(
    ("resolve", "expected"),
    [
        ("first_served", FIRST_KEPT),
        ("majority", NEWCOMER_KEPT),
        (keep_the_second, NEWCOMER_KEPT),
        (raise_instead, FIRST_KEPT),  # (a WARNING; user code does not break rule 22)
    ],
    ids=["first_served", "majority", "function", "function-raises"],
)
def test_a_lone_host_cut_keeps_the_registrar_its_resolve_strategy_chooses(
    resolve: Any, expected: tuple[Any, ...]
) -> None:
    """Issue 51, finding 9: `resolve=` decides which of two servers of one name a heal
    keeps. "majority" keeps the newcomer that began to serve on the side with two of
    the three hosts (with the old rule, first served, the lone host's was kept)."""
    for seed in range(4):
        run = simulation.run(
            with_provider(lone_host_cut, restart="temporary", resolve=resolve), seed=seed
        )
        assert expected == run.value, f"seed {seed}"
        assert () == run.errors


def test_a_resolve_function_gets_both_claimants_with_their_sides() -> None:
    """The function is given plain data, first served first: the lone host's registrar
    began with every member heard, the newcomer with two of the three (a majority)."""
    seen: list[rr.Claimant] = []

    def record(first: rr.Claimant, second: rr.Claimant) -> rr.Claimant:
        seen.extend((first, second))
        return first

    run = simulation.run(with_provider(lone_host_cut, restart="temporary", resolve=record), seed=1)

    assert FIRST_KEPT == run.value
    first, second = seen[:2]
    assert ("provider", 2, 2, True) == (first.name, first.side, first.members, first.majority)
    assert ("provider", 2, 3, True) == (second.name, second.side, second.members, second.majority)
    assert first.stamp < second.stamp
    assert first.served_since <= second.served_since


def test_a_simulated_network_refuses_a_resolve_that_is_no_strategy() -> None:
    with pytest.raises(rr.ConfigError, match="resolve must be"):
        simulation.SimulatedNetwork(resolve="largest")


def test_a_network_closed_during_a_cut_ends_the_server_beyond_it_too() -> None:
    """A name served on both sides of a cut when the network closes: both servers end
    (the hub's `leave` ended only the newest of each name; the other was put back as
    the name's server and still took messages)."""

    def scenario() -> tuple[list[str], list[str]]:
        folder = tempfile.mkdtemp(prefix="rr-sim-close-")
        network = simulation.SimulatedNetwork()
        manager = rr.ManagerSpec("provider", setup=leaf_setup, isolation="process")
        sup = rr.Supervisor(manager, state_dir=folder, network=network, name="root")
        spec = rr.ManagerSpec(
            "provider", setup=leaf_setup, isolation="process", restart="temporary"
        )
        beyond = rr.Supervisor(spec, state_dir=f"{folder}/b", network=network, name="beyond")
        try:
            sup.start()
            network.partition([sup.child("provider").pid])
            beyond.start()
            hub = network._simulated()
            served_before = hub.names()
            network.close()
            return served_before, hub.names()
        finally:
            beyond.stop()
            sup.stop()
            shutil.rmtree(folder, ignore_errors=True)

    run = simulation.run(scenario, seed=1)

    assert ((["provider"], []), ()) == (run.value, tuple(run.errors))


@pytest.mark.parametrize("end", ["returns", "raises", "interrupted"])
@pytest.mark.parametrize("network", ["SimulatedNetwork", "MemoryNetwork"])
def test_a_run_over_frees_its_networks_name_however_its_cleanup_went(
    end: str, network: str
) -> None:
    """A run's network left open (its task returned or raised without closing it, or the
    run was cancelled while a `finally` waited: a test's timeout in CI) no longer holds its
    name once the run is over; before, every later run of the process failed
    `ConfigError: ... 'simulated' is open already` (some 100 tests after one timeout).
    A plain `MemoryNetwork` too (tests/simulation/test_manager.py runs one so named)."""
    began = threading.Event()

    def main() -> None:
        if network == "MemoryNetwork":
            MemoryNetwork("simulated")
        else:
            simulation.SimulatedNetwork()
        if end == "raises":
            raise KeyError("a failed run")
        if end == "interrupted":
            began.set()  # (a real event: the interrupting thread waits on it)
            try:
                while True:  # (for ever, in virtual time)
                    runtime.sleep(0.001)  # allowed: virtual time
            finally:
                runtime.Event().wait()  # (a cleanup that waits: never reaches a close)

    interrupting = interrupted_when(began) if end == "interrupted" else contextlib.nullcontext()
    raised = pytest.raises((KeyError, Interrupted))
    with interrupting, raised if end != "returns" else contextlib.nullcontext():
        simulation.run(main, seed=1, until=1e9, max_steps=10**12)

    again = simulation.run(lambda: simulation.SimulatedNetwork().close(), seed=1)

    assert () == tuple(again.errors)


def test_the_files_of_the_processes_a_run_killed_are_closed_when_it_ends(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulated kill keeps the killed process's memory (its threads are dropped at the
    run's end, not at the kill); what it held open, its backup's files, is closed as it
    dies (`runtime.hold`), not whenever the garbage collector next runs (a crash loop's
    some 6,000 descriptors outlived its run in a test process and a later test's
    `select()` failed: descriptor out of range)."""

    def open_files() -> int:
        return len(os.listdir("/proc/self/fd"))

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, _network: Any) -> None:
        for n in range(10):
            app.call("provider", "leaf", n)
            simulation.kill(supervisor.child("provider").pid)
            supervisor.wait_restarted("provider", restarts=n + 1, timeout=10.0)
            simulation.sleep(2.0)  # (virtual: within the tree's restart intensity)

    monkeypatch.setattr(_run, "COLLECT_AFTER", 10**9)  # (no collection: closing alone)
    gc.collect()
    before = open_files()
    gc.disable()  # (only the run's end may collect)
    try:
        run = simulation.run(with_provider(body), seed=1)
        after = open_files()
    finally:
        gc.enable()

    assert ((), before) == (tuple(run.errors), after)


# -- a new link's dial: what its sender sent meanwhile dies with it (issue 51) -------------

TOLD: list[tuple[int, float]] = []  # (pid, virtual time) of each `told_here` that ran


def told_here(_registrar: Any) -> None:
    """Run in the receiving process (sent by reference: `TOLD` is this module's)."""
    TOLD.append((simulation.pid(), simulation.now()))


def sent_then_killed(connected: bool) -> Callable[[], Any]:
    """A process tells registrar `target` of another process (over the link it made for a
    call before if `connected`, else a new one), goes on, and is SIGKILLed right after:
    whether the frame ran there, and whether the sender went on."""

    def scenario() -> Any:
        TOLD.clear()
        network = simulation.SimulatedNetwork()
        try:
            simulation.start_process(serve_alone(network, "target"), name="target")
            until_served(network, "target")
            went_on: list[float] = []

            def sender() -> None:
                remote = network.address.attach().resolve("target")
                assert remote is not None
                if connected:  # (its first frame arrived: the link is dialed)
                    remote.run(lambda _registrar: None, timeout=5.0)
                remote.submit(told_here)
                went_on.append(simulation.now())  # (it went on after its send)
                simulation.kill(simulation.pid())  # (SIGKILL, before the frame arrived)

            simulation.start_process(sender, name="sender")
            simulation.sleep(1.0)
            return len(went_on), len(TOLD)
        finally:
            network.close()

    return scenario


@pytest.mark.parametrize("connected", [False, True], ids=["new-link", "connected"])
def test_a_frame_sent_on_a_link_still_dialing_dies_with_its_sender(connected: bool) -> None:
    """A new link is dialed until its first frame arrives (that frame's drawn delay stands
    for the connect and the handshake): what its sender sent before then is held in the
    sender, lost if the sender is killed first, as frames queued behind an AF_UNIX connect
    on its writer thread are (issue 51: a manager's first status of a new life to one
    consumer registrar, sent on a new connection; the manager went on and was killed before
    that connection connected). On a link dialed before, the frame is on the wire: it
    arrives after its sender's death. The reference is
    `tests/transport/unix/test_link.py::test_a_frame_sent_on_a_connection_still_connecting_dies_with_its_sender`."""
    for seed in range(5):
        run = simulation.run(sent_then_killed(connected), seed=seed, preempt=0.1)
        assert ((1, 1 if connected else 0), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


# -- lost for good (rule 19) and a process that cannot hear its router --------------------


def serve_alone(
    network: simulation.SimulatedNetwork, name: str, setup: Callable[[Any], None] = leaf_setup
) -> Callable[[], None]:
    """The main thread of a process that serves registrar `name` on `network` and that
    nobody supervises (its membership names no speaker: rule 19)."""

    def main() -> None:
        registrar = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=name), network=network.address.attach()
        )
        setup(registrar)

    return main


def until_served(network: simulation.SimulatedNetwork, *names: str) -> None:
    while not set(names) <= set(network.names()):
        simulation.sleep(0.05)


def start_tree(
    network: simulation.SimulatedNetwork,
    folder: str,
    restart: Literal["permanent", "transient", "temporary"] = "permanent",
) -> tuple[int, list[int]]:
    """Start a process `tree` whose supervisor runs manager `provider` in a process of
    its own (a consumer in another process sees both). Returns the tree's pid and a list
    that holds the provider's first pid once it serves."""
    children: list[int] = []

    def tree() -> None:
        spec = rr.ManagerSpec("provider", setup=leaf_setup, isolation="process", restart=restart)
        sup = rr.Supervisor(spec, state_dir=folder, network=network, name="tree")
        sup.start()
        pid = sup.child("provider").pid
        assert pid is not None
        children.append(pid)

    return simulation.start_process(tree, name="tree"), children


@contextlib.contextmanager
def app_on(
    folder: str | None = None, heal: bool = False, **network: Any
) -> Iterator[tuple[simulation.SimulatedNetwork, rr.ResourceRegistrar]]:
    """A simulated network (of these options) and a consumer `app` on it; at the end the
    network is healed (with `heal`), `app` stopped, the network closed and `folder` (if
    given) removed."""
    on = simulation.SimulatedNetwork(**network)
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=on)
    try:
        yield on, app
    finally:
        try:
            if heal:
                on.heal()
            app.stop()
        finally:
            on.close()
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def lost_provider(how: str) -> Callable[[], Any]:
    """A consumer `app` holds an id at `provider`, served by a process nobody restarts;
    that process is killed (`kill`) or stopped past its lease (`stop`): the carrier says
    it is lost (rule 19): `app` hears FATAL for the id once and forgets it."""

    def scenario() -> Any:
        with app_on(lease=1.0) as (network, app):
            pid = simulation.start_process(serve_alone(network, "provider"), name="provider")
            until_served(network, "provider")
            heard: list[tuple[str, Any]] = []
            held = app.call(
                "provider",
                "leaf",
                "x",
                on_status=lambda query, update: heard.append((query.id, update.status)),
            )
            simulation.kill(pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
            simulation.sleep(2.0)  # (past its lease)
            try:
                app.unload(held.id)
            except rr.UnknownQueryError:
                unload = "unknown"
            else:
                unload = "unloaded"
            outcome = (heard == [(held.id, rr.Status.FATAL)], unload, app.client_queries())
            if how == "stop":
                simulation.kill(pid, signal.SIGCONT)
            return outcome

    return scenario


@pytest.mark.parametrize("how", ["kill", "stop"])
def test_a_provider_nobody_restarts_is_lost_and_its_consumer_hears_fatal_and_forgets(
    how: str,
) -> None:
    """The carrier's rule 19 on the simulation: a process nobody supervises is killed, or
    stopped past its lease (its tokens go, as Zenoh's): every process that hears the
    network hears the name lost (`Messenger.lost`), so its consumers hear `FATAL` and
    forget their ids (the same messenger and registrar code as on the real carriers)."""
    for seed in range(10):
        run = simulation.run(lost_provider(how), seed=seed, preempt=0.1)
        assert ((True, "unknown", []), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_provider_whose_supervisor_lives_is_awaited_not_lost_and_lost_once_that_one_goes() -> (
    None
):
    """Rule 19: a killed manager whose supervisor's process is alive is not lost (it may
    be restarted: its consumers keep their ids); once its supervisor's process is gone
    too, it is lost (the real carriers' "awaited" names)."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-awaited-")
        with app_on(folder=folder) as (network, app):
            tree_pid, children = start_tree(network, folder, restart="temporary")
            until_served(network, "provider")
            held = app.call("provider", "leaf", "x")
            simulation.kill(children[0])  # (temporary: its supervisor does not restart it)
            simulation.sleep(2.0)
            awaited = [q.id for q in app.client_queries()]
            simulation.kill(tree_pid)  # (its speaker goes too: nobody will say more)
            simulation.sleep(2.0)
            return held.id in awaited, [q.id for q in app.client_queries()]

    for seed in range(5):
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert ((True, []), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_process_that_cannot_hear_its_router_serves_no_name_and_its_calls_fail() -> None:
    """A process whose router went (`deafen`): it refuses to serve a name it cannot tell
    is free (as Zenoh's `Presence.wait_turn`, with its words), its calls and the calls
    to what it serves fail as unavailable at once, it hears every name served elsewhere
    lost, and the others hear what it served, nobody's to restart, lost (rule 19). Once
    it hears its router again (`hear`), calls both ways work again."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-deaf-")
        network = simulation.SimulatedNetwork()
        manager = rr.ManagerSpec("provider", setup=leaf_setup, isolation="process")
        sup = rr.Supervisor(manager, state_dir=folder, network=network, name="root")
        out: dict[str, Any] = {}
        deaf = runtime.Event()
        heard = runtime.Event()
        done = runtime.Event()

        def member() -> None:
            me = rr.ResourceRegistrar.start(
                rr.RegistrarConfig(name="member"), network=network.address.attach()
            )
            leaf_setup(me)
            held = me.call("provider", "leaf", "m")
            deaf.wait()
            try:
                rr.ResourceRegistrar.start(
                    rr.RegistrarConfig(name="other"), network=network.address.attach()
                )
            except rr.RegistrarUnavailableError as exc:
                out["serve"] = str(exc)
            began = simulation.now()
            try:
                me.call("provider", "leaf", "n", timeout=5.0)
            except rr.RegistrarUnavailableError:
                out["call"] = ("unavailable", simulation.now() - began < 0.1)
            simulation.sleep(0.5)
            out["member holds"] = held.id in [q.id for q in me.client_queries()]
            heard.wait()
            simulation.sleep(1.0)  # (reachable again: the reconcile)
            out["member after"] = me.call("provider", "leaf", "n").response
            done.set()

        try:
            sup.start()
            app = sup.registrar("app")
            pid = simulation.start_process(member, name="member")
            until_served(network, "member")
            mine = app.call("member", "leaf", "a")
            simulation.sleep(0.5)
            network.deafen(pid)
            deaf.set()
            simulation.sleep(0.5)
            began = simulation.now()
            try:
                app.call("member", "leaf", "b", timeout=5.0)
            except rr.RegistrarUnavailableError:
                out["app call"] = ("unavailable", simulation.now() - began < 0.1)
            out["app holds"] = mine.id in [q.id for q in app.client_queries()]
            network.hear(pid)
            heard.set()
            done.wait()
            out["app after"] = app.call("member", "leaf", "c").response
            app.stop()
            return out
        finally:
            try:
                sup.stop()
            finally:
                network.close()
                shutil.rmtree(folder, ignore_errors=True)

    for seed in range(10):
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert () == tuple(run.errors), f"seed {seed}"
        out = run.value
        assert out.pop("serve").startswith(
            "cannot tell whether another process of system 'simulated' serves a registrar "
            "named 'other', so this process does not serve it: this process's router "
        ), f"seed {seed}"
        assert {
            "call": ("unavailable", True),
            "member holds": False,  # (its provider is lost for it: FATAL, forgotten)
            "app call": ("unavailable", True),
            "app holds": False,  # (what it served is lost: nobody restarts it)
            "member after": "leaf n",
            "app after": "leaf c",
        } == out, f"seed {seed}"


def lost_under_a_composite() -> dict[str, Any]:
    """Rule 19 up a dependency path: `app` holds a composite of `agent` (both in the
    network's process), built on a leaf of `provider`, served by a process nobody
    restarts; that process is killed: the carrier says `provider` is lost."""
    network = simulation.SimulatedNetwork()
    heard: list[tuple[str, str, Any]] = []

    def hear(who: str) -> Callable[[rr.Query, rr.StatusUpdate], None]:
        return lambda query, update: heard.append((who, query.id, update.status))

    agent, app = (
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name), network=network)
        for name in ("agent", "app")
    )
    try:
        agent.register_server(
            "composite",
            load=lambda r: agent.call("provider", "leaf", r).response,
            unload=lambda *_: None,
            on_status=hear("composite"),
        )
        pid = simulation.start_process(serve_alone(network, "provider"), name="provider")
        until_served(network, "provider")
        held = app.call("agent", "composite", "x", on_status=hear("app"))
        (leaf,) = agent.client_queries()
        simulation.kill(pid)
        simulation.sleep(1.0)
        return {
            "heard": sorted(heard),
            "ids": (leaf.id, held.id),
            "agent holds": [q.id for q in agent.client_queries()],
            "app holds": [q.id for q in app.client_queries()],
        }
    finally:
        try:
            app.stop()
            agent.stop()
        finally:
            network.close()


def test_rule_19_a_lost_provider_is_fatal_up_every_path_once_and_forgotten() -> None:
    def broken(seen: dict[str, Any]) -> bool:
        _leaf, held = seen["ids"]
        return (
            [("app", held, rr.Status.FATAL), ("composite", held, rr.Status.FATAL)]
            != seen["heard"]  # (the composite's server hears it about what app holds)
            or [] != seen["agent holds"]  # (forgotten: rule 19)
            or [held] != seen["app holds"]  # (its composite got FATAL; the id is app's)
        )

    assert [] == simulated.seeds_where(lost_under_a_composite, broken, simulated.SEEDS)


def test_a_second_server_of_a_name_served_on_its_side_is_refused_and_the_first_serves_on() -> None:
    """One name, one registrar (rule 22; architecture.md): with no cut between them, a
    process that serves a name another live process serves is refused with
    `DuplicateNameError`, as on the real carriers (AF_UNIX: the name's `flock`; Zenoh:
    `Presence.wait_turn` sees its token), and the first serves on; the reference is
    `tests/transport/test_transport.py::TestAtTheCarrier::test_a_name_another_process_serves_is_refused_and_the_first_serves_on`.
    The simulated carrier ended the first on the network instead (its registrar ran on,
    reached by nobody) and let the second serve."""

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        held = app.call("provider", "leaf", "x")
        first = supervisor.child("provider").pid
        folder = tempfile.mkdtemp(prefix="rr-sim-second-")
        spec = rr.ManagerSpec(
            "provider", setup=leaf_setup, isolation="process", restart="temporary"
        )
        second = rr.Supervisor(spec, state_dir=folder, network=network, name="second")
        try:
            try:
                second.start()
            except rr.SupervisorGaveUpError as exc:
                refused = str(exc.__cause__).strip().splitlines()[-1]  # (the child's)
            else:
                refused = f"served by pid {second.child('provider').pid}"
            after = app.call("provider", "leaf", "y", timeout=5.0).response
            served = supervisor.run_in(
                "provider",
                lambda r: sorted(q.request for q in r.server_queries("leaf")),
                timeout=5.0,
            )
            return (
                refused,
                supervisor.child("provider").pid == first,
                after,
                served,
                held.id in [q.id for q in app.client_queries()],
            )
        finally:
            second.stop()
            shutil.rmtree(folder, ignore_errors=True)

    for seed in range(5):
        run = simulation.run(with_provider(body), seed=seed, preempt=0.1)
        duplicate = (
            "rr_actors.errors.DuplicateNameError: a registrar named 'provider' is already "
            "served on system 'simulated' (by process 2)"
        )
        assert (duplicate, True, "leaf y", ["x", "y"], True) == run.value, f"seed {seed}"


def test_a_kill_beyond_a_cut_ends_what_the_killed_process_served_not_the_other_server() -> None:
    """A name served on both sides of a cut, and the process of the one cut off is
    killed: what it served ends, as the kernel closes a dead process's sockets; the
    server on the other side serves on, and after the heal every process reaches it
    (the process's end cut the name's newest server, the one beyond: the consumer's
    next call failed, and the dead one stayed the name's server)."""

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        first = supervisor.child("provider").pid
        network.partition([first])
        folder = tempfile.mkdtemp(prefix="rr-sim-beyond-")
        spec = rr.ManagerSpec(
            "provider", setup=leaf_setup, isolation="process", restart="temporary"
        )
        beyond = rr.Supervisor(spec, state_dir=folder, network=network, name="beyond")
        try:
            beyond.start()
            second = beyond.child("provider").pid
            simulation.kill(first, signal.SIGKILL)
            during = app.call("provider", "leaf", "y", timeout=5.0).response
            network.heal()
            simulation.sleep(1.0)
            after = app.call("provider", "leaf", "z", timeout=5.0).response
            served = beyond.run_in(
                "provider",
                lambda r: sorted(q.request for q in r.server_queries("leaf")),
                timeout=5.0,
            )
            return during, after, served, beyond.child("provider").pid == second
        finally:
            beyond.stop()
            shutil.rmtree(folder, ignore_errors=True)

    for seed in range(5):
        scenario = with_provider(body, heartbeat=None, restart="temporary")
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert ("leaf y", "leaf z", ["y", "z"], True) == run.value, f"seed {seed}"


def test_a_name_whose_server_is_silent_past_its_lease_is_refused_as_unavailable() -> None:
    """A process stopped past its lease cannot be reached, but it is not lost: it may
    run again. Another process that serves its name meanwhile is refused with
    `RegistrarUnavailableError`, as Zenoh's `wait_turn` refuses a name whose server went
    without a clean stop while its supervisor may restart it (AF_UNIX, with no lease,
    refuses it as served: the stopped process holds the name's lock); once the first
    runs again it is the name's one server."""

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        first = supervisor.child("provider").pid
        simulation.kill(first, signal.SIGSTOP)
        simulation.sleep(1.5)  # (past its lease)
        folder = tempfile.mkdtemp(prefix="rr-sim-silent-")
        spec = rr.ManagerSpec(
            "provider", setup=leaf_setup, isolation="process", restart="temporary"
        )
        second = rr.Supervisor(spec, state_dir=folder, network=network, name="second")
        try:
            try:
                second.start()
            except rr.SupervisorGaveUpError as exc:
                refused = str(exc.__cause__).strip().splitlines()[-1].split(":")[0]
            else:
                refused = f"served by pid {second.child('provider').pid}"
            simulation.kill(first, signal.SIGCONT)
            simulation.sleep(1.0)
            after = app.call("provider", "leaf", "y", timeout=5.0).response
            return refused, after, supervisor.child("provider").pid == first
        finally:
            second.stop()
            shutil.rmtree(folder, ignore_errors=True)

    for seed in range(5):
        run = simulation.run(with_provider(body, lease=1.0, heartbeat=None), seed=seed)
        refused = "rr_actors.errors.RegistrarUnavailableError"
        assert (refused, "leaf y", True) == run.value, f"seed {seed}"


def cut_past_the_lease(cut_for: float) -> Callable[[], Any]:
    """A consumer `app` holds an id at `provider`, served by a process nobody restarts;
    that process is cut off the others for `cut_for` s on a network whose lease is 1 s,
    then healed; then `app` calls it again."""

    def scenario() -> Any:
        with app_on(lease=1.0) as (network, app):
            pid = simulation.start_process(serve_alone(network, "provider"), name="provider")
            until_served(network, "provider")
            heard: list[tuple[str, Any]] = []
            held = app.call(
                "provider",
                "leaf",
                "x",
                on_status=lambda query, update: heard.append((query.id, update.status)),
            )
            network.partition([pid])
            simulation.sleep(cut_for)
            during = ([s for i, s in heard if i == held.id], [q.id for q in app.client_queries()])
            network.heal()
            simulation.sleep(1.0)  # (the heal's reconciliation)
            after = app.call("provider", "leaf", "y", timeout=5.0).response
            return during == ([], [held.id]), during == ([rr.Status.FATAL], []), after

    return scenario


@pytest.mark.parametrize(("cut_for", "outcome"), [(0.5, "kept"), (2.0, "lost")])
def test_a_cut_past_the_lease_makes_each_side_hear_the_names_across_lost(
    cut_for: float, outcome: str
) -> None:
    """Rule 19 at a cut, as Zenoh's tokens say it: a cut shorter than the lease loses
    nothing; one past it makes each side hear the other's names go, so a name served
    across by a process nobody restarts is lost (its consumer hears `FATAL` and forgets
    its id), and after the heal it is reachable and answers again (rule 20)."""
    for seed in range(5):
        run = simulation.run(cut_past_the_lease(cut_for), seed=seed, preempt=0.1)
        kept, lost, after = run.value
        assert (outcome == "kept", outcome == "lost", "leaf y", ()) == (
            kept,
            lost,
            after,
            tuple(run.errors),
        ), f"seed {seed}"


def test_a_cut_past_the_lease_awaits_a_name_whose_supervisor_is_on_its_side() -> None:
    """Rule 19 at a cut: the provider is cut off, its supervisor (and its consumer `app`)
    are on the other side and hear its tokens go: awaited, not lost (its supervisor may
    restart it), so `app` keeps its id through the cut and the heal."""

    def body(supervisor: rr.Supervisor, app: rr.ResourceRegistrar, network: Any) -> Any:
        held = app.call("provider", "leaf", "x")
        network.partition([supervisor.child("provider").pid])
        simulation.sleep(2.0)  # (past the lease)
        during = [q.id for q in app.client_queries()]
        network.heal()
        simulation.sleep(1.0)
        return during == [held.id], app.call("provider", "leaf", "y", timeout=5.0).response

    for seed in range(5):
        run = simulation.run(with_provider(body, lease=1.0, heartbeat=None), seed=seed)
        assert ((True, "leaf y"), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_process_restarted_beyond_a_cut_stays_beyond_it() -> None:
    """A supervisor and its manager are cut off a consumer; the manager is killed and
    restarted by that supervisor: the new process is on its supervisor's side of the cut
    (a host's processes are), so the consumer cannot reach it until the heal."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-beyond-")
        with app_on(folder=folder) as (network, app):
            tree_pid, children = start_tree(network, folder)
            until_served(network, "provider")
            app.call("provider", "leaf", "x")
            network.partition([tree_pid, children[0]])
            simulation.kill(children[0])
            simulation.sleep(0.5)
            until_served(network, "provider")  # (restarted beyond the cut)
            try:
                app.call("provider", "leaf", "y", timeout=2.0)
            except rr.RegistrarUnavailableError:
                during = "unavailable"
            else:
                during = "answered"
            network.heal()
            simulation.sleep(1.0)
            return during, app.call("provider", "leaf", "z", timeout=5.0).response

    for seed in range(5):
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert (("unavailable", "leaf z"), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_name_awaited_across_a_cut_is_lost_once_its_supervisor_goes() -> None:
    """Rule 19 at a cut past the lease: the consumer awaits a provider cut off from it
    while the provider's supervisor, on the consumer's side, lives; once that
    supervisor's process ends, nobody will restart the provider: lost for the consumer
    (FATAL, forgotten), before the heal."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-across-")
        with app_on(lease=1.0, folder=folder, heal=True) as (network, app):
            tree_pid, children = start_tree(network, folder)
            until_served(network, "provider")
            held = app.call("provider", "leaf", "x")
            network.partition([children[0]])
            simulation.sleep(2.0)  # (past the lease: awaited)
            awaited = [q.id for q in app.client_queries()]
            simulation.kill(tree_pid)
            simulation.sleep(1.0)
            return awaited == [held.id], [q.id for q in app.client_queries()]

    for seed in range(5):
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert ((True, []), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def test_a_name_served_again_on_its_side_during_a_cut_is_no_longer_awaited_across() -> None:
    """A provider cut off past the lease is awaited by its consumer (its supervisor is
    on the consumer's side); killed beyond the cut, it is restarted by that supervisor on
    the consumer's side and serves the consumer again. Its supervisor then stopped past
    the lease does not make the live provider lost: it was no longer awaited
    (second review of session 6: the stale entry made `app` forget `y`)."""

    def scenario() -> Any:
        folder = tempfile.mkdtemp(prefix="rr-sim-again-")
        with app_on(lease=1.0, folder=folder, heal=True) as (network, app):
            tree_pid, children = start_tree(network, folder)
            until_served(network, "provider")
            app.call("provider", "leaf", "x")
            network.partition([children[0]])
            simulation.sleep(2.0)  # (past the lease: awaited across)
            simulation.kill(children[0])  # (restarted by `tree`, on `app`'s side)
            simulation.sleep(1.0)
            until_served(network, "provider")
            held = app.call("provider", "leaf", "y", timeout=5.0)
            simulation.kill(tree_pid, signal.SIGSTOP)
            simulation.sleep(2.0)  # (the speaker silent past the lease)
            kept = [q.id for q in app.client_queries()]
            simulation.kill(tree_pid, signal.SIGCONT)
            return held.id in kept

    for seed in range(3):
        run = simulation.run(scenario, seed=seed, preempt=0.1)
        assert (True, ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def kept_one_dies_during_the_yield() -> Any:
    """Rule 22's yield step, with its forced interleaving: `provider` served first by a
    process nobody supervises (kept at the heal); a second one served beyond a cut, on
    the consumer `app`'s side, holds `app`'s id; at the heal the second yields, and while
    it unloads (its `unload` waits on a gate) the kept one's process is SIGKILLed (lost
    for good, rule 19). What is left: the yielder's process alive, what a new call
    answers, whether `app` still holds its old id."""
    network = simulation.SimulatedNetwork()
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=network)
    began, gate = runtime.Event(), runtime.Event()

    def gated_unload(*_: Any) -> None:
        began.set()
        assert gate.wait(5.0)

    def gated_setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=lambda r: f"leaf {r}", unload=gated_unload)

    try:
        first = simulation.start_process(serve_alone(network, "provider"), name="kept")
        until_served(network, "provider")
        network.partition([first])
        second = simulation.start_process(
            serve_alone(network, "provider", gated_setup), name="yielder"
        )
        simulation.sleep(0.5)  # (it serves the consumer's side)
        held = app.call("provider", "leaf", "y", timeout=5.0)  # (the second one's)
        network.heal()
        assert began.wait(5.0)  # (the second one yields: it unloads what it served)
        simulation.kill(first, signal.SIGKILL)
        simulation.sleep(0.5)  # (the carrier says it is lost)
        gate.set()
        simulation.sleep(1.0)  # (the yield ends)
        alive = any(p.pid == second and p.alive for p in running_scheduler().processes)
        answer = app.call("provider", "leaf", "z", timeout=5.0).response
        return alive, answer, held.id in [q.id for q in app.client_queries()]
    finally:
        gate.set()
        try:
            app.stop()
        finally:
            network.close()


def test_a_yield_whose_kept_server_dies_before_it_ends_serves_the_name_on() -> None:
    """Rule 22, the kept one lost during the yield: the one that yields serves its name
    again once what it unloads is gone (`Messenger.lost` ─► `Endpoint.keep_name`), so
    the name is not left unserved; the consumer's id it released is FATAL and forgotten
    (rule 19 for the one lost, rule 20 with the one serving)."""
    for seed in range(10):
        run = simulation.run(kept_one_dies_during_the_yield, seed=seed, preempt=0.1)
        assert ((True, "leaf z", False), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def one_way_heal() -> Any:
    """Rule 22 after a link that heals one way: `provider` served first by `kept`, and by
    a second process beyond a cut, on the consumer `app`'s side, where `app` holds an id;
    at the heal the second one's process does not hear the first's server (`unheard`),
    the first's does. What is left: whether the second registrar still runs, what a new
    call answers, whether `app` still holds its id from the second."""
    second: list[rr.ResourceRegistrar] = []

    def setup(registrar: rr.ResourceRegistrar) -> None:
        leaf_setup(registrar)
        second.append(registrar)

    with app_on() as (network, app):
        first = simulation.start_process(serve_alone(network, "provider"), name="kept")
        until_served(network, "provider")
        network.partition([first])
        newcomer = simulation.start_process(serve_alone(network, "provider", setup), name="new")
        simulation.sleep(0.5)  # (it serves the consumer's side)
        held = app.call("provider", "leaf", "y", timeout=5.0)  # (the second one's)
        network.heal(unheard=[newcomer])
        simulation.sleep(2.0)  # (the claim, the yield, the reconcile)
        answer = app.call("provider", "leaf", "z", timeout=5.0).response
        ids = [q.id for q in app.client_queries()]
        return second[0].is_alive(), answer, held.id in ids


def test_a_newcomer_that_does_not_hear_the_kept_server_after_a_heal_is_told_and_yields() -> None:
    """Rule 22 through a link that healed one way: the process of the one kept hears the
    newcomer and tells it (a `Claim` on the name, as Zenoh's carrier puts it on the
    name's key), so the newcomer yields though it never heard the kept one's token; the
    consumer's id there is FATAL and forgotten (rule 20)."""
    for seed in range(10):
        run = simulation.run(one_way_heal, seed=seed, preempt=0.1)
        assert ((False, "leaf z", False), ()) == (run.value, tuple(run.errors)), f"seed {seed}"


def kept_one_dies_at_the_heal() -> Any:
    """`provider` served first by a process nobody supervises, and beyond a cut by a
    second, on the consumer `app`'s side, where `app` holds an id whose unload waits on a
    gate; the first's process is SIGKILLed in the step of the heal, before the second's
    process hears of the first (no choice point between). What a call answers then."""
    network = simulation.SimulatedNetwork()
    app = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="app"), network=network)
    gate = runtime.Event()

    def gated_setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server(
            "leaf", load=lambda r: f"leaf {r}", unload=lambda *_: gate.wait(5.0)
        )

    try:
        first = simulation.start_process(serve_alone(network, "provider"), name="kept")
        until_served(network, "provider")
        network.partition([first])
        simulation.start_process(serve_alone(network, "provider", gated_setup), name="second")
        simulation.sleep(0.5)  # (it serves the consumer's side)
        app.call("provider", "leaf", "y", timeout=5.0)  # (the second one's)
        network.heal()
        simulation.kill(first, signal.SIGKILL)
        simulation.sleep(0.5)  # (the second yields to it, and hears it lost)
        gate.set()
        simulation.sleep(1.0)
        return app.call("provider", "leaf", "z", timeout=5.0).response
    finally:
        gate.set()
        try:
            app.stop()
        finally:
            network.close()


def test_a_kept_server_that_dies_before_the_other_hears_of_it_leaves_the_name_served() -> None:
    """Rule 22: the one kept at a heal dies before the other's process hears of it. As
    Zenoh's presence does (it applies the kept one's token, then its end), the other
    yields to it, then hears it lost during its yield, and serves on."""
    for seed in range(10):
        run = simulation.run(kept_one_dies_at_the_heal, seed=seed, preempt=0.1)
        assert ("leaf z", ()) == (run.value, tuple(run.errors)), f"seed {seed}"
