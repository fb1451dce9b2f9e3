"""Three hosts in a line, `a` - `b` - `c` (issue 33, section 4): `a` and `c` dial only `b`.

`hosts.ThreeHosts`: namespace `a` (`alpha`) has a veth to `b` (`bravo`), `b` one to `c`
(`charlie`), and `a` and `c` have no link and no route to each other. Each host runs one
`ZenohNetwork` of the system "lab" with mutual TLS and members `alpha`, `bravo`,
`charlie` (certificates made by the test, `tests/support/pki.py`; `bravo`'s names both its
addresses). `b` listens on both of its addresses and dials nobody; `a` and `c` listen on
nothing and dial `b`. So every message between `a` and `c` is routed by `b`'s Zenoh
router (an rr_actors router session already: `zenoh.net`), through its access control
on both of its links. `c` serves `erm` (the provider), `b` serves `hub`, `a` serves
`app` (the consumer).

- `test_a_calls_a_registrar_on_c_through_b_with_mutual_tls`: `a` cannot open a TCP
  connection to `c` at all, and its router's only link is to `bravo`; yet `app` waits
  for `erm`, calls it, hears its WARNING and unloads it (`c`'s unload runs); no host logs
  a WARNING (no link watch takes `c` for unreachable).
- `test_a_non_member_linked_to_b_reaches_nothing_on_c`: `stranger` (a certificate of
  the lab's CA, not in `bravo`'s members) links to `b` (which warns naming it); its call
  to `erm` fails with `UnknownRegistrarError` and `c` never sees its registrar: `b`'s
  access control drops it before anything is routed on.
- `test_each_link_admits_by_its_peers_name_so_the_router_vouches_for_what_it_forwards`:
  `a` and `c` admit only `bravo` (and themselves), yet call each other: Zenoh's access
  control judges a message by the certificate of the link it comes over, so a router
  member vouches for what it forwards (`docs/how-to/securing-registrars.md` says so).
- `test_a_cut_between_b_and_c_fails_as_calls_to_c_fast_and_heals`: with an id held at
  `erm` and a call in flight, the veth b-c goes down (no FIN): the call in flight fails
  with `RegistrarUnavailableError`, the held id is `FATAL` and forgotten, a new call
  fails at once, each within the bounds of the two-host table
  (`docs/explanation/failure-semantics.md`); `a`'s calls to `hub` on `b` go on working.
  The veth comes back: `a`'s calls to `erm` succeed within 10 s, the id it forgot is
  released at `erm` (its unload runs once), a new load works, nothing more is `FATAL`.
- `test_a_cut_of_both_of_bs_links_heals_too`: both veths down, then up: as above, and
  `hub` is unreachable from `a` meanwhile.
- `test_a_supervised_manager_killed_on_c_comes_back_without_fatal_for_a`: a process
  manager `cam` under a supervisor on `c`, SIGKILLed: `a` sees its supervisor (`c`'s
  router process) through `b`, so `cam` is not lost: no `FATAL`, `a`'s id is kept by
  the restored catalog and released there when `a` lets go (rules 15 and 19).

Routing needed no change (every `ZenohNetwork` is a Zenoh router, and routers route
between their links; the access control allows `rr/<system>/**` on each link of a
member, whoever sent the message); the error of a call to a registrar seen gone now says
that the link down may be one beyond this host's router.

What a worker's callbacks record (with `time.monotonic()`, one clock for every process of
the machine whatever its namespace) stays in the worker (`hosts.KEPT`) and is read back.
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
from tests.support import hosts, pki

SYSTEM = "lab"
PORT = 7447
MEMBERS = ["alpha", "bravo", "charlie"]
BOUND = 10.0  # seconds any one thing awaited may take (a loaded machine)
CUT_BOUND = 2.0  # seconds after a cut by which calls in flight fail (the two-host table's)
AT_ONCE = 1.0  # seconds a call to a registrar seen gone may take to fail
QUIET = 3.0  # seconds something that must not happen is given to happen anyway


# -- what runs in the workers ------------------------------------------------------------------


def provider_setup(registrar: rr.ResourceRegistrar) -> None:
    """`camera` records its loads and unloads; `hang` blocks its load until the gate opens."""
    kept = hosts.KEPT
    kept.update(loads=[], unloads=[], unloaded=queue.Queue(), gate=threading.Event())
    kept["hang_started"] = threading.Event()

    def load(request: Any) -> Any:
        kept["loads"].append(request)
        return {"stream": request}

    def unload(request: Any, _response: Any) -> None:
        kept["unloads"].append(request)
        kept["unloaded"].put(request)

    def hang(request: Any) -> Any:
        kept["hang_started"].set()
        kept["gate"].wait(30)
        return request

    registrar.register_server("camera", load=load, unload=unload)
    registrar.register_server("hang", load=hang, unload=lambda _q, _r: None)
    registrar.register_server("probe", load=lambda request: request, unload=lambda _q, _r: None)


def hub_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("probe", load=lambda request: request, unload=lambda _q, _r: None)


def call_camera(registrar: rr.ResourceRegistrar, device: int) -> str:
    return registrar.call(
        "erm", "camera", {"device": device}, on_status=hosts.record_status, timeout=BOUND
    ).id


def call_hang(registrar: rr.ResourceRegistrar) -> str:
    return registrar.call("erm", "hang", "r", timeout=30).id


def call_hub(registrar: rr.ResourceRegistrar, n: int) -> None:
    registrar.unload(registrar.call("hub", "probe", n, timeout=BOUND).id)


def failing_call(
    registrar: rr.ResourceRegistrar, target: str, device: int
) -> tuple[str, str, float]:
    """What a call to `target` fails with: the error's type name and message; seconds taken."""
    started = time.monotonic()
    try:
        registrar.unload(registrar.call(target, "probe", device, timeout=BOUND).id)
    except rr.RrError as exc:
        return type(exc).__name__, str(exc), time.monotonic() - started
    return "no error", "", time.monotonic() - started


