"""Only members of the system get in (issue 23): mutual TLS and access control, on two hosts.

Host `a` (10.77.<n>.1) listens on `tls/<a>:7447` and serves `erm` as the member `robot`;
host `b` (10.77.<n>.2) runs the member `operator` (its registrar `app` calls `erm`) and, in
workers of its own, whoever else connects (the `lab` fixture). The certificates are made
by the test (`tests/support/pki.py`): the system's CA "lab", each member's certificate naming its
host's address. One test per row of the issue's table "What a peer without the system's
certificate gets"; in each, `operator` still calls `erm` across the veth after the peer
tried, and what the peer sends is a pickle that would create a file if it were unpickled
(`CreatesAFile`, framed with the wire header as a process of the system frames a message
for a registrar): the file never appears (the namespaces share the file system, so the
test looks itself). What must not happen is given `QUIET` (3 s) to happen anyway.

- row 1, `test_members_call_each_other_and_each_side_names_the_other`: calls, a status
  (the provider's WARNING reaches the consumer's `on_status`), unload (the provider's
  unload runs); INFO names the other member on both sides; no WARNING on either.
  `test_members_that_dial_each_other_are_linked_and_neither_warns`: both listen and dial
  each other; calls both ways; once linked, neither counts its endpoint unlinked through
  the 2 s grace and past it, and no WARNING but the first host's, from before the second
  listened, that nobody listened there (true then: that is not a false alarm).
- row 2, `test_plain_tcp_to_the_tls_port_is_closed_unread`: raw bytes, a raw pickle, a
  framed pickle over plain TCP: the listener answers a TLS alert (`decode_error`) and
  closes. `test_a_plain_zenoh_peer_at_the_tls_port_gets_no_link`: a plain Zenoh peer
  (`tcp/` to the `tls/` port) gets no link; its registrar token and its put on
  `rr/lab/reg/erm` never arrive (`a`'s `names()` never shows it).
- row 3, `test_a_client_without_the_systems_certificate_is_refused_in_the_handshake`:
  raw `ssl` clients on `b` (trusting the lab CA, so only the listener can refuse):
  self-signed and another system's CA get `unknown ca`, another CA of the lab's own
  name `decrypt error`, expired and not yet valid `certificate expired`, no certificate
  `certificate required`. `test_an_rr_actors_host_so_refused_is_warned_with_the_reason_
  and_is_not_in`: a host whose files are valid for another system's CA gets the WARNING
  naming the endpoint and `unknown ca`, its calls fail with `UnknownRegistrarError`, its
  router has no link, `a` never sees its registrar, what is put through its router on
  `rr/lab/reg/erm` never arrives.
- row 4, `test_a_ca_signed_non_member_links_but_every_message_is_dropped`: `stranger`
  (lab CA, not in `a`'s members) links; one WARNING on `a` naming it and `b`'s address,
  one only though a second link from that address comes and goes; it cannot call `erm`;
  a raw Zenoh session with its certificate puts a framed pickle on `rr/lab/reg/erm` and
  declares a registrar token: neither arrives. The same puts with a member's certificate
  (raw, and through a member's router) are unpickled: the checks are not vacuous.
- row 5, `test_a_member_refuses_a_listener_impostor`: a member dials the real `robot`
  on `a` and a listener on `a`'s port 7448 whose certificate is of another CA, or of the
  lab CA but not naming the address dialled: it calls `erm`, has no link to the
  impostor, its WARNING says which (though it is linked to that address's other port),
  and what the impostor puts on the member's registrar never arrives.
- row 6, `test_a_member_whose_key_was_replaced_gets_a_config_error_on_its_own_host`:
  `ConfigError` from `rr.ZenohTLS(...)` in `a`'s worker naming the key and the cert.
- bounds, `test_a_burst_of_refused_handshakes_fails_no_member_call_and_a_member_joins_
  during_it`: 200 refused handshakes from 20 clients at once (Zenoh pauses its accept
  loop 100 ms after each); every call of `operator` meanwhile succeeds, and a member that
  joins during the burst has its first call answered before the burst ended (within 10 s:
  `benchmarks/bench_zenoh_tls.py`). Latency (p99) is measured in `benchmarks/`, never
  asserted in a test.
- flood (issue 29), `test_a_member_rejoins_in_10_s_while_a_third_host_floods_the_port_
  with_failed_handshakes`: a third host `c` (`TwoHosts(outsider=True)`) connects, sends
  a few bytes and closes, from 4 threads at full rate, against `a`'s `tls/` port; every
  call of `operator` on its link meanwhile succeeds; `a` names `c` in a WARNING; the
  veth a-b is cut until `b` has lost `erm` and brought back: `b` calls `erm` within 10 s
  while the flood goes on, and again within 10 s after it stopped (0.4 s measured).
  `..._from_32_addresses` (issue 40): the same from 32 addresses of `c`, each under the
  gate's `HOLD`: `a` names the members' addresses it still takes packets from.
- forged SYNs (issue 40), `test_a_member_rejoins_in_10_s_though_a_third_host_forges_
  syns_from_its_address`: while `b` is out of reach (its end of the veth down: `a` keeps
  its route to `b`), `c` sends 13 SYNs a second whose source is `b`'s address
  (`tests/support/spoof.py`); `a` holds as many half-open connections from `b`'s address
  as main's gate dropped it for; `b` re-joins within 10 s with the forging going on, and
  after a second run of it; `a` never names `b`'s address in a WARNING.
"""

from __future__ import annotations

import contextlib
import datetime
import pickle
import queue
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from tests.support import hosts, pki, spoof
from tests.support.hostile import CreatesAFile
from tests.support.waiting import wait_for

SYSTEM = "lab"
PORT = 7447
MEMBERS = ["robot", "operator"]
BOUND = 10.0  # seconds any one thing awaited may take (a loaded machine)
QUIET = 3.0  # seconds something that must not happen is given to happen anyway

