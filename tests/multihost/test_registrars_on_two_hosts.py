"""Registrars on two hosts over the Zenoh carrier (issue 22), in two real network namespaces.

Written against issue 22's public API before its carrier landed: the whole module is skipped,
saying so, until `rr.ZenohNetwork` exists, and then runs as is. Each host has one worker with
one `ZenohNetwork` of the system "lab" (`hosts.rr_join`); host `a` serves `erm` (the provider)
and `app-a`, host `b` serves `app-b`; `b` connects to `a`. The bounds are the issue's, with the
default lease (1 s). What a worker's callbacks record stays in the worker (`hosts.KEPT`) and is
read back with `call`.
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

import hosts
import pytest

import rr_actors as rr

pytestmark = pytest.mark.skipif(
    not hosts.has_carrier(),
    reason="rr.ZenohNetwork (issue 22's carrier) or ResourceRegistrar.start(..., network=) "
    "has not landed yet",
)

SYSTEM = "lab"
PORT = 7447


# -- what runs in the workers ------------------------------------------------------------------


def provider_setup(registrar: rr.ResourceRegistrar) -> None:
    """`camera` records its loads and unloads; `hang` blocks its load until the gate opens."""
    kept = hosts.KEPT
    kept.update(
        loads=[],
        unloads=queue.Queue(),
        gate=threading.Event(),
        hang_started=threading.Event(),
    )

    def load(request: Any) -> Any:
        kept["loads"].append(request)
        return {"stream": request}

    def hang(request: Any) -> Any:
        kept["hang_started"].set()
        kept["gate"].wait(30)
        return request

    registrar.register_server(
        "camera", load=load, unload=lambda request, _response: kept["unloads"].put(request)
    )
    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)
    registrar.register_server("probe", load=lambda request: request, unload=lambda _q, _r: None)


def record_status(query: rr.Query, update: rr.StatusUpdate) -> None:
    """A consumer's status callback: (its query id, status name, source) into `KEPT`."""
    hosts.KEPT.setdefault("heard", queue.Queue()).put((query.id, update.status.name, update.source))


def call_camera(registrar: rr.ResourceRegistrar, device: int, timeout: float = 10.0) -> str:
    query = registrar.call(
        "erm", "camera", {"device": device}, on_status=record_status, timeout=timeout
    )
    return query.id


def call_hang(registrar: rr.ResourceRegistrar) -> str:
    return registrar.call("erm", "hang", "r", timeout=30).id


def unload(registrar: rr.ResourceRegistrar, query_id: str) -> None:
    registrar.unload(query_id)


def held(registrar: rr.ResourceRegistrar) -> list[str]:
    return [query.id for query in registrar.client_queries()]


def send_warning(registrar: rr.ResourceRegistrar) -> None:
    query_id = registrar.server_queries("camera")[0].id
    registrar.send_status(query_id, rr.Status.WARNING, "hot", timeout=5)


def loads() -> list[Any]:
    return list(hosts.KEPT["loads"])


def wait_set(name: str, timeout: float) -> bool:
    return bool(hosts.KEPT[name].wait(timeout))


def open_gate() -> None:
    hosts.KEPT["gate"].set()


def next_status(timeout: float) -> tuple[str, str, str]:
    """The next status a consumer's callback recorded (`TimeoutError` if none came)."""
    heard: queue.Queue[tuple[str, str, str]] = hosts.KEPT.setdefault("heard", queue.Queue())
    try:
        return heard.get(timeout=timeout)
    except queue.Empty:
        raise TimeoutError(f"no status within {timeout:g} s") from None


def more_statuses() -> int:
    heard: queue.Queue[Any] = hosts.KEPT.setdefault("heard", queue.Queue())
    return heard.qsize()


def unloaded(request: Any, timeout: float) -> list[Any]:
    """Every request unloaded until `request` is (`TimeoutError` if it is not within `timeout`)."""
    deadline = time.monotonic() + timeout
    seen = []
    while request not in seen:
        try:
            seen.append(hosts.KEPT["unloads"].get(timeout=max(0.0, deadline - time.monotonic())))
        except queue.Empty:
            raise TimeoutError(f"{request!r} was not unloaded within {timeout:g} s") from None
    return seen