def unload(registrar: rr.ResourceRegistrar, query_id: str) -> None:
    registrar.unload(query_id)


def held(registrar: rr.ResourceRegistrar) -> list[str]:
    return [query.id for query in registrar.client_queries()]


def unloaded(request: Any, timeout: float) -> float:
    """When `request` was unloaded (`TimeoutError` if it is not within `timeout`)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            seen = hosts.KEPT["unloaded"].get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise TimeoutError(f"{request!r} was not unloaded within {timeout:g} s") from None
        if seen == request:
            return time.monotonic()


def counts(device: int) -> tuple[int, int]:
    """How often `camera` loaded and unloaded `device`."""
    request = {"device": device}
    return hosts.KEPT["loads"].count(request), hosts.KEPT["unloads"].count(request)


def wait_for_name(name: str, timeout: float) -> None:
    hosts.KEPT["network"].wait_for(name, timeout=timeout)


def router_links() -> list[str]:
    """The member names at the other end of this worker's router's TLS links."""
    session = hosts.KEPT["network"].services().session
    return sorted(
        str(link.auth_identifier)
        for link in session.info.links()
        if str(link.dst).startswith("tls/")
    )


def tcp_connect(address: str, port: int) -> str:
    """What a plain TCP connect to `address`:`port` from this host gets (an `OSError`'s
    text, or "connected")."""
    import socket  # noqa: PLC0415

    try:
        with socket.create_connection((address, port), timeout=2.0):
            return "connected"
    except OSError as exc:
        return str(exc)


# -- the test's side ---------------------------------------------------------------------------


@dataclasses.dataclass
class Lab:
    """The three hosts, and the worker of each (`a`: `app`; `b`: `hub`; `c`: `erm`)."""

    net: hosts.ThreeHosts
    ca: tuple[Any, Any]
    a: hosts.Worker
    b: hosts.Worker
    c: hosts.Worker


def tls_of(
    net: hosts.ThreeHosts,
    ca: tuple[Any, Any],
    name: str,
    *addresses: str,
    members: list[str] = MEMBERS,
) -> dict[str, Any]:
    cert, key = pki.issue(net.directory, name, addresses, ca=ca)
    return {"ca": str(ca[0]), "cert": str(cert), "key": str(key), "members": members}


@contextlib.contextmanager
def made_lab(ends_admit: list[str] = MEMBERS, resolve: str = "first_served") -> Iterator[Lab]:
    """The lab; `a` and `c` admit `ends_admit` (`b` admits all three); every host's
    network resolves two servers of one name by `resolve` (rule 22)."""
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    with hosts.ThreeHosts() as net:
        ca = pki.make_ca(net.directory, SYSTEM)
        a, b, c = net.a.spawn(), net.b.spawn(), net.c.spawn()
        b_for_a, b_for_c = f"tls/{net.b.address}:{PORT}", f"tls/{net.b_toward_c}:{PORT}"
        b.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[b_for_a, b_for_c],
            connect=[],
            tls=tls_of(net, ca, "bravo", net.b.address, net.b_toward_c),
            resolve=resolve,
            timeout=30,
        )
        b.call(hosts.rr_start, "hub", hub_setup, timeout=30)
        c.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[],
            connect=[b_for_c],
            tls=tls_of(net, ca, "charlie", net.c.address, members=["charlie", *ends_admit]),
            resolve=resolve,
            timeout=30,
        )
        c.call(hosts.rr_start, "erm", provider_setup, timeout=30)
        a.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[],
            connect=[b_for_a],
            tls=tls_of(net, ca, "alpha", net.a.address, members=["alpha", *ends_admit]),
            resolve=resolve,
            timeout=30,
        )
        a.call(hosts.rr_start, "app", timeout=30)
        try:
            a.call(hosts.rr_until_answered, "app", "erm", "probe", 2 * BOUND, timeout=60)
            yield Lab(net, ca, a, b, c)
        finally:
            with contextlib.suppress(Exception):
                c.call(hosts.open_gate, timeout=5)  # (a load still held at the gate ends)
            for worker in (a, c, b):
                if worker.alive:
                    with contextlib.suppress(Exception):
                        worker.call(hosts.rr_stop, timeout=30)


@pytest.fixture
def lab() -> Iterator[Lab]:
    with made_lab() as made:
        yield made


def warnings(lab: Lab) -> dict[str, list[str]]:
    return {
        worker.host.name: worker.call(hosts.rr_logs, "WARNING", timeout=10)
        for worker in (lab.a, lab.b, lab.c)
    }


def test_a_calls_a_registrar_on_c_through_b_with_mutual_tls(lab: Lab) -> None:
    a, c = lab.a, lab.c
    # no way from a to c but through b: no route, and a's router links to bravo alone
    assert "unreachable" in a.call(tcp_connect, lab.net.c.address, PORT, timeout=10)
    assert ["bravo"] == a.call(router_links, timeout=10)
    assert ["bravo"] == c.call(router_links, timeout=10)
    assert ["alpha", "charlie"] == lab.b.call(router_links, timeout=10)

    a.call(wait_for_name, "erm", BOUND, timeout=30)
    query_id = a.call(hosts.rr_run, "app", call_camera, 1, timeout=30)
    c.call(hosts.rr_run, "erm", hosts.send_warning, 1, timeout=30)
    heard_id, status, source, _ = a.call(hosts.next_status, BOUND, timeout=30)
    a.call(hosts.rr_run, "app", unload, query_id, timeout=30)
    c.call(unloaded, {"device": 1}, BOUND, timeout=30)

    assert (query_id, "WARNING", "erm/camera") == (heard_id, status, source)
    assert (1, 1) == c.call(counts, 1, timeout=10)
    assert {"a": [], "b": [], "c": []} == warnings(lab)


def warned_of(name: str, timeout: float) -> str:
    """The first WARNING of this worker naming `name` (`TimeoutError` if none comes)."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    def found() -> list[str]:
        return [m for m in hosts.rr_logs("WARNING") if repr(name) in m]

    if not wait_for(lambda: bool(found()), timeout):
        raise TimeoutError(f"no WARNING naming {name!r} within {timeout:g} s")
    return found()[0]