# Each test's bound, its lab's setup and teardown included (pytest-timeout's covers all
# three): the `lab` fixture makes two namespaces, a TLS router and a worker process in each,
# a manager process, and a first call; its teardown stops them. Unloaded that is 5 s; beside
# two busy loops (load 10 to 15 on 2 cores) the setup alone took 21 to 42 s, and the default
# 60 s stopped 3 of 10 runs of `test_plain_tcp_to_the_tls_port_is_closed_unread`, each step
# within its own bound (BOUND, a worker's 30 s): twice in the teardown, once in the first
# plain attempt. Heavier tests say more below.
pytestmark = pytest.mark.timeout(150)


# -- what runs in the workers (sent by value with the functions that use them) -----------------


def framed_pickle(path: Path, sender: str = "intruder") -> bytes:
    """A message for a registrar as a process of the system sends it: the wire header,
    then a frame whose pickle creates `path` when unpickled."""
    from rr_actors._transport.codec import frame  # noqa: PLC0415
    from rr_actors._transport.zenoh.wire import MESSAGE, header  # noqa: PLC0415

    return header(MESSAGE, sender) + frame(7, CreatesAFile(str(path)))


def erm_setup(registrar: rr.ResourceRegistrar) -> None:
    """`camera` records its unloads in `KEPT["unloads"]`."""
    unloads: queue.Queue[Any] = queue.Queue()
    hosts.KEPT["unloads"] = unloads
    registrar.register_server(
        "camera",
        load=lambda request: {"stream": request},
        unload=lambda request, _response: unloads.put(request),
    )


def call_camera(registrar: rr.ResourceRegistrar, device: int) -> Any:
    query = registrar.call("erm", "camera", {"device": device}, timeout=10)
    registrar.unload(query.id)
    return query.response


def record_status(query: rr.Query, update: rr.StatusUpdate) -> None:
    hosts.KEPT.setdefault("heard", queue.Queue()).put(
        (query.id, update.status.name, update.source, update.message)
    )


def call_with_status(registrar: rr.ResourceRegistrar, device: int) -> str:
    return registrar.call(
        "erm", "camera", {"device": device}, on_status=record_status, timeout=10
    ).id


def unload(registrar: rr.ResourceRegistrar, query_id: str) -> None:
    registrar.unload(query_id)


def next_from(name: str, timeout: float) -> Any:
    """The next item of `KEPT[name]` (a queue); `TimeoutError` if none within `timeout`."""
    try:
        return hosts.KEPT.setdefault(name, queue.Queue()).get(timeout=timeout)
    except queue.Empty:
        raise TimeoutError(f"nothing in {name} within {timeout:g} s") from None


