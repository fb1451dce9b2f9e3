"""Registrars on two hosts over the Zenoh carrier (issue 22), in two real network namespaces.

Each host has a worker with one `ZenohNetwork` of the system "lab" (`hosts.rr_join`); host
`a` serves `erm` (the provider) and `app-a`, host `b` serves `app-b` and `cm` (whose
`filtered` depends on `erm`'s camera); `b` connects to `a`. The tests that leave the hosts
as they found them share one `shared` lab (a module fixture: each test uses devices of its
own); those that kill a process or cut the link get a `lab` of their own. The bounds are the
issue's, with the default lease (1 s), each asserted on a clock around the event waited for:
what a worker's callbacks record (with `time.monotonic()`, one clock for every process of
the machine, whatever its namespace) stays in the worker (`hosts.KEPT`) and is read back
with `call`.

Bad input (a malformed endpoint, a bad system name, `tls` omitted, a peer of another
version) needs no second host: `tests/transport/zenoh/test_carrier.py`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import queue
import signal
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from tests.support import hosts

SYSTEM = "lab"
PORT = 7447


# -- what runs in the workers ------------------------------------------------------------------


def provider_setup(registrar: rr.ResourceRegistrar) -> None:
    """`camera` records its loads and unloads; `hang` blocks its load until the gate opens."""
    kept = hosts.KEPT
    kept.update(
        loads=[],
        unloads=queue.Queue(),
        unloaded_all=[],
        gate=threading.Event(),
        hang_started=threading.Event(),
    )

    def load(request: Any) -> Any:
        kept["loads"].append(request)
        return {"stream": request}

    def unload(request: Any, _response: Any) -> None:
        kept["unloaded_all"].append(request)
        kept["unloads"].put(request)

    def hang(request: Any) -> Any:
        kept["hang_started"].set()
        kept["gate"].wait(30)
        return request

    registrar.register_server("camera", load=load, unload=unload)
    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)
    registrar.register_server("probe", load=lambda request: request, unload=lambda _q, _r: None)


def call_camera(registrar: rr.ResourceRegistrar, device: int, timeout: float = 10.0) -> str:
    query = registrar.call(
        "erm", "camera", {"device": device}, on_status=hosts.record_status, timeout=timeout
    )
    return query.id


def call_hang(registrar: rr.ResourceRegistrar) -> str:
    return registrar.call("erm", "hang", "r", timeout=30).id


def unload(registrar: rr.ResourceRegistrar, query_id: str) -> None:
    registrar.unload(query_id)


def held(registrar: rr.ResourceRegistrar) -> list[str]:
    return [query.id for query in registrar.client_queries()]


def loads_of(device: int) -> int:
    return hosts.KEPT["loads"].count({"device": device})


def unloads_of(device: int) -> int:
    return hosts.KEPT["unloaded_all"].count({"device": device})


def unloaded(request: Any, timeout: float) -> float:
    """When `request` was unloaded (`TimeoutError` if it is not within `timeout`)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            seen = hosts.KEPT["unloads"].get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise TimeoutError(f"{request!r} was not unloaded within {timeout:g} s") from None
        if seen == request:
            return time.monotonic()


def cm_setup(registrar: rr.ResourceRegistrar) -> None:
    """`filtered` depends on the camera of `erm`, on the other host; its server's
    `on_status` records what reaches it in `KEPT["server_heard"]`."""
    heard: queue.Queue[Any] = queue.Queue()
    hosts.KEPT["server_heard"] = heard

    def load(request: Any) -> Any:
        return registrar.call("erm", "camera", request, timeout=10).response

    registrar.register_server(
        "filtered",
        load=load,
        unload=lambda _q, _r: None,
        on_status=lambda _query, update: heard.put(
            (update.status.name, update.source, time.monotonic())
        ),
    )


def call_filtered(registrar: rr.ResourceRegistrar, device: int) -> str:
    return registrar.call(
        "cm", "filtered", {"device": device}, on_status=hosts.record_status, timeout=10
    ).id


def server_heard(timeout: float) -> tuple[str, str, float]:
    try:
        got: tuple[str, str, float] = hosts.KEPT["server_heard"].get(timeout=timeout)
    except queue.Empty:
        raise TimeoutError(f"no status at the server within {timeout:g} s") from None
    return got


def more_server_heard() -> int:
    return int(hosts.KEPT["server_heard"].qsize())