# -- the test's side ---------------------------------------------------------------------------


@dataclasses.dataclass
class Lab:
    """The two hosts, the provider's worker on `a`, the consumer's worker on `b`."""

    net: hosts.TwoHosts
    a: hosts.Worker
    b: hosts.Worker


@pytest.fixture
def lab(two_hosts: hosts.TwoHosts) -> Iterator[Lab]:
    a, b = two_hosts.a.spawn(), two_hosts.b.spawn()
    here, there = two_hosts.a.endpoint(PORT), two_hosts.b.endpoint(PORT)
    a.call(hosts.rr_join, system=SYSTEM, listen=[here], connect=[], timeout=30)
    a.call(hosts.rr_start, "erm", provider_setup, timeout=30)
    a.call(hosts.rr_start, "app-a", timeout=30)
    b.call(hosts.rr_join, system=SYSTEM, listen=[there], connect=[here], timeout=30)
    b.call(hosts.rr_start, "app-b", timeout=30)
    b.call(hosts.rr_until_answered, "app-b", "erm", "probe", 15.0, timeout=30)
    yield Lab(two_hosts, a, b)
    if a.alive:
        with contextlib.suppress(Exception):
            a.call(open_gate, timeout=5)  # (a load still held at the gate ends)
    for worker in (b, a):
        if worker.alive:
            with contextlib.suppress(Exception):
                worker.call(hosts.rr_stop, timeout=30)


def test_equal_calls_from_both_hosts_load_once_and_unload_when_the_last_lets_go(lab: Lab) -> None:
    from_a = lab.a.call(hosts.rr_run, "app-a", call_camera, 0, timeout=15)
    from_b = lab.b.call(hosts.rr_run, "app-b", call_camera, 0, timeout=15)
    assert [{"device": 0}] == lab.a.call(loads, timeout=5)

    lab.b.call(hosts.rr_run, "app-b", unload, from_b, timeout=10)
    lab.a.call(hosts.rr_run, "app-a", unload, from_a, timeout=10)

    assert [{"device": 0}] == lab.a.call(unloaded, {"device": 0}, 5.0, timeout=10)
    assert from_a != from_b


def test_concurrent_equal_calls_from_both_hosts_load_once(lab: Lab) -> None:
    from_a = lab.a.submit(hosts.rr_run, "app-a", call_camera, 1)
    from_b = lab.b.submit(hosts.rr_run, "app-b", call_camera, 1)

    ids = {from_a.result(15), from_b.result(15)}

    assert 2 == len(ids)
    assert [{"device": 1}] == lab.a.call(loads, timeout=5)


def test_a_status_sent_on_host_a_reaches_the_consumer_on_host_b_once(lab: Lab) -> None:
    held_id = lab.b.call(hosts.rr_run, "app-b", call_camera, 2, timeout=15)

    lab.a.call(hosts.rr_run, "erm", send_warning, timeout=10)

    assert (held_id, "WARNING", "erm/camera") == lab.b.call(next_status, 5.0, timeout=10)
    assert 0 == lab.b.call(more_statuses, timeout=5)


def test_a_sigkill_of_the_providers_process_fails_calls_at_once_and_its_ids_are_fatal(
    lab: Lab,
) -> None:
    held_id = lab.b.call(hosts.rr_run, "app-b", call_camera, 3, timeout=15)
    in_flight = lab.b.submit(hosts.rr_run, "app-b", call_hang)
    assert lab.a.call(wait_set, "hang_started", 10.0, timeout=15)

    killed = time.monotonic()
    os.kill(lab.a.pid, signal.SIGKILL)

    with pytest.raises(rr.RegistrarUnavailableError):
        in_flight.result(5)
    assert time.monotonic() - killed < 1.0
    assert (held_id, "FATAL", "erm/camera") == lab.b.call(next_status, 1.0, timeout=5)
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
    assert lab.a.call(wait_set, "hang_started", 10.0, timeout=15)

    cut = time.monotonic()
    lab.net.link_down()
    with pytest.raises(rr.RegistrarUnavailableError):
        in_flight.result(5)
    assert time.monotonic() - cut < 2.0
    assert (held_id, "FATAL", "erm/camera") == lab.b.call(next_status, 2.0, timeout=5)
    started = time.monotonic()
    with pytest.raises(rr.RegistrarUnavailableError):
        lab.b.call(hosts.rr_run, "app-b", call_camera, 6, timeout=15)
    assert time.monotonic() - started < 1.0

    healed = time.monotonic()
    lab.net.link_up()
    lab.a.call(open_gate, timeout=5)
    lab.b.call(hosts.rr_until_answered, "app-b", "erm", "probe", 10.0, timeout=15)
    assert time.monotonic() - healed < 10.0
    gone = lab.a.call(unloaded, {"device": 5}, 10.0, timeout=15)
    assert 1 == gone.count({"device": 5})