def logged(level: str, parts: list[str], timeout: float) -> str:
    """The first message of `level` kept by `hosts.rr_join`'s handler that holds every one
    of `parts`, waited for (`TimeoutError` naming what was logged if none comes)."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    def found() -> list[str]:
        return [m for m in hosts.rr_logs(level) if all(part in m for part in parts)]

    if not wait_for(lambda: bool(found()), timeout):
        raise TimeoutError(f"no {level} with {parts} within {timeout:g} s: {hosts.rr_logs()}")
    return found()[0]


def call_fails(registrar: rr.ResourceRegistrar) -> str:
    """The name of the error a call to `erm` fails with."""
    try:
        registrar.call("erm", "camera", {"device": 0}, timeout=5)
    except rr.RrError as exc:
        return type(exc).__name__
    return "no error"


def router_links() -> list[tuple[str, str]]:
    """This worker's router's TLS links: (the peer's common name, its locator)."""
    session = hosts.KEPT["network"].services().session
    return [
        (str(link.auth_identifier), str(link.dst))
        for link in session.info.links()
        if str(link.dst).startswith("tls/")
    ]


def put_through_router(key: str, path: Path) -> None:
    """Put `framed_pickle(path)` on `key` from a raw session of this host's own (joined to
    this worker's router over its Unix socket, as a manager process joins it, with its
    process token)."""
    import json  # noqa: PLC0415

    import zenoh  # noqa: PLC0415

    socket_path = hosts.KEPT["network"].address.socket_path
    settings = {
        "mode": "client",
        "connect": {"endpoints": [f"unixsock-stream/{socket_path}"]},
        "scouting": {"multicast": {"enabled": False}},
    }
    session = zenoh.open(zenoh.Config.from_json5(json.dumps(settings)))
    try:
        zid = str(session.zid())  # a member process's token, and its id in the header
        session.liveliness().declare_token(f"rr/{SYSTEM}/live/proc/{zid}")
        session.put(key, framed_pickle(path, zid))
    finally:
        session.close()


def raw_open(
    connect: list[str], tls: dict[str, Any] | None, wait: float = 5.0
) -> list[tuple[str, str]]:
    """Open a raw Zenoh peer session (`KEPT["raw"]`): plain, or mutual TLS with the files
    of `tls` as `zenoh.config` sets them. Its links once it has one, within `wait` s."""
    import json  # noqa: PLC0415

    import zenoh  # noqa: PLC0415

    from rr_actors._transport.zenoh.ops.config import _tls_settings  # noqa: PLC0415
    from tests.support.waiting import wait_for  # noqa: PLC0415

    link: dict[str, Any] = {}
    if tls is not None:
        link = {"protocols": ["tls"], "tls": _tls_settings(rr.ZenohTLS(**tls))}
    settings = {
        "mode": "peer",
        "listen": {"endpoints": []},
        "connect": {"endpoints": connect, "timeout_ms": 0, "exit_on_failure": False},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": link},
    }
    session = zenoh.open(zenoh.Config.from_json5(json.dumps(settings)))
    hosts.KEPT["raw"] = session

    def links() -> list[tuple[str, str]]:
        return [(str(k.auth_identifier), str(k.dst)) for k in session.info.links()]

    wait_for(lambda: bool(links()), wait)
    return links()


def raw_links() -> list[tuple[str, str]]:
    return [(str(k.auth_identifier), str(k.dst)) for k in hosts.KEPT["raw"].info.links()]


def raw_intrude(name: str, path: Path) -> str:
    """With the raw session: a process token and a registrar token for `name` (as a
    process serving it declares), and `framed_pickle(path)` put on `rr/lab/reg/erm`; the
    session's Zenoh id."""
    session = hosts.KEPT["raw"]
    zid = str(session.zid())
    hosts.KEPT["tokens"] = [
        session.liveliness().declare_token(f"rr/{SYSTEM}/live/proc/{zid}"),
        session.liveliness().declare_token(f"rr/{SYSTEM}/live/reg/{name}/{zid}/0/1048576/1"),
    ]
    session.put(f"rr/{SYSTEM}/reg/erm", framed_pickle(path, zid))
    return zid


def raw_close() -> None:
    hosts.KEPT.pop("tokens", None)
    session = hosts.KEPT.pop("raw", None)
    if session is not None:
        session.close()


def plain_attempt(host: str, port: int, payload: bytes, timeout: float) -> bytes:
    """Plain TCP: send `payload`, read to the end; what came back (`b"RESET"` for a reset)."""
    import socket  # noqa: PLC0415

    received = b""
    with socket.create_connection((host, port), timeout=timeout) as conn:
        try:
            conn.sendall(payload)
            while chunk := conn.recv(4096):
                received += chunk
        except (ConnectionResetError, BrokenPipeError):
            return received + b"RESET"
    return received


def tls_attempt(
    host: str, port: int, ca: str, cert: str | None, key: str | None, payload: bytes
) -> str:
    """One TLS 1.3 client (Python's `ssl`, trusting `ca`, with `cert` if given): hand
    shake, send `payload`, read. What happened: `alert: <OpenSSL reason>`, `closed`,
    `reset`, or `read: <bytes>` (the listener took it)."""
    import socket  # noqa: PLC0415
    import ssl  # noqa: PLC0415

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.minimum_version = ssl.TLSVersion.TLSv1_3
    context.load_verify_locations(cafile=ca)
    if cert is not None:
        context.load_cert_chain(cert, key)
    try:
        with (
            socket.create_connection((host, port), timeout=BOUND) as raw,
            context.wrap_socket(raw, server_hostname=host) as conn,
        ):
            conn.sendall(payload)
            data = conn.recv(4096)
            return "closed" if data == b"" else f"read: {data!r}"
    except ssl.SSLError as exc:
        return f"alert: {exc.reason}"
    except (ConnectionResetError, BrokenPipeError):
        return "reset"


# -- the test's side ---------------------------------------------------------------------------


def tls_files(
    directory: Path,
    name: str,
    address: str,
    ca: tuple[Path, Path],
    members: list[str] = MEMBERS,
    *,
    trust: Path | None = None,
) -> dict[str, Any]:
    """`rr.ZenohTLS`'s arguments for a host `name` at `address`, signed by `ca` (trusting
    `trust` instead of `ca`'s certificate, if given)."""
    cert, key = pki.issue(directory, name, (address,), ca=ca)
    return {"ca": str(trust or ca[0]), "cert": str(cert), "key": str(key), "members": members}


def join(
    worker: hosts.Worker,
    tls: dict[str, Any],
    *,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    start: str | None = None,
    setup: Any = None,
) -> None:
    worker.call(
        hosts.rr_join,
        system=SYSTEM,
        listen=listen or [],
        connect=connect or [],
        tls=tls,
        timeout=30,
    )
    if start is not None:
        worker.call(hosts.rr_start, start, setup, timeout=30)


@pytest.fixture
def lab(two_hosts: hosts.TwoHosts, tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    """`robot` on `a` serving `erm`, `operator` on `b` whose `app` calls it; the CA."""
    with started_lab(two_hosts, tmp_path) as ca:
        yield ca


@contextlib.contextmanager
def started_lab(two_hosts: hosts.TwoHosts, tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    """The `lab` fixture's hosts, on `two_hosts`."""
    a, b = two_hosts.a, two_hosts.b
    ca = pki.make_ca(tmp_path / "lab", SYSTEM)
    join(
        a.worker,
        tls_files(tmp_path / "lab", "robot", a.address, ca),
        listen=[a.endpoint(PORT, "tls")],
        start="erm",
        setup=erm_setup,
    )
    join(
        b.worker,
        tls_files(tmp_path / "lab", "operator", b.address, ca),
        connect=[a.endpoint(PORT, "tls")],
        start="app",
    )
    b.call(hosts.rr_until_answered, "app", "erm", "camera", BOUND, timeout=30)
    assert {"probe": 1} == a.call(next_from, "unloads", BOUND, timeout=30)
    yield ca
    for host in (b, a):
        for worker in list(host._workers):
            if worker.alive:
                with contextlib.suppress(Exception):  # (stopped with the hosts anyway)
                    worker.call(hosts.rr_stop, timeout=30)


def member_calls(b: hosts.Host, device: int) -> None:
    """The member `operator` calls `erm` across the veth, as before anyone else came.

    A call that fails carries `operator`'s log (INFO and up) as a note: whether its link
    to `robot` went, and when, is the first question such a failure asks (CI, once, at
    load 14: "erm unreachable" after the plain attempts of
    `test_plain_tcp_to_the_tls_port_is_closed_unread`, not reproduced since).
    """
    try:
        answer = b.call(hosts.rr_run, "app", call_camera, device, timeout=30)
    except Exception as exc:
        with contextlib.suppress(Exception):
            exc.add_note("operator's log:\n" + "\n".join(b.call(hosts.rr_logs, timeout=10)))
        raise
    assert answer == {"stream": {"device": device}}


def never_appear(*paths: Path) -> None:
    """None of `paths` is created within `QUIET` seconds (one wait for them all)."""
    assert not wait_for(lambda: any(path.exists() for path in paths), QUIET), (
        f"{[str(path) for path in paths if path.exists()]} created: a peer's pickle was unpickled"
    )


# -- row 1: a member ---------------------------------------------------------------------------


def test_members_call_each_other_and_each_side_names_the_other(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path]
) -> None:
    a, b = two_hosts.a, two_hosts.b
    member_calls(b, 3)
    assert {"device": 3} == a.call(next_from, "unloads", BOUND, timeout=30)
    query_id = b.call(hosts.rr_run, "app", call_with_status, 4, timeout=30)
    a.call(hosts.rr_run, "erm", hosts.send_warning, 4, timeout=30)
    assert (query_id, "WARNING", "erm/camera", "hot") == b.call(
        next_from, "heard", BOUND, timeout=30
    )
    b.call(hosts.rr_run, "app", unload, query_id, timeout=30)
    assert {"device": 4} == a.call(next_from, "unloads", BOUND, timeout=30)
    for host, other, name in ((a, b, "operator"), (b, a, "robot")):
        said = f"ZenohNetwork 'lab': member '{name}' linked at {other.address}"
        assert said == host.call(logged, "INFO", [said], BOUND, timeout=30)
    assert [] == a.call(hosts.rr_logs, "WARNING", timeout=10)
    assert [] == b.call(hosts.rr_logs, "WARNING", timeout=10)


def unlinked_within(timeout: float) -> list[list[tuple[str, str]]]:
    """What this worker's link watch counts unlinked (`LinkWatch.unlinked`), looked at every
    `TICK` s for `timeout` s, as the watch looks: each non-empty answer."""
    from rr_actors_lab.observe._links import TICK  # noqa: PLC0415

    watch = hosts.KEPT["network"].beside  # (the lab's `Across`: its link watch)
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        unlinked = watch.unlinked()
        if unlinked:
            seen.append(unlinked)
        threading.Event().wait(TICK)  # (a look at a state, not a synchronisation)
    return seen


def test_members_that_dial_each_other_are_linked_and_neither_warns(
    two_hosts: hosts.TwoHosts, tmp_path: Path
) -> None:
    # Each listens and dials the other: `b` dials `a` (listening already) at once, `a`
    # reaches `b` at Zenoh's next retry, so for a while `a`'s only link may be the one whose
    # port is `b`'s own, not the one `a` dials (Zenoh 1.10 then keeps both). Once linked,
    # neither counts its endpoint unlinked (looked at through the grace and past it,
    # whatever the WARNING's once-a-minute limit hides) nor warns. Only `a` may have
    # warned before `b` listened (on a loaded machine `b` starts seconds later): that
    # nobody listened there then, which was true.
    a, b = two_hosts.a, two_hosts.b
    ca = pki.make_ca(tmp_path / "lab", SYSTEM)
    here, there = a.endpoint(PORT, "tls"), b.endpoint(PORT, "tls")
    files = {
        a: tls_files(tmp_path / "lab", "robot", a.address, ca),
        b: tls_files(tmp_path / "lab", "operator", b.address, ca),
    }
    nobody_listened = f"no link to connect endpoint {there}: cannot reach it (Connection refused)"
    try:
        join(a.worker, files[a], listen=[here], connect=[there], start="erm", setup=erm_setup)
        join(b.worker, files[b], listen=[there], connect=[here], start="app", setup=erm_setup)
        b.call(hosts.rr_until_answered, "app", "erm", "camera", BOUND, timeout=30)
        a.call(hosts.rr_until_answered, "erm", "app", "camera", BOUND, timeout=30)
        unlinked = [host.worker.submit(unlinked_within, grace() + QUIET) for host in (a, b)]
        assert [[], []] == [future.result(timeout=30) for future in unlinked]
        warned = [host.call(hosts.rr_logs, "WARNING", timeout=10) for host in (a, b)]
        assert [] == [w for w in warned[0] if nobody_listened not in w], warned[0]
        assert [] == warned[1]
    finally:
        for host in (b, a):
            with contextlib.suppress(Exception):
                host.call(hosts.rr_stop, timeout=30)


def grace() -> float:
    """Seconds a connect endpoint may stay unlinked before its WARNING."""
    from rr_actors_lab.observe._links import GRACE  # noqa: PLC0415

    return GRACE


# -- row 2: plain TCP to the tls/ port ---------------------------------------------------------


def refused_plainly(answer: bytes) -> bool:
    """The listener's answer to plain TCP: nothing but a TLS alert record (content type 21),
    then the connection closed (or reset)."""
    answer = answer.removesuffix(b"RESET")
    return answer == b"" or answer.startswith(b"\x15\x03")


def test_plain_tcp_to_the_tls_port_is_closed_unread(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = two_hosts.a, two_hosts.b
    created = [tmp_path / f"created-{n}" for n in range(2)]
    payloads = [
        b"GET / HTTP/1.0\r\n\r\n",
        pickle.dumps(CreatesAFile(str(created[0]))),
        framed_pickle(created[1]),
    ]
    intruder = b.spawn()
    answers = [
        intruder.call(plain_attempt, a.address, PORT, payload, BOUND, timeout=30)
        for payload in payloads
    ]
    assert all(refused_plainly(answer) for answer in answers), answers
    member_calls(b, 1)
    never_appear(*created)
    member_calls(b, 2)


def test_a_plain_zenoh_peer_at_the_tls_port_gets_no_link(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = two_hosts.a, two_hosts.b
    created = tmp_path / "created"
    intruder = b.spawn()
    intruder.call(raw_open, [a.endpoint(PORT, "tcp")], None, 0.0, timeout=30)
    intruder.call(raw_intrude, "intruder", created, timeout=30)
    seen = a.worker.submit(hosts.names_within, "intruder", QUIET)
    member_calls(b, 1)
    never_appear(created)
    assert not seen.result(timeout=30)
    assert [] == intruder.call(raw_links, timeout=30)
    intruder.call(raw_close, timeout=30)
    member_calls(b, 2)


# -- row 3: refused in the handshake -----------------------------------------------------------


def odd_certificates(directory: Path, ca: tuple[Path, Path], address: str) -> dict[str, Any]:
    """Client certificates the listener must refuse, named `operator` (a member's name)
    and naming `address`: (cert, key) paths, or `None` for no certificate."""
    now = datetime.datetime.now(datetime.UTC)
    other = pki.make_ca(directory / "other", SYSTEM)  # another CA of the same name
    depot = pki.make_ca(directory / "depot", "depot")  # another system's
    made: dict[str, Any] = {
        "self-signed": pki.issue(directory / "self", "operator", (address,)),
        "another CA": pki.issue(directory / "other", "operator", (address,), ca=other),
        "another system's CA": pki.issue(directory / "depot", "operator", (address,), ca=depot),
        "expired": pki.issue(
            directory / "expired",
            "operator",
            (address,),
            ca=ca,
            not_before=now - 30 * pki.DAY,
            not_after=now - pki.DAY,
        ),
        "not yet valid": pki.issue(
            directory / "early", "operator", (address,), ca=ca, not_before=now + pki.DAY
        ),
        "no certificate": None,
    }
    return made


def test_a_client_without_the_systems_certificate_is_refused_in_the_handshake(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = two_hosts.a, two_hosts.b
    odd = odd_certificates(tmp_path / "odd", lab, b.address)
    intruder = b.spawn()
    created = {kind: tmp_path / f"created-{n}" for n, kind in enumerate(odd)}
    outcomes = {
        kind: intruder.call(
            tls_attempt,
            a.address,
            PORT,
            str(lab[0]),
            None if pair is None else str(pair[0]),
            None if pair is None else str(pair[1]),
            framed_pickle(created[kind]),
            timeout=30,
        )
        for kind, pair in odd.items()
    }
    assert outcomes == {
        "self-signed": "alert: TLSV1_ALERT_UNKNOWN_CA",
        "another CA": "alert: TLSV1_ALERT_DECRYPT_ERROR",  # its name, not its key
        "another system's CA": "alert: TLSV1_ALERT_UNKNOWN_CA",
        "expired": "alert: SSLV3_ALERT_CERTIFICATE_EXPIRED",
        "not yet valid": "alert: SSLV3_ALERT_CERTIFICATE_EXPIRED",  # rustls says so too
        "no certificate": "alert: TLSV13_ALERT_CERTIFICATE_REQUIRED",
    }
    member_calls(b, 1)
    never_appear(*created.values())
    member_calls(b, 2)


def test_an_rr_actors_host_so_refused_is_warned_with_the_reason_and_is_not_in(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    # b's files are valid for its own CA (depot's), and it trusts the lab's too, so its
    # only trouble is the listener's: it refuses b's certificate (`unknown ca`)
    a, b = two_hosts.a, two_hosts.b
    depot = pki.make_ca(tmp_path / "depot", "depot")
    trusted = tmp_path / "depot" / "trusted.pem"
    trusted.write_bytes(depot[0].read_bytes() + lab[0].read_bytes())
    refused = b.spawn()
    endpoint = a.endpoint(PORT, "tls")
    join(
        refused,
        tls_files(tmp_path / "depot", "operator", b.address, depot, trust=trusted),
        connect=[endpoint],
        start="mallory",
    )
    warning = refused.call(
        logged, "WARNING", [f"no link to connect endpoint {endpoint}"], BOUND, timeout=30
    )
    assert "the listener refused this host's certificate (unknown ca)" in warning
    assert "UnknownRegistrarError" in warning
    assert "UnknownRegistrarError" == refused.call(hosts.rr_run, "mallory", call_fails, timeout=30)
    created = tmp_path / "created"
    refused.call(put_through_router, f"rr/{SYSTEM}/reg/erm", created, timeout=30)
    seen = a.worker.submit(hosts.names_within, "mallory", QUIET)
    member_calls(b, 1)
    never_appear(created)
    assert not seen.result(timeout=30)
    assert [] == refused.call(router_links, timeout=30)
    member_calls(b, 2)


# -- row 4: signed by the system's CA, not a member --------------------------------------------


def test_a_ca_signed_non_member_links_but_every_message_is_dropped(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = two_hosts.a, two_hosts.b
    endpoint = a.endpoint(PORT, "tls")
    stranger_tls = tls_files(tmp_path / "lab", "stranger", b.address, lab, [*MEMBERS, "stranger"])
    stranger = b.spawn()
    join(stranger, stranger_tls, connect=[endpoint], start="mallory")
    warning = a.call(logged, "WARNING", ["'stranger'"], BOUND, timeout=30)
    assert f"'stranger' at {b.address} linked with a certificate signed by this system's CA" in (
        warning
    )
    assert "every message of it is dropped both ways" in warning

    # its link is up (robot is a member on its side), yet it sees nothing of a's
    def stranger_links() -> list[tuple[str, str]]:
        return [(n, where.split("#")[0]) for n, where in stranger.call(router_links, timeout=30)]

    assert wait_for(lambda: stranger_links() == [("robot", endpoint)], BOUND), stranger_links()
    assert "UnknownRegistrarError" == stranger.call(hosts.rr_run, "mallory", call_fails, timeout=30)

    # a raw session with the stranger's certificate: linked again from b's address
    created = tmp_path / "created"
    raw = b.spawn()
    assert ["robot"] == [
        name for name, _ in raw.call(raw_open, [endpoint], stranger_tls, timeout=30)
    ]
    raw.call(raw_intrude, "intruder", created, timeout=30)
    seen = a.worker.submit(hosts.names_within, "intruder", QUIET)
    member_calls(b, 1)
    never_appear(created)
    assert not seen.result(timeout=30)
    assert not a.call(hosts.names_within, "mallory", 0.0, timeout=30)
    raw.call(raw_close, timeout=30)
    a.call(logged, "INFO", [f"link to 'stranger' at {b.address} closed"], BOUND, timeout=30)
    assert 1 == len([m for m in a.call(hosts.rr_logs, "WARNING", timeout=30) if "stranger" in m])
    member_calls(b, 2)

    # the same put with a member's certificate is unpickled: the check above is not vacuous
    control = tmp_path / "control"
    member_tls = tls_files(tmp_path / "insider", "operator", b.address, lab)
    raw.call(raw_open, [endpoint], member_tls, timeout=30)
    raw.call(raw_intrude, "insider", control, timeout=30)
    assert wait_for(control.exists, BOUND)
    raw.call(raw_close, timeout=30)
    through = tmp_path / "through-a-members-router"  # (rows 3 and 5 put so)
    b.call(put_through_router, f"rr/{SYSTEM}/reg/erm", through, timeout=30)
    assert wait_for(through.exists, BOUND)
    member_calls(b, 3)


# -- row 5: a listener impostor ----------------------------------------------------------------


@pytest.mark.parametrize(
    "impostor",
    ["another CA", "a lab certificate for another address"],
)
def test_a_member_refuses_a_listener_impostor(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path, impostor: str
) -> None:
    # The impostor listens on a (port 7448) as `robot`, and accepts the lab's certificates:
    # only the member that dials it can refuse the link. The member dials the real `robot`
    # on a (port 7447) too, and calls its `erm` meanwhile.
    a, b = two_hosts.a, two_hosts.b
    fake = a.spawn()
    endpoint = a.endpoint(PORT + 1, "tls")
    if impostor == "another CA":
        depot = pki.make_ca(tmp_path / "depot", "depot")
        trusted = tmp_path / "depot" / "trusted.pem"
        trusted.write_bytes(depot[0].read_bytes() + lab[0].read_bytes())
        files = tls_files(tmp_path / "depot", "robot", a.address, depot, trust=trusted)
        reason = f"the listener's certificate is not signed by this system's CA {lab[0]}"
    else:
        files = tls_files(tmp_path / "elsewhere", "robot", "10.0.0.99", lab)
        reason = f"the listener's certificate does not name {a.address}"
    join(fake, files, listen=[endpoint], start="fake")
    dialer = b.spawn()
    join(
        dialer,
        tls_files(tmp_path / "dialer", "operator", b.address, lab),
        connect=[a.endpoint(PORT, "tls"), endpoint],
        start="dialer",
    )
    dialer.call(hosts.rr_until_answered, "dialer", "erm", "camera", BOUND, timeout=30)
    warning = dialer.call(
        logged, "WARNING", [f"no link to connect endpoint {endpoint}"], BOUND, timeout=30
    )
    assert reason in warning
    created = tmp_path / "created"
    fake.call(put_through_router, f"rr/{SYSTEM}/reg/dialer", created, timeout=30)
    seen = dialer.submit(hosts.names_within, "fake", QUIET)
    member_calls(b, 1)
    never_appear(created)
    assert not seen.result(timeout=30)
    assert [("robot", a.endpoint(PORT, "tls"))] == [
        (name, where.split("#")[0]) for name, where in dialer.call(router_links, timeout=30)
    ]
    assert {"stream": {"device": 2}} == dialer.call(
        hosts.rr_run, "dialer", call_camera, 2, timeout=30
    )
    member_calls(b, 3)


# -- row 6: a member whose key was replaced ----------------------------------------------------


def make_tls(files: dict[str, Any]) -> str:
    return repr(rr.ZenohTLS(**files))


def test_a_member_whose_key_was_replaced_gets_a_config_error_on_its_own_host(
    two_hosts: hosts.TwoHosts, tmp_path: Path
) -> None:
    a = two_hosts.a
    ca = pki.make_ca(tmp_path / "lab", SYSTEM)
    files = tls_files(tmp_path / "lab", "robot", a.address, ca)
    assert "name='robot'" in a.call(make_tls, files, timeout=30)
    _, other_key = pki.issue(tmp_path / "other", "robot", (a.address,), ca=ca)
    Path(files["key"]).write_bytes(other_key.read_bytes())
    with pytest.raises(rr.ConfigError) as caught:
        a.call(make_tls, files, timeout=30)
    assert f"key {files['key']} is not the private key of cert {files['cert']}" in str(caught.value)


# -- bounds: a burst of refused handshakes -----------------------------------------------------


def refused_burst(
    host: str, port: int, clients: int, each: int, ca: str, cert: str, key: str
) -> tuple[dict[str, int], float]:
    """`clients` threads started at once, each making `each` TLS handshakes with `cert`
    one after the other; how many ended how (`KEPT["burst"]` counts those done), and
    when the last one ended (`time.monotonic()`)."""
    done: list[str] = []
    hosts.KEPT["burst"] = done
    start = threading.Barrier(clients)

    def client() -> None:
        start.wait()
        for _ in range(each):
            try:
                done.append(tls_attempt(host, port, ca, cert, key, b"x"))
            except OSError as exc:
                done.append(f"error: {exc!r}")

    threads = [threading.Thread(target=client) for _ in range(clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    ended = time.monotonic()
    outcomes: dict[str, int] = {}
    for outcome in done:
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    return outcomes, ended


def burst_done() -> int:
    return len(hosts.KEPT.get("burst", []))


def keep_calling(registrar: rr.ResourceRegistrar) -> tuple[int, list[str]]:
    """Call `erm` until `KEPT["stop"]` is set, about 50 calls a second (a pace, so as not
    to load the machine more than a member does): how many succeeded, how others failed."""
    stop = hosts.KEPT.setdefault("stop", threading.Event())
    succeeded, failed = 0, []
    device = 100
    while not stop.wait(0.02):
        device += 1
        try:
            assert call_camera(registrar, device) == {"stream": {"device": device}}
            succeeded += 1
        except Exception as exc:
            failed.append(repr(exc))
    return succeeded, failed


def stop_calling() -> None:
    hosts.KEPT.setdefault("stop", threading.Event()).set()


def join_and_first_call(tls: dict[str, Any], endpoint: str) -> tuple[float, float]:
    """Seconds from joining (`ZenohNetwork` made) to this host's first answered call, and
    when that was (`time.monotonic()`: one clock for every process of the machine)."""
    started = time.monotonic()
    hosts.rr_join(system=SYSTEM, listen=[], connect=[endpoint], tls=tls)
    hosts.rr_start("late")
    hosts.rr_until_answered("late", "erm", "camera", 30.0)
    answered = time.monotonic()
    return answered - started, answered


def test_a_burst_of_refused_handshakes_fails_no_member_call_and_a_member_joins_during_it(
    two_hosts: hosts.TwoHosts, lab: tuple[Path, Path], tmp_path: Path
) -> None:
    # In during the burst, not after it: each refusal pauses the listener's accepts for
    # about 100 ms, so the 200 take 20 s or more, and a member that connects meanwhile
    # waits for the refusals queued before it only (20 clients: about 2 s; the benchmark
    # has the documented 10 s). On a loaded machine that took 10.2 s, past a 10 s bound.
    a, b = two_hosts.a, two_hosts.b
    bad_cert, bad_key = pki.issue(tmp_path / "self", "operator", (b.address,))
    burster, late = b.spawn(), b.spawn()  # (started before: a Python start is not the join)
    calling = b.worker.submit(hosts.rr_run, "app", keep_calling)
    burst = burster.submit(
        refused_burst, a.address, PORT, 20, 10, str(lab[0]), str(bad_cert), str(bad_key)
    )
    assert wait_for(lambda: burster.call(burst_done, timeout=10) >= 20, 30.0)
    joined_during = burster.call(burst_done, timeout=10)
    took, joined = late.call(
        join_and_first_call,
        tls_files(tmp_path / "late", "operator", b.address, lab),
        a.endpoint(PORT, "tls"),
        timeout=60,
    )
    outcomes, burst_ended = burst.result(timeout=120)
    b.call(stop_calling, timeout=10)
    succeeded, failed = calling.result(timeout=30)
    assert {"alert: TLSV1_ALERT_UNKNOWN_CA": 200} == outcomes
    assert joined_during < 200  # the member joined during the burst
    assert joined < burst_ended, f"a member joining during the burst took {took:.1f} s"
    assert [] == failed
    assert succeeded > 0
    member_calls(b, 1)


# -- bounds: a flood of failed handshakes from a third host ------------------------------------


def rejoin_seconds(two_hosts: hosts.TwoHosts) -> float:
    """Cut the veth between `a` and `b` until `b` has lost `erm`, bring it back: the
    seconds from then to `b`'s first answered call to `erm` (`rejoined`)."""
    two_hosts.link_down()
    try:
        assert two_hosts.b.call(hosts.rr_unlinked_within, "erm", BOUND, timeout=30)
    finally:
        two_hosts.link_up()
    return rejoined(two_hosts.b)


GIVE_UP = 30.0  # seconds after which a member that has not re-joined is counted as out


def rejoined(b: hosts.Host) -> float:
    """Seconds from now to `b`'s first answered call to `erm` (infinity: none within
    `GIVE_UP` s)."""
    started = time.monotonic()
    try:
        b.call(hosts.rr_until_answered, "app", "erm", "camera", GIVE_UP, timeout=GIVE_UP + 30)
    except rr.RrError:
        return float("inf")
    return time.monotonic() - started


def took(seconds: float) -> str:
    return f"in {seconds:.1f} s" if seconds < GIVE_UP else f"not within {GIVE_UP:g} s"


@pytest.fixture
def outsider_lab(tmp_path: Path) -> Iterator[tuple[hosts.TwoHosts, tuple[Path, Path]]]:
    """The `lab` on two hosts with an outsider `c` (a veth of its own to `a`)."""
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    with hosts.TwoHosts(outsider=True) as made, started_lab(made, tmp_path) as ca:
        yield made, ca


@pytest.mark.timeout(150)
def test_a_member_rejoins_in_10_s_while_a_third_host_floods_the_port_with_failed_handshakes(
    outsider_lab: tuple[hosts.TwoHosts, tuple[Path, Path]],
) -> None:
    two_hosts, _ = outsider_lab
    a, b, c = two_hosts.a, two_hosts.b, two_hosts.c
    assert c is not None
    attacker = c.spawn()
    calling = b.worker.submit(hosts.rr_run, "app", keep_calling)
    attacker.call(hosts.flood, a.address, PORT, 4, timeout=10)

    # until `a` says it drops the flood, or (without that) the flood has made 2,000
    # connections, each 0.1 s of the listener's time: a member re-joining after them
    # would wait minutes
    def seen() -> bool:
        said = [m for m in a.call(hosts.rr_logs, "WARNING", timeout=10) if c.address in m]
        return bool(said) or attacker.call(hosts.flood_counts, timeout=10)["connected"] >= 2000

    assert wait_for(seen, 30.0)
    seen_at = attacker.call(hosts.flood_counts, timeout=10)["attempts"]
    assert wait_for(  # (20 more: 2.5 s of a dropped flood, a moment of the other)
        lambda: attacker.call(hosts.flood_counts, timeout=10)["attempts"] >= seen_at + 20, 30.0
    )
    b.call(stop_calling, timeout=10)
    succeeded, failed = calling.result(timeout=30)
    assert [] == failed  # the link already up was not slowed down
    assert succeeded > 0
    before = attacker.call(hosts.flood_counts, timeout=10)["attempts"]
    during = rejoin_seconds(two_hosts)
    assert attacker.call(hosts.flood_counts, timeout=10)["attempts"] > before  # (still flooding)
    warning = a.call(logged, "WARNING", [f"{c.address} holds"], BOUND, timeout=30)
    assert f"connections to {a.address}:{PORT} and is not a member's address" in warning
    attacker.call(hosts.flood_stop, timeout=30)
    after = rejoin_seconds(two_hosts)
    rejoins = f"b re-joined {took(during)} during the flood, {took(after)} after it"
    assert max(during, after) < 10.0, rejoins
    member_calls(b, 1)


@pytest.mark.timeout(150)
def test_a_member_rejoins_in_10_s_while_a_third_host_floods_the_port_from_32_addresses(
    outsider_lab: tuple[hosts.TwoHosts, tuple[Path, Path]],
) -> None:
    # Each of c's 32 addresses holds fewer connections than the gate drops one for; all
    # together hold the listener's queue: the port takes members' addresses only.
    two_hosts, _ = outsider_lab
    a, b, c = two_hosts.a, two_hosts.b, two_hosts.c
    assert c is not None
    stem = c.address.rsplit(".", 1)[0]
    sources = [c.address, *(f"{stem}.{n}" for n in range(100, 131))]
    for address in sources[1:]:
        c.run("ip", "addr", "add", f"{address}/24", "dev", hosts.OUTSIDE)
    attacker = c.spawn()
    calling = b.worker.submit(hosts.rr_run, "app", keep_calling)
    attacker.call(hosts.flood, a.address, PORT, 4, sources, timeout=10)

    def seen() -> bool:  # said, or (without that) 200 connections made, 20 s of the listener's
        said = [m for m in a.call(hosts.rr_logs, "WARNING", timeout=10) if "none a member" in m]
        return bool(said) or attacker.call(hosts.flood_counts, timeout=10)["connected"] >= 200

    assert wait_for(seen, 30.0)
    seen_at = attacker.call(hosts.flood_counts, timeout=10)["attempts"]
    assert wait_for(
        lambda: attacker.call(hosts.flood_counts, timeout=10)["attempts"] >= seen_at + 20, 30.0
    )
    b.call(stop_calling, timeout=10)
    succeeded, failed = calling.result(timeout=30)
    before = attacker.call(hosts.flood_counts, timeout=10)["attempts"]
    during = rejoin_seconds(two_hosts)
    assert attacker.call(hosts.flood_counts, timeout=10)["attempts"] > before  # (still flooding)
    attacker.call(hosts.flood_stop, timeout=30)
    after = rejoin_seconds(two_hosts)

    rejoins = f"b re-joined {took(during)} during the flood, {took(after)} after it"
    assert max(during, after) < 10.0, rejoins
    assert [] == failed  # the link already up was not slowed down
    assert succeeded > 0
    warning = a.call(logged, "WARNING", ["none a member's"], BOUND, timeout=30)
    assert f"connections to {a.address}:{PORT}" in warning
    assert f"the port takes packets only from members' addresses ({b.address})" in warning
    member_calls(b, 1)


# -- bounds: forged SYNs from a third host, carrying a member's address (issue 40) --------------

SPOOF_RATE = 13.0  # forged SYNs a second (the issue's run)
SPOOFED = 40  # forged SYNs sent while the member is out of reach (about 3 s of them)


def half_open(host: hosts.Host, source: str) -> int:
    """How many half-open connections (`SYN-RECV`) from `source` to port `PORT` `host`
    holds now (iproute2's `ss`, in its namespace)."""
    lines = host.run("ss", "-Htn", "state", "syn-recv", "sport", "=", f":{PORT}", "dst", source)
    return len(lines.splitlines())


def out_of_reach(two_hosts: hosts.TwoHosts) -> None:
    """Take `b`'s end of the veth down, as a robot that leaves the radio's range: `a`
    keeps its route to `b`'s address (its end stays up, without a carrier), so what it
    sends there vanishes. Returns once `b` has lost `erm`."""
    two_hosts.b.run("ip", "link", "set", hosts.INTERFACE, "down")
    assert two_hosts.b.call(hosts.rr_unlinked_within, "erm", BOUND, timeout=30)


def back_in_reach(two_hosts: hosts.TwoHosts) -> None:
    two_hosts.b.run("ip", "link", "set", hosts.INTERFACE, "up")


@pytest.mark.timeout(240)
def test_a_member_rejoins_in_10_s_though_a_third_host_forges_syns_from_its_address(
    outsider_lab: tuple[hosts.TwoHosts, tuple[Path, Path]],
) -> None:
    # The issue's run: while member b is out of reach, c sends 13 SYNs a second whose
    # source is b's address, to a's tls/ port. a answers each toward b and holds it
    # half-open (more than the gate's HOLD of them: on main's code, b's address was
    # dropped, and b's own re-dials kept the drop up). b's link comes back while the
    # forging goes on (during), then once more after a second run of it (after).
    from rr_actors._transport.zenoh.ops.gate import HOLD  # noqa: PLC0415

    two_hosts, _ = outsider_lab
    a, b, c = two_hosts.a, two_hosts.b, two_hosts.c
    assert c is not None
    spoofer = c.spawn()

    def sent(more: int) -> None:
        assert wait_for(
            lambda: spoofer.call(spoof.spoof_counts, timeout=10)["sent"] >= more,
            BOUND + SPOOFED / SPOOF_RATE,
        )

    out_of_reach(two_hosts)
    try:
        spoofer.call(spoof.spoof_start, b.address, a.address, PORT, SPOOF_RATE, timeout=10)
        # landed: as many half-open connections from b's address as main's gate dropped
        # an address for (with b's old link still closing there)
        assert wait_for(lambda: half_open(a, b.address) >= HOLD, BOUND)
        sent(SPOOFED)
    finally:
        back_in_reach(two_hosts)
    during = rejoined(b)
    so_far = spoofer.call(spoof.spoof_counts, timeout=10)["sent"]
    out_of_reach(two_hosts)
    try:
        sent(so_far + SPOOFED)
        spoofer.call(spoof.spoof_stop, timeout=10)
    finally:
        back_in_reach(two_hosts)
    after = rejoined(b)

    dropped_b = [m for m in a.call(hosts.rr_logs, "WARNING", timeout=10) if b.address in m]
    rejoins = f"b re-joined {took(during)} while its address was forged, {took(after)} after it"
    assert max(during, after) < 10.0, rejoins
    assert [] == dropped_b
    member_calls(b, 1)