def call_dup(registrar: rr.ResourceRegistrar) -> str:
    return registrar.call("dup", "probe", 7, timeout=10).id


def stop_registrar(name: str) -> None:
    hosts.KEPT["registrars"].pop(name).stop()


def until_stopped(registrar: rr.ResourceRegistrar, name: str, timeout: float) -> None:
    """Call `name`/probe until it fails with `RegistrarStoppedError` (each failure or
    answer is immediate: a retry, not a sleep): this process saw it stop."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            registrar.unload(registrar.call(name, "probe", 1, timeout=5).id)
        except rr.RegistrarStoppedError:
            return
    raise TimeoutError(f"{name} was not seen stopped within {timeout:g} s")


# -- the test's side ---------------------------------------------------------------------------


@dataclasses.dataclass
class Lab:
    """The two hosts, the provider's worker on `a`, the consumers' worker on `b`."""

    net: hosts.TwoHosts
    a: hosts.Worker
    b: hosts.Worker


@contextlib.contextmanager
def made_lab(two_hosts: hosts.TwoHosts) -> Iterator[Lab]:
    a, b = two_hosts.a.spawn(), two_hosts.b.spawn()
    here, there = two_hosts.a.endpoint(PORT), two_hosts.b.endpoint(PORT)
    a.call(hosts.rr_join, system=SYSTEM, listen=[here], connect=[], timeout=30)
    a.call(hosts.rr_start, "erm", provider_setup, timeout=30)
    a.call(hosts.rr_start, "app-a", timeout=30)
    b.call(hosts.rr_join, system=SYSTEM, listen=[there], connect=[here], timeout=30)
    b.call(hosts.rr_start, "app-b", timeout=30)
    b.call(hosts.rr_until_answered, "app-b", "erm", "probe", 15.0, timeout=30)
    try:
        yield Lab(two_hosts, a, b)
    finally:
        if a.alive:
            with contextlib.suppress(Exception):
                a.call(hosts.open_gate, timeout=5)  # (a load still held at the gate ends)
        for worker in (b, a):
            if worker.alive:
                with contextlib.suppress(Exception):
                    worker.call(hosts.rr_stop, timeout=30)


@pytest.fixture
def lab(two_hosts: hosts.TwoHosts) -> Iterator[Lab]:
    """A lab of this test's own (it kills a process or cuts the link)."""
    with made_lab(two_hosts) as made:
        yield made


@pytest.fixture(scope="module")
def shared() -> Iterator[Lab]:
    """One lab for the tests that leave it as they found it (`cm` on `b` too)."""
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    with hosts.TwoHosts() as two_hosts, made_lab(two_hosts) as made:
        made.b.call(hosts.rr_start, "cm", cm_setup, timeout=30)
        yield made


def test_equal_calls_from_both_hosts_load_once_and_unload_when_the_last_lets_go(
    shared: Lab,
) -> None:
    from_a = shared.a.call(hosts.rr_run, "app-a", call_camera, 0, timeout=15)
    from_b = shared.b.call(hosts.rr_run, "app-b", call_camera, 0, timeout=15)
    assert 1 == shared.a.call(loads_of, 0, timeout=5)

    shared.b.call(hosts.rr_run, "app-b", unload, from_b, timeout=10)
    assert 0 == shared.a.call(unloads_of, 0, timeout=5)  # app-a still holds it
    shared.a.call(hosts.rr_run, "app-a", unload, from_a, timeout=10)

    shared.a.call(unloaded, {"device": 0}, 5.0, timeout=10)
    assert from_a != from_b
    assert 1 == shared.a.call(unloads_of, 0, timeout=5)
    with pytest.raises(rr.UnknownQueryError):  # released: its id is unknown
        shared.b.call(hosts.rr_run, "app-b", unload, from_b, timeout=10)


def test_concurrent_equal_calls_from_both_hosts_load_once(shared: Lab) -> None:
    from_a = shared.a.submit(hosts.rr_run, "app-a", call_camera, 1)
    from_b = shared.b.submit(hosts.rr_run, "app-b", call_camera, 1)

    ids = [from_a.result(15), from_b.result(15)]

    assert 2 == len(set(ids))
    assert 1 == shared.a.call(loads_of, 1, timeout=5)
    shared.a.call(hosts.rr_run, "app-a", unload, ids[0], timeout=10)
    shared.b.call(hosts.rr_run, "app-b", unload, ids[1], timeout=10)
    shared.a.call(unloaded, {"device": 1}, 5.0, timeout=10)