def test_a_non_member_linked_to_b_reaches_nothing_on_c(lab: Lab) -> None:
    # b's access control drops what a non-member sends before it is routed on
    stranger = lab.net.a.spawn()
    stranger_tls = tls_of(lab.net, lab.ca, "stranger", lab.net.a.address)
    stranger_tls["members"] = [*MEMBERS, "stranger"]  # (on its own side, it is one)
    stranger.call(
        hosts.rr_join,
        system=SYSTEM,
        listen=[],
        connect=[f"tls/{lab.net.b.address}:{PORT}"],
        tls=stranger_tls,
        timeout=30,
    )
    stranger.call(hosts.rr_start, "mallory", timeout=30)

    assert "not in members" in lab.b.call(warned_of, "stranger", BOUND, timeout=30)
    seen_at_c = lab.c.submit(hosts.names_within, "mallory", QUIET)
    kind, message, _ = stranger.call(hosts.rr_run, "mallory", failing_call, "erm", 1, timeout=30)
    assert "UnknownRegistrarError" == kind, message
    assert not seen_at_c.result(timeout=30)
    assert (0, 0) == lab.c.call(counts, 1, timeout=10)
    lab.a.call(hosts.rr_run, "app", call_hub, 2, timeout=30)  # the members go on
    query_id = lab.a.call(hosts.rr_run, "app", call_camera, 2, timeout=30)
    lab.a.call(hosts.rr_run, "app", unload, query_id, timeout=30)
    stranger.call(hosts.rr_stop, timeout=30)