def test_a_name_served_on_the_other_host_cannot_be_started_again(lab: Lab) -> None:
    with pytest.raises(rr.DuplicateNameError):
        lab.b.call(hosts.rr_start, "erm", None, timeout=15)

    lab.b.call(hosts.rr_run, "app-b", call_camera, 7, timeout=15)
    assert [{"device": 7}] == lab.a.call(loads, timeout=5)


def test_a_call_to_a_name_of_another_system_fails_at_once_naming_the_callers_system(
    lab: Lab,
) -> None:
    other = lab.net.b.spawn()
    other.call(
        hosts.rr_join,
        system="other",
        listen=[lab.net.b.endpoint(PORT + 1)],
        connect=[lab.net.a.endpoint(PORT)],
        timeout=30,
    )
    other.call(hosts.rr_start, "app-c", timeout=30)

    started = time.monotonic()
    with pytest.raises(rr.UnknownRegistrarError, match="other"):
        other.call(hosts.rr_run, "app-c", call_camera, 8, timeout=15)

    assert time.monotonic() - started < 2.0
    other.call(hosts.rr_stop, timeout=30)


# -- a supervisor on each host -----------------------------------------------------------------


def cm_setup(registrar: rr.ResourceRegistrar) -> None:
    """`filtered` depends on the camera of `erm`, on the other host."""

    def load(request: Any) -> Any:
        return registrar.call("erm", "camera", request, timeout=10).response

    registrar.register_server("filtered", load=load, unload=lambda _q, _r: None)


def start_tree(manager: str, setup: Any, state_dir: str, consumer: str | None = None) -> None:
    """A supervisor in this worker with one process manager, on the worker's network."""
    make: Any = rr.Supervisor
    sup = make(
        [rr.ManagerSpec(manager, setup=setup, isolation="process")],
        state_dir=state_dir,
        network=hosts.KEPT["network"],
    )
    sup.start()
    hosts.KEPT["sup"] = sup
    if consumer is not None:
        hosts.KEPT["registrars"][consumer] = sup.registrar(consumer)


def manager_pid(name: str) -> int:
    pid = hosts.KEPT["sup"].child(name).pid
    assert pid is not None
    return int(pid)


def wait_restarted(name: str, timeout: float) -> None:
    hosts.KEPT["sup"].wait_restarted(name, timeout=timeout)


def stop_tree() -> None:
    sup = hosts.KEPT.pop("sup", None)
    if sup is not None:
        sup.stop()


def call_filtered(registrar: rr.ResourceRegistrar, device: int) -> str:
    return registrar.call(
        "cm", "filtered", {"device": device}, on_status=record_status, timeout=10
    ).id


def until_filtered(registrar: rr.ResourceRegistrar, device: int, timeout: float) -> str:
    """`call_filtered` until it succeeds (each failure is immediate: a retry, not a sleep)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return call_filtered(registrar, device)
        except rr.RegistrarUnavailableError:
            if time.monotonic() > deadline:
                raise


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
        b.call(hosts.rr_run, "app-b", until_filtered, 9, 15.0, timeout=30)

        os.kill(a.call(manager_pid, "erm", timeout=10), signal.SIGKILL)
        a.call(wait_restarted, "erm", 10.0, timeout=15)
        b.call(hosts.rr_run, "app-b", until_filtered, 10, 10.0, timeout=15)

        assert 0 == b.call(more_statuses, timeout=5)  # no FATAL: erm was not lost
    finally:
        b.call(stop_tree, timeout=60)
        a.call(stop_tree, timeout=60)