def test_a_status_sent_on_host_a_reaches_every_callback_on_both_hosts_once(shared: Lab) -> None:
    # erm/camera (a) <- cm/filtered (b) <- app-a (a), and <- app-b (b) directly (a dedup hit
    # of cm's own call): one status goes up every path, across the veth twice for app-a.
    via_cm = shared.a.call(hosts.rr_run, "app-a", call_filtered, 2, timeout=15)
    direct = shared.b.call(hosts.rr_run, "app-b", call_camera, 2, timeout=15)
    assert 1 == shared.a.call(loads_of, 2, timeout=5)

    sent = shared.a.call(hosts.rr_run, "erm", hosts.send_warning, 2, timeout=10)

    query_b, status_b, source_b, at_b = shared.b.call(hosts.next_status, 5.0, timeout=10)
    status_cm, source_cm, at_cm = shared.b.call(server_heard, 5.0, timeout=10)
    query_a, status_a, source_a, at_a = shared.a.call(hosts.next_status, 5.0, timeout=10)
    assert (direct, "WARNING", "erm/camera") == (query_b, status_b, source_b)
    assert ("WARNING", "erm/camera") == (status_cm, source_cm)
    assert (via_cm, "WARNING", "erm/camera") == (query_a, status_a, source_a)
    assert max(at_a, at_b, at_cm) - sent < 5.0
    assert [0, 0, 0] == [
        shared.a.call(hosts.more_statuses, timeout=5),
        shared.b.call(hosts.more_statuses, timeout=5),
        shared.b.call(more_server_heard, timeout=5),
    ]
    shared.a.call(hosts.rr_run, "app-a", unload, via_cm, timeout=10)
    shared.b.call(hosts.rr_run, "app-b", unload, direct, timeout=10)
    shared.a.call(unloaded, {"device": 2}, 5.0, timeout=10)


def test_a_name_served_on_the_other_host_cannot_be_started_again(shared: Lab) -> None:
    shared.a.call(hosts.rr_start, "dup", provider_setup, timeout=30)

    with pytest.raises(rr.DuplicateNameError):
        shared.b.call(hosts.rr_start, "dup", None, timeout=15)

    # calls from there still reach the remote one
    reached = shared.b.call(hosts.rr_run, "app-b", call_dup, timeout=15)
    shared.b.call(hosts.rr_run, "app-b", unload, reached, timeout=10)
    # nothing left behind: once the remote one stopped, the name is free there
    shared.a.call(stop_registrar, "dup", timeout=30)
    shared.b.call(hosts.rr_run, "app-b", until_stopped, "dup", 10.0, timeout=15)
    shared.b.call(hosts.rr_start, "dup", None, timeout=15)
    shared.b.call(stop_registrar, "dup", timeout=30)


def test_a_call_to_a_name_of_another_system_fails_at_once_naming_the_callers_system(
    shared: Lab,
) -> None:
    other = shared.net.b.spawn()
    try:
        other.call(
            hosts.rr_join,
            system="other",
            listen=[shared.net.b.endpoint(PORT + 1)],
            connect=[shared.net.a.endpoint(PORT)],
            timeout=30,
        )
        other.call(hosts.rr_start, "app-c", timeout=30)

        started = time.monotonic()
        with pytest.raises(rr.UnknownRegistrarError, match="system 'other'"):
            other.call(hosts.rr_run, "app-c", call_camera, 8, timeout=15)

        assert time.monotonic() - started < 2.0
        assert 0 == shared.a.call(loads_of, 8, timeout=5)
    finally:
        other.call(hosts.rr_stop, timeout=30)
        other.stop()


# -- a process killed, a link cut --------------------------------------------------------------


def test_a_sigkill_of_the_providers_process_fails_calls_at_once_and_its_ids_are_fatal(
    lab: Lab,
) -> None:
    held_id = lab.b.call(hosts.rr_run, "app-b", call_camera, 3, timeout=15)
    in_flight = lab.b.submit(hosts.rr_run, "app-b", call_hang)
    assert lab.a.call(hosts.wait_set, "hang_started", 10.0, timeout=15)

    killed = time.monotonic()
    os.kill(lab.a.pid, signal.SIGKILL)

    with pytest.raises(rr.RegistrarUnavailableError):
        in_flight.result(5)
    assert time.monotonic() - killed < 1.0
    query_id, status, source, fatal_at = lab.b.call(hosts.next_status, 5.0, timeout=10)
    assert (held_id, "FATAL", "erm/camera") == (query_id, status, source)
    assert fatal_at - killed < 1.0
    assert held_id not in lab.b.call(hosts.rr_run, "app-b", held, timeout=5)
    started = time.monotonic()
    with pytest.raises(rr.RegistrarUnavailableError):
        lab.b.call(hosts.rr_run, "app-b", call_camera, 4, timeout=15)
    assert time.monotonic() - started < 1.0