def test_each_link_admits_by_its_peers_name_so_the_router_vouches_for_what_it_forwards() -> None:
    # a admits only bravo (and itself), c likewise: what c sends reaches a over b's link,
    # whose certificate is bravo's; b's members (all three) decide who gets through b
    with made_lab(ends_admit=["bravo"]) as lab:
        query_id = lab.a.call(hosts.rr_run, "app", call_camera, 3, timeout=30)
        lab.a.call(hosts.rr_run, "app", unload, query_id, timeout=30)
        lab.c.call(unloaded, {"device": 3}, BOUND, timeout=30)


def _cut_and_heal(lab: Lab, cut: list[tuple[str, str]]) -> None:
    """Cut the veths `cut`, check what `a` sees of `erm` (and of `hub`), heal, check again."""
    a, c = lab.a, lab.c
    held_id = a.call(hosts.rr_run, "app", call_camera, 5, timeout=30)
    in_flight = a.submit(hosts.rr_run, "app", call_hang)
    assert c.call(hosts.wait_set, "hang_started", BOUND, timeout=30)

    started = time.monotonic()
    for pair in cut:
        lab.net.link_down(*pair)
    with pytest.raises(rr.RegistrarUnavailableError, match=r"'erm'.*a link on the way"):
        in_flight.result(BOUND)
    failed = time.monotonic() - started
    query_id, status, source, fatal_at = a.call(hosts.next_status, BOUND, timeout=30)
    kind, message, took = a.call(hosts.rr_run, "app", failing_call, "erm", 6, timeout=30)
    hub_seen = a.call(hosts.rr_run, "app", failing_call, "hub", 7, timeout=30)[0]

    assert failed < CUT_BOUND
    assert (held_id, "FATAL", "erm/camera") == (query_id, status, source)
    assert fatal_at - started < CUT_BOUND  # erm is not supervised: lost (rule 19)
    assert held_id not in a.call(hosts.rr_run, "app", held, timeout=10)
    assert ("RegistrarUnavailableError", True) == (kind, "a link on the way" in message)
    assert took < AT_ONCE
    hub_cut = ("b", "c") not in cut or ("a", "b") in cut
    assert hub_seen == ("RegistrarUnavailableError" if hub_cut else "no error")

    healing = time.monotonic()
    for pair in cut:
        lab.net.link_up(*pair)
    c.call(hosts.open_gate, timeout=5)
    a.call(hosts.rr_until_answered, "app", "erm", "probe", BOUND, timeout=30)
    healed = time.monotonic() - healing
    c.call(unloaded, {"device": 5}, BOUND, timeout=30)  # the id a forgot, released at c
    again = a.call(hosts.rr_run, "app", call_camera, 5, timeout=30)  # loads anew
    a.call(hosts.rr_run, "app", unload, again, timeout=30)
    c.call(unloaded, {"device": 5}, BOUND, timeout=30)
    a.call(hosts.rr_run, "app", call_hub, 8, timeout=30)

    assert healed < BOUND
    assert (2, 2) == c.call(counts, 5, timeout=10)
    assert 0 == a.call(hosts.more_statuses, timeout=10)  # nothing FATAL after the heal


@pytest.mark.timeout(180)
def test_a_cut_between_b_and_c_fails_as_calls_to_c_fast_and_heals(lab: Lab) -> None:
    _cut_and_heal(lab, [("b", "c")])


@pytest.mark.timeout(180)
def test_a_cut_of_both_of_bs_links_heals_too(lab: Lab) -> None:
    _cut_and_heal(lab, [("a", "b"), ("b", "c")])


# -- a supervised manager on c -----------------------------------------------------------------


def start_tree(state_dir: str) -> None:
    """A supervisor in this worker with one process manager, `cam` (a `provider_setup`)."""
    sup = rr.Supervisor(
        [rr.ManagerSpec("cam", setup=provider_setup, isolation="process")],
        state_dir=state_dir,
        network=hosts.KEPT["network"],
    )
    sup.start()
    hosts.KEPT["sup"] = sup


def wait_restarted(name: str, timeout: float) -> None:
    hosts.KEPT["sup"].wait_restarted(name, timeout=timeout)


def in_manager(name: str, fn: Any, *args: Any) -> Any:
    """`fn(*args)` in manager `name`'s process (its own `hosts.KEPT`)."""
    return hosts.KEPT["sup"].run_in(name, lambda _registrar: fn(*args), timeout=BOUND)


def call_cam(registrar: rr.ResourceRegistrar, device: int) -> str:
    return registrar.call(
        "cam", "camera", {"device": device}, on_status=hosts.record_status, timeout=BOUND
    ).id


def until_cam(registrar: rr.ResourceRegistrar, device: int, timeout: float) -> str:
    """`call_cam` until it succeeds (each failure is immediate: a retry, not a sleep)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return call_cam(registrar, device)
        except rr.RegistrarUnavailableError:
            if time.monotonic() > deadline:
                raise


@pytest.mark.timeout(180)
def test_a_supervised_manager_killed_on_c_comes_back_without_fatal_for_a(lab: Lab) -> None:
    # a sees cam's supervisor (c's router process) through b: cam is not lost (rule 19)
    a, c = lab.a, lab.c
    c.call(start_tree, str(lab.net.directory / "c"), timeout=60)
    try:
        before = a.call(hosts.rr_run, "app", until_cam, 9, BOUND, timeout=30)

        os.kill(c.call(hosts.manager_pid, "cam", timeout=10), signal.SIGKILL)
        c.call(wait_restarted, "cam", BOUND, timeout=30)
        after = a.call(hosts.rr_run, "app", until_cam, 10, BOUND, timeout=30)

        assert 0 == a.call(hosts.more_statuses, timeout=10)  # no FATAL: cam was not lost
        assert {before, after} <= set(a.call(hosts.rr_run, "app", held, timeout=10))
        # its restored catalog kept a's id (rule 15): released there when app lets go
        a.call(hosts.rr_run, "app", unload, before, timeout=30)
        c.call(in_manager, "cam", unloaded, {"device": 9}, BOUND, timeout=30)
        a.call(hosts.rr_run, "app", unload, after, timeout=30)
    finally:
        c.call(hosts.stop_tree, timeout=60)


# -- rule 22's resolve strategy: a lone host against the majority (issue 51, finding 9) --------


def stopped_within(name: str, timeout: float) -> bool:
    """Whether this worker's registrar `name` stops within `timeout` seconds."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    registrar = hosts.KEPT["registrars"][name]
    return bool(wait_for(lambda: not registrar.is_alive(), timeout))


def alive(name: str) -> bool:
    return bool(hosts.KEPT["registrars"][name].is_alive())


@pytest.mark.timeout(240)
def test_with_resolve_majority_the_lone_hosts_registrar_yields_to_the_majoritys() -> None:
    """`c` (serving `erm`) is cut from `a` and `b`; `erm` is lost on their side, and `b`
    serves a newcomer of it, which `a`'s `app` loads from. At the heal, with every host's
    `resolve="majority"`, the newcomer is kept (it began with two of the three members
    heard; `c`'s registrar yields: one ERROR, it unloads what it served), and what `a`
    loaded during the cut stays loaded. (First served, the old and default rule, keeps
    `c`'s and undoes `a`'s load: `test_registrars_on_two_hosts`.)"""
    with made_lab(resolve="majority") as lab:
        a, b, c = lab.a, lab.b, lab.c
        before = a.call(hosts.rr_run, "app", call_camera, 5, timeout=30)  # at c's erm
        lab.net.link_down("b", "c")
        assert b.call(hosts.rr_unlinked_within, "erm", BOUND, timeout=30)
        assert a.call(hosts.rr_unlinked_within, "erm", BOUND, timeout=30)
        assert (before, "FATAL") == a.call(hosts.next_status, BOUND, timeout=30)[:2]  # (lost)
        b.call(hosts.rr_start, "erm", provider_setup, timeout=30)  # (the newcomer)
        a.call(hosts.rr_until_answered, "app", "erm", "probe", BOUND, timeout=30)
        during = a.call(hosts.rr_run, "app", call_camera, 7, timeout=30)
        assert (1, 0) == b.call(counts, 7, timeout=10)

        lab.net.link_up("b", "c")

        assert c.call(stopped_within, "erm", 30.0, timeout=35)
        c.call(unloaded, {"device": 5}, BOUND, timeout=30)  # (what it served)
        errors = c.call(hosts.rr_logs, "ERROR", timeout=5)
        assert 1 == len(errors), errors
        assert "resolve='majority' keeps the other one" in errors[0]
        assert b.call(alive, "erm", timeout=5)
        assert during in a.call(hosts.rr_run, "app", held, timeout=10)
        again = a.call(hosts.rr_run, "app", call_camera, 7, timeout=30)  # (b's, loaded)
        assert (1, 0) == b.call(counts, 7, timeout=10)
        for query_id in (again, during):
            a.call(hosts.rr_run, "app", unload, query_id, timeout=30)
        b.call(unloaded, {"device": 7}, BOUND, timeout=30)
        assert [] == b.call(hosts.rr_logs, "ERROR", timeout=5)