def test_a_cut_link_fails_calls_and_a_healed_one_releases_what_the_consumer_forgot(
    lab: Lab,
) -> None:
    held_id = lab.b.call(hosts.rr_run, "app-b", call_camera, 5, timeout=15)
    in_flight = lab.b.submit(hosts.rr_run, "app-b", call_hang)
    assert lab.a.call(hosts.wait_set, "hang_started", 10.0, timeout=15)

    cut = time.monotonic()
    lab.net.link_down()
    with pytest.raises(rr.RegistrarUnavailableError):
        in_flight.result(5)
    assert time.monotonic() - cut < 2.0
    query_id, status, source, fatal_at = lab.b.call(hosts.next_status, 5.0, timeout=10)
    assert (held_id, "FATAL", "erm/camera") == (query_id, status, source)
    assert fatal_at - cut < 2.0  # erm is not supervised: lost (rule 4)
    assert held_id not in lab.b.call(hosts.rr_run, "app-b", held, timeout=5)
    for device in (6, 7):  # each call during the cut fails at once
        started = time.monotonic()
        with pytest.raises(rr.RegistrarUnavailableError):
            lab.b.call(hosts.rr_run, "app-b", call_camera, device, timeout=15)
        assert time.monotonic() - started < 1.0

    healed = time.monotonic()
    lab.net.link_up()
    lab.a.call(hosts.open_gate, timeout=5)
    lab.b.call(hosts.rr_until_answered, "app-b", "erm", "probe", 10.0, timeout=15)
    assert time.monotonic() - healed < 10.0
    lab.a.call(unloaded, {"device": 5}, 10.0, timeout=15)  # (at the cut or once healed)
    again = lab.b.call(hosts.rr_run, "app-b", call_camera, 5, timeout=15)  # loads anew
    lab.b.call(hosts.rr_run, "app-b", unload, again, timeout=10)
    lab.a.call(unloaded, {"device": 5}, 10.0, timeout=15)
    assert [2, 2] == [lab.a.call(loads_of, 5, timeout=5), lab.a.call(unloads_of, 5, timeout=5)]
    assert 0 == lab.b.call(hosts.more_statuses, timeout=5)  # nothing FATAL after the heal


# -- one name, one registrar, through cuts and heals (rule 22) ---------------------------------


def yielded_within(name: str, timeout: float) -> float:
    """When this worker's registrar `name` stopped (`TimeoutError` if it does not within
    `timeout` seconds)."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    registrar = hosts.KEPT["registrars"][name]
    if not wait_for(lambda: not registrar.is_alive(), timeout):
        raise TimeoutError(f"registrar {name} still runs after {timeout:g} s")
    return time.monotonic()


def unloaded_each(devices: list[int], timeout: float) -> bool:
    """Whether the camera of each of `devices` is unloaded within `timeout` seconds (in
    whatever order: `unloaded` takes the first of its queue)."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    return bool(wait_for(lambda: all(unloads_of(d) for d in devices), timeout))


def router_address() -> Any:
    """This worker's `ZenohNetwork.address`: how a process of its host attaches."""
    return hosts.KEPT["network"].address


def rr_attach(address: Any) -> None:
    """Join the system through the router at `address` (a client process, as a manager
    process attaches), keeping the log as `hosts.rr_join` does."""
    import logging  # noqa: PLC0415

    records: list[tuple[str, str]] = []
    hosts.KEPT["logs"] = records

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append((record.levelname, record.getMessage()))

    log = logging.getLogger("rr_actors")
    log.addHandler(Keep(logging.INFO))
    log.setLevel(min(log.getEffectiveLevel(), logging.INFO))
    hosts.KEPT["network"] = address.attach()
    hosts.KEPT["registrars"] = {}


def names_seen() -> list[str]:
    return list(hosts.KEPT["network"].names())


def wait_served(name: str, timeout: float) -> None:
    hosts.KEPT["network"].wait_for(name, timeout=timeout)


def call_error(registrar: rr.ResourceRegistrar, device: int) -> str:
    """`call_camera`'s error, as `"<class>: <message>"` (`"answered"` if none)."""
    try:
        call_camera(registrar, device, timeout=10)
    except rr.RrError as exc:
        return f"{type(exc).__name__}: {exc}"
    return "answered"


@pytest.mark.timeout(120)
def test_a_name_served_on_both_sides_of_a_cut_is_kept_on_one_after_the_heal(lab: Lab) -> None:
    kept = lab.a.call(hosts.rr_run, "app-a", call_camera, 100, timeout=15)
    lab.net.link_down()
    assert lab.b.call(hosts.rr_unlinked_within, "erm", 10.0, timeout=15)
    assert lab.a.call(hosts.rr_unlinked_within, "app-b", 10.0, timeout=15)
    # erm is lost on b's side (not supervised, rule 19): b may serve the name there
    lab.b.call(hosts.rr_start, "erm", provider_setup, timeout=30)
    during = [lab.b.call(hosts.rr_run, "app-b", call_camera, d, timeout=15) for d in (100, 102)]
    assert [1, 1] == [lab.b.call(loads_of, d, timeout=5) for d in (100, 102)]

    healed = time.monotonic()
    lab.net.link_up()

    # exactly one serves: a's, served first; b's yields (an ERROR), unloads what it served
    assert lab.b.call(yielded_within, "erm", 30.0, timeout=35) - healed < 30.0
    assert lab.b.call(unloaded_each, [100, 102], 10.0, timeout=15)
    errors = lab.b.call(hosts.rr_logs, "ERROR", timeout=5)
    assert 1 == len(errors), errors
    assert errors[0].startswith("registrar 'erm' of system 'lab' is served by process ")
    assert "this one stops serving" in errors[0]
    # app-b's ids were held at the erm that yielded: the one kept does not hold them
    fatal = [lab.b.call(hosts.next_status, 15.0, timeout=20) for _ in during]
    assert sorted((query_id, "FATAL") for query_id in during) == sorted(
        (query_id, status) for query_id, status, _source, _at in fatal
    )
    assert [] == lab.b.call(hosts.rr_run, "app-b", held, timeout=5)
    # from both hosts, erm is a's now: device 100 is a dedup hit there, loaded once
    again = lab.b.call(hosts.rr_run, "app-b", call_camera, 100, timeout=15)
    assert [1, 0] == [lab.a.call(loads_of, 100, timeout=5), lab.a.call(unloads_of, 100, timeout=5)]
    assert [1, 1] == [lab.b.call(loads_of, 100, timeout=5), lab.b.call(unloads_of, 100, timeout=5)]
    assert [0, 1, 1] == [
        lab.a.call(loads_of, 102, timeout=5),
        lab.b.call(loads_of, 102, timeout=5),
        lab.b.call(unloads_of, 102, timeout=5),
    ]
    assert "erm" in lab.b.call(names_seen, timeout=5)
    lab.b.call(hosts.rr_run, "app-b", unload, again, timeout=10)
    lab.a.call(hosts.rr_run, "app-a", unload, kept, timeout=10)
    lab.a.call(unloaded, {"device": 100}, 10.0, timeout=15)
    assert 0 == lab.b.call(hosts.more_statuses, timeout=5)


@pytest.mark.timeout(120)
def test_a_process_whose_router_was_killed_serves_no_name(lab: Lab) -> None:
    client = lab.net.b.spawn()
    try:
        client.call(rr_attach, lab.b.call(router_address, timeout=10), timeout=30)
        client.call(hosts.rr_start, "app-c", timeout=30)
        client.call(hosts.rr_until_answered, "app-c", "erm", "probe", 15.0, timeout=30)
        lab.b.kill()  # b's router: SIGKILL
        fresh = lab.net.b.spawn()  # a new router on b serves the system's names again
        fresh.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[lab.net.b.endpoint(PORT + 1)],
            connect=[lab.net.a.endpoint(PORT)],
            timeout=30,
        )
        fresh.call(wait_served, "erm", 15.0, timeout=20)  # (its link to a is up)

        called = client.call(hosts.rr_run, "app-c", call_error, 104, timeout=30)
        started = time.monotonic()
        with pytest.raises(rr.RegistrarUnavailableError) as refused:
            client.call(hosts.rr_start, "erm", provider_setup, timeout=30)
        took = time.monotonic() - started
        warned = client.call(hosts.rr_logs, "WARNING", timeout=5)
    finally:
        with contextlib.suppress(Exception):
            client.call(hosts.rr_stop, timeout=30)
        client.stop()

    assert str(refused.value).startswith(
        "cannot tell whether another process of system 'lab' serves a registrar named 'erm', "
        "so this process does not serve it: this process's router (process "
    )
    assert called.startswith("RegistrarUnavailableError: ")
    assert took < 5.0  # (at once: it knows its router is gone; not after asking for 5 s)
    assert any("this process lost its link to its router" in line for line in warned), warned
    assert 0 == lab.a.call(loads_of, 104, timeout=5)
    assert ["erm"] == [n for n in fresh.call(names_seen, timeout=5) if n == "erm"]


# -- a supervisor on each host -----------------------------------------------------------------


def start_tree(
    manager: str,
    setup: Any,
    state_dir: str,
    consumer: str | None = None,
    restart: str = "permanent",
) -> None:
    """A supervisor in this worker with one process manager, on the worker's network."""
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=setup, isolation="process", restart=restart)],  # type: ignore[arg-type]
        state_dir=state_dir,
        network=hosts.KEPT["network"],
    )
    sup.start()
    hosts.KEPT["sup"] = sup
    if consumer is not None:
        hosts.KEPT["registrars"][consumer] = sup.registrar(consumer)


def wait_restarted(name: str, timeout: float) -> float:
    hosts.KEPT["sup"].wait_restarted(name, timeout=timeout)
    return time.monotonic()


def run_in(name: str, fn: Any, *args: Any) -> Any:
    return hosts.KEPT["sup"].run_in(name, lambda registrar: fn(registrar, *args), timeout=15)


def in_manager(_registrar: rr.ResourceRegistrar, fn: Any, *args: Any) -> Any:
    """`fn(*args)` in a manager's process (its own `hosts.KEPT`)."""
    return fn(*args)


def until_filtered(
    registrar: rr.ResourceRegistrar, device: int, timeout: float
) -> tuple[str, float]:
    """`call_filtered` until it succeeds (each failure is immediate: a retry, not a sleep);
    its id, and when it succeeded."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            query_id = call_filtered(registrar, device)
        except rr.RegistrarUnavailableError:
            if time.monotonic() > deadline:
                raise
        else:
            return query_id, time.monotonic()


@pytest.mark.timeout(120)
def test_a_supervised_manager_killed_on_one_host_comes_back_without_fatal_for_the_other(
    two_hosts: hosts.TwoHosts,
) -> None:
    a, b = two_hosts.a.spawn(), two_hosts.b.spawn()
    here, there = two_hosts.a.endpoint(PORT), two_hosts.b.endpoint(PORT)
    a.call(hosts.rr_join, system=SYSTEM, listen=[here], connect=[], timeout=30)
    b.call(hosts.rr_join, system=SYSTEM, listen=[there], connect=[here], timeout=30)
    a.call(start_tree, "erm", provider_setup, str(two_hosts.directory / "a"), timeout=60)
    b.call(start_tree, "cm", cm_setup, str(two_hosts.directory / "b"), "app-b", timeout=60)
    try:
        before, _ = b.call(hosts.rr_run, "app-b", until_filtered, 9, 15.0, timeout=30)

        os.kill(a.call(hosts.manager_pid, "erm", timeout=10), signal.SIGKILL)
        restarted = a.call(wait_restarted, "erm", 10.0, timeout=15)
        _, answered = b.call(hosts.rr_run, "app-b", until_filtered, 10, 10.0, timeout=15)

        assert answered - restarted < 10.0
        assert 0 == b.call(hosts.more_statuses, timeout=5)  # no FATAL: erm was not lost
        # its restored catalog kept cm's id (rule 15): released there when app-b lets go
        b.call(hosts.rr_run, "app-b", unload, before, timeout=10)
        a.call(run_in, "erm", in_manager, unloaded, {"device": 9}, 10.0, timeout=20)
    finally:
        b.call(hosts.stop_tree, timeout=60)
        a.call(hosts.stop_tree, timeout=60)


@pytest.mark.timeout(120)
def test_a_consumer_on_host_b_that_dies_for_good_has_its_ids_released_on_host_a(
    shared: Lab,
) -> None:
    # Rule 7: a temporary process manager on b is not restarted; its supervisor's death
    # watch reaches erm on a (its token alone says "supervised": not lost by presence).
    tree = shared.net.b.spawn()
    try:
        tree.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[shared.net.b.endpoint(PORT + 2)],
            connect=[shared.net.a.endpoint(PORT)],
            timeout=30,
        )
        state_dir = str(shared.net.directory / "dies")
        tree.call(start_tree, "app-t", None, state_dir, None, "temporary", timeout=60)
        tree.call(run_in, "app-t", call_camera, 20, timeout=30)
        assert 1 == shared.a.call(loads_of, 20, timeout=5)

        killed = time.monotonic()
        os.kill(tree.call(hosts.manager_pid, "app-t", timeout=10), signal.SIGKILL)
        released = shared.a.call(unloaded, {"device": 20}, 10.0, timeout=15)

        assert released - killed < 5.0
        assert 1 == shared.a.call(unloads_of, 20, timeout=5)
    finally:
        with contextlib.suppress(Exception):
            tree.call(hosts.stop_tree, timeout=60)
        with contextlib.suppress(Exception):
            tree.call(hosts.rr_stop, timeout=30)
        tree.stop()
    assert 1 == shared.a.call(unloads_of, 20, timeout=5)


# -- rule 22: the one kept dies while the other yields -----------------------------------------


def gated_setup(registrar: rr.ResourceRegistrar) -> None:
    """`provider_setup`, and `slow`, whose unload says it began and waits for its gate."""
    provider_setup(registrar)
    kept = hosts.KEPT
    kept.update(slow_began=threading.Event(), slow_gate=threading.Event())

    def unload(_request: Any, _response: Any) -> None:
        kept["slow_began"].set()
        kept["slow_gate"].wait(30)

    registrar.register_server("slow", load=lambda request: request, unload=unload)


def call_slow(registrar: rr.ResourceRegistrar) -> str:
    return registrar.call("erm", "slow", "s", timeout=10).id


def wait_kept(key: str, timeout: float) -> bool:
    return bool(hosts.KEPT[key].wait(timeout))


def set_kept(key: str) -> None:
    hosts.KEPT[key].set()


def serves_here(name: str) -> bool:
    """Whether this worker's network serves registrar `name` (from this process)."""
    return hosts.KEPT["network"].serving(name) is not None


@pytest.mark.timeout(120)
def test_a_yield_whose_kept_server_dies_before_it_ends_serves_the_name_on(lab: Lab) -> None:
    """Rule 22's yield, the one kept lost meanwhile (forced: the yielder's unload waits on a
    gate until the kept one's process is SIGKILLed): the one that yields serves its name
    again once its unload is done, so a process that joins later finds it served."""
    lab.net.link_down()
    assert lab.b.call(hosts.rr_unlinked_within, "erm", 10.0, timeout=15)
    lab.b.call(hosts.rr_start, "erm", gated_setup, timeout=30)  # (erm is lost on b's side)
    lab.b.call(hosts.rr_run, "app-b", call_slow, timeout=15)
    lab.net.link_up()
    assert lab.b.call(wait_kept, "slow_began", 30.0, timeout=35)  # b's erm yields
    assert not lab.b.call(serves_here, "erm", timeout=5)
    lab.a.kill()  # the kept erm's process (and a's router): nobody restarts it
    assert lab.b.call(hosts.rr_unlinked_within, "erm", 10.0, timeout=15)
    lab.b.call(set_kept, "slow_gate", timeout=5)  # (the yield's unload ends)

    fresh = lab.net.a.spawn()  # a process that joins after all this
    try:
        fresh.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[lab.net.a.endpoint(PORT + 1)],
            connect=[lab.net.b.endpoint(PORT)],
            timeout=30,
        )
        fresh.call(hosts.rr_start, "app-c", timeout=30)
        fresh.call(hosts.rr_until_answered, "app-c", "erm", "probe", 15.0, timeout=30)
    finally:
        with contextlib.suppress(Exception):
            fresh.call(hosts.rr_stop, timeout=30)
        fresh.stop()
    assert lab.b.call(serves_here, "erm", timeout=5)
    warned = lab.b.call(hosts.rr_logs, "WARNING", timeout=5)
    assert any("serves again" in line for line in warned), warned
