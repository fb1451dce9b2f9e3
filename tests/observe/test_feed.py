"""The system's event stream over Zenoh on one host (`rr_actors_lab.observe._feed`).

A `ZenohNetwork` on loopback (plain TCP: nothing crosses a machine), its registrars, and
a raw Zenoh session that attaches through the router's Unix socket (as a buggy member
process of this host could) and puts what it likes on `rr/<system>/ev/<zid>`:

- the subscription hands over this host's events, with the member name and stamps, in
  `hlc` order;
- a pickle (one that would create a file if unpickled) and lines that are no events are
  dropped with a WARNING and never unpickled: `pickle` and `cloudpickle`'s loaders are
  watched while the stream is read, and the file never appears; a valid line after
  them is still delivered (the check is not vacuous);
- a process sends its events only while someone subscribes (Zenoh's matching status);
- with TLS (on loopback, `tests/pki.py`'s certificates) the events of a supervisor's
  manager process, which it sends itself, carry the member name as the router's do;
- `window` out of range is a `ConfigError` naming it.
"""

from __future__ import annotations

import json
import os
import pickle
import socket
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors_lab.observe import _feed as zenoh_events
from tests.support import pki
from tests.support.hostile import CreatesAFile
from tests.support.hosts import free_port
from tests.support.waiting import wait_for

zenoh = pytest.importorskip("zenoh")

BOUND = 10.0


@pytest.fixture
def net() -> Iterator[rr.ZenohNetwork]:
    network = rr.ZenohNetwork(
        system=f"ev-{uuid.uuid4().hex[:8]}", listen=[f"tcp/127.0.0.1:{free_port()}"], tls=None
    )
    yield network
    network.close()


@pytest.fixture
def erm(net: rr.ZenohNetwork) -> Iterator[rr.ResourceRegistrar]:
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
    registrar.register_server("camera", load=lambda request: request, unload=lambda *_: None)
    yield registrar
    registrar.stop()


def _raw_session(network: rr.ZenohNetwork) -> Any:
    config = zenoh.Config.from_json5(
        '{"mode": "client", "scouting": {"multicast": {"enabled": false}}, '
        f'"connect": {{"endpoints": ["unixsock-stream/{network.address.socket_path}"]}}}}'
    )
    return zenoh.open(config)


def test_the_subscription_gets_this_hosts_events_in_hlc_order(
    net: rr.ZenohNetwork, erm: rr.ResourceRegistrar
) -> None:
    seen: list[events.Event] = []
    with net.subscribe_events(seen.append, window=0.2) as subscription:
        query = erm.call("erm", "camera", {"device": 1})
        erm.unload(query.id)
        assert wait_for(lambda: any(isinstance(e, events.QueryForgotten) for e in seen), BOUND)
        assert subscription.wait_delivered(timeout=BOUND)
    kinds = [type(e).__name__ for e in seen if getattr(e, "query_id", None) == query.id]
    assert kinds[:3] == ["ResourceLoaded", "ConsumerAdded", "CallAnswered"]
    assert [e.hlc for e in seen] == sorted(e.hlc for e in seen)
    assert {e.host for e in seen} == {socket.gethostname()}  # (no TLS: the host name)


def test_what_is_not_an_event_is_dropped_and_nothing_is_unpickled(
    net: rr.ZenohNetwork, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: Any
) -> None:
    evil = tmp_path / "created-by-unpickling"
    unpickled: list[str] = []
    real_loads = pickle.loads

    def watched(*args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name == "rr-events-merge":
            unpickled.append("pickle.loads")
        return real_loads(*args, **kwargs)

    monkeypatch.setattr(pickle, "loads", watched)
    seen: list[events.Event] = []
    good = events.InDoubt("erm", "q-good", at=1.0, pid=1, host="robot", hlc=5 << 12)
    raw = _raw_session(net)
    try:
        with net.subscribe_events(seen.append, window=0) as _subscription:
            key = f"rr/{net.system}/ev/{raw.zid()}"
            publisher = raw.declare_publisher(key)
            assert wait_for(lambda: publisher.matching_status.matching, BOUND)
            publisher.put(pickle.dumps(CreatesAFile(str(evil))))
            publisher.put(b'{"type": "InDoubt", "schema": 3}\nnot json\n[1, 2]')
            publisher.put(json.dumps(events.to_dict(good)).encode())
            assert wait_for(lambda: good in seen, BOUND)
            publisher.undeclare()
    finally:
        raw.close()
    assert [good] == seen
    assert not evil.exists()
    assert [] == unpickled
    dropped = [r.getMessage() for r in caplog.records if "event stream" in r.getMessage()]
    assert dropped
    assert key in dropped[0]


def test_a_process_sends_its_events_only_while_someone_subscribes(
    net: rr.ZenohNetwork, erm: rr.ResourceRegistrar
) -> None:
    tap = events.everything()
    assert not tap.listened  # nobody subscribed: the registrars build no event for it
    raw = _raw_session(net)
    heard: list[str] = []
    try:
        subscriber = raw.declare_subscriber(
            f"rr/{net.system}/ev/*", lambda sample: heard.append(str(sample.key_expr))
        )
        assert wait_for(lambda: tap.listened, BOUND)  # (Zenoh's matching status)
        query = erm.call("erm", "camera", {"device": 2})
        assert wait_for(lambda: bool(heard), BOUND)
        erm.unload(query.id)
        subscriber.undeclare()
        assert wait_for(lambda: not tap.listened, BOUND)
    finally:
        raw.close()


def test_events_given_right_before_a_close_are_still_sent(net: rr.ZenohNetwork) -> None:
    # (a manager process's last events, as it stops: once dropped by a close that gave its
    # forwarder no time at all, and warned of on the demo's terminal)
    from rr_actors_lab.observe._feed import EventExport, decode  # noqa: PLC0415

    keys = net.services().keys
    listening, exporting = _raw_session(net), _raw_session(net)
    zid = str(exporting.info.zid())
    heard: list[events.Event] = []
    try:
        listening.declare_subscriber(
            keys.events(zid), lambda sample: heard.extend(decode(sample.payload.to_bytes())[0])
        )
        export = EventExport(exporting, keys, zid)
        assert export.wait_sending(BOUND)  # (Zenoh's matching status)
        events.everything().publish(events.EventsDropped(7, "full"))

        export.close()

        assert wait_for(
            lambda: any(isinstance(e, events.EventsDropped) and e.count == 7 for e in heard),
            BOUND,
        )
    finally:
        exporting.close()
        listening.close()


def camera_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("camera", load=lambda request: request, unload=lambda *_: None)


def test_with_tls_every_process_names_the_member_a_manager_process_too(
    tmp_path: Path, process_helpers: Any
) -> None:
    ca = pki.make_ca(tmp_path, "lab")
    cert, key = pki.issue(tmp_path, "robot", ["127.0.0.1"], ca=ca)
    tls = rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=["robot"])
    system = f"ev-{uuid.uuid4().hex[:8]}"
    net = rr.ZenohNetwork(system=system, listen=["tls/127.0.0.1:0"], tls=tls)
    seen: list[events.Event] = []
    spec = rr.ManagerSpec("erm", setup=camera_setup, isolation="process")
    with net, rr.Supervisor([spec], network=net) as sup:
        app = sup.registrar("app")
        with net.subscribe_events(seen.append, window=0.2):
            query_ids = []
            while not wait_for(
                lambda: any(isinstance(e, events.ResourceLoaded) for e in seen), 0.2
            ):
                query_ids.append(app.call("erm", "camera", {"device": len(query_ids)}).id)
                assert len(query_ids) < BOUND / 0.2, "no event of the manager process came"
            pids = {e.pid for e in seen if isinstance(e, events.ResourceLoaded)}
            assert wait_for(lambda: any(isinstance(e, events.CallAnswered) for e in seen), BOUND)
    assert pids
    assert os.getpid() not in pids  # (its own process's events, sent by it)
    assert {"robot"} == {e.host for e in seen}


def _in_doubt(query_id: str, stamp: int) -> bytes:
    line = events.InDoubt("erm", query_id, at=1.0, pid=1, host="robot", hlc=stamp << 12)
    return json.dumps(events.to_dict(line)).encode()


def test_a_member_that_floods_big_batches_is_dropped_past_its_bound_and_the_others_are_not(
    net: rr.ZenohNetwork, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 40: one member's batches of 14 MiB (the per-batch limit allows 16) filled a
    subscriber's memory, 1,024 of them in all. Now what a subscriber holds of one sender is
    bounded (`HELD_BYTES`): a second big batch that comes while the first is held for its
    `window` is dropped unread, counted in an `EventsDropped` before what comes after it,
    and warned of naming the sender; another member's events still come. (The memory this
    saves is measured in `benchmarks/bench_events_flood.py`.)"""
    flood = [_in_doubt(f"big-{i}-" + "x" * (1024 * 1024), 10 + i) for i in range(14)]
    batch = b"\n".join(flood)  # 14 MiB
    seen: list[events.Event] = []
    flooder, other = _raw_session(net), _raw_session(net)
    try:
        with net.subscribe_events(seen.append, window=5.0) as subscription:
            key = f"rr/{net.system}/ev/{flooder.zid()}"
            block = zenoh.CongestionControl.BLOCK  # (else Zenoh may drop a big put itself)
            publisher = flooder.declare_publisher(key, congestion_control=block)
            other_publisher = other.declare_publisher(
                f"rr/{net.system}/ev/{other.zid()}", congestion_control=block
            )
            assert wait_for(lambda: publisher.matching_status.matching, BOUND)
            assert wait_for(lambda: other_publisher.matching_status.matching, BOUND)
            publisher.put(batch)
            publisher.put(batch)  # (while the first is held: over the sender's bound)
            publisher.put(_in_doubt("after", 30))
            other_publisher.put(_in_doubt("other", 31))
            ids = lambda: {getattr(e, "query_id", None) for e in seen}  # noqa: E731
            assert wait_for(lambda: {"after", "other"} <= ids(), 3 * BOUND)
            assert subscription.wait_delivered(timeout=BOUND)
    finally:
        flooder.close()
        other.close()

    kinds = [
        "dropped" if isinstance(e, events.EventsDropped) else e.query_id.split("-")[0]
        for e in seen
        if isinstance(e, events.EventsDropped | events.InDoubt)
    ]
    # (the notice is told as the drop is seen; the events are held `window` s)
    assert ["dropped", *["big"] * 14, "after", "other"] == kinds
    assert 14 == next(e.count for e in seen if isinstance(e, events.EventsDropped))
    warned = [r.getMessage() for r in caplog.records if "dropped 14 events" in r.getMessage()]
    assert 1 == len(warned)
    assert key in warned[0]
    assert "HELD_BYTES" in warned[0]


def test_a_batch_whose_events_weigh_more_than_the_bound_is_read_up_to_it_and_counted(
    net: rr.ZenohNetwork, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A batch of small events weighs more read (`EVENT_BYTES` each) than its bytes: what
    would pass the bound is dropped as it is read, and every event is either delivered or
    counted in an `EventsDropped` (the bounds are made small here to keep it quick)."""
    monkeypatch.setattr(zenoh_events, "HELD_BYTES", (64 * 1024, 256 * 1024))
    sent = 400
    batch = b"\n".join(_in_doubt(f"q-{i}", 10 + i) for i in range(sent))  # ~60 KiB
    seen: list[events.Event] = []
    raw = _raw_session(net)
    try:
        with net.subscribe_events(seen.append, window=0) as subscription:
            key = f"rr/{net.system}/ev/{raw.zid()}"
            publisher = raw.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_for(lambda: publisher.matching_status.matching, BOUND)
            publisher.put(batch)
            assert wait_for(lambda: any(isinstance(e, events.EventsDropped) for e in seen), BOUND)
            assert subscription.wait_delivered(timeout=BOUND)
    finally:
        raw.close()

    delivered = [e for e in seen if isinstance(e, events.InDoubt)]
    dropped = sum(e.count for e in seen if isinstance(e, events.EventsDropped))
    assert 0 < len(delivered) < sent
    assert sent == len(delivered) + dropped
    assert [f"q-{i}" for i in range(len(delivered))] == [e.query_id for e in delivered]
    warned = [r.getMessage() for r in caplog.records if "would pass HELD_BYTES" in r.getMessage()]
    assert 1 == len(warned)
    assert key in warned[0]


def _sealer(directory: Path, name: str, ca: Any, members: list[str]) -> Any:
    """A `Seal` with the certificate of member `name` (issued by `ca` into `directory`)."""
    from rr_actors_lab.observe._seal import Seal  # noqa: PLC0415 - cryptography

    cert, key = pki.issue(directory, name, ["127.0.0.1"], ca=ca, key_type=KEY_TYPES[name])
    return Seal(rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=members), SEALED_SYSTEM)


SEALED_SYSTEM = "sealed"
KEY_TYPES = {"robot": "p256", "operator": "ed25519", "stranger": "p384", "forger": "rsa2048"}


@pytest.mark.parametrize("key_type", ["p256", "rsa2048"])
def test_with_tls_the_host_of_an_event_is_the_member_whose_certificate_sealed_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, key_type: str
) -> None:
    """Issue 40: a member's events that said another host's name were delivered as that
    host's. Now a batch is sealed by its host's certificate (`seal`), and an event's host
    is its sealer's whatever the event says. What no member sealed is dropped: no seal,
    a certificate of another CA or of a name not in `members`, a batch changed after
    it was sealed, a seal of another system's batch. (A raw Zenoh session attached
    through the router's Unix socket puts each, as a buggy member process could.)"""
    members = ["robot", "operator"]
    ca = pki.make_ca(tmp_path, "lab")
    cert, key = pki.issue(tmp_path, "robot", ["127.0.0.1"], ca=ca, key_type=key_type)
    tls = rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=members)
    operator = _sealer(tmp_path, "operator", ca, members)
    stranger = _sealer(tmp_path, "stranger", ca, ["stranger"])  # (its CA, not a member)
    other_ca = pki.make_ca(tmp_path / "other", "lab")
    forger = _sealer(tmp_path / "other", "forger", other_ca, ["forger"])
    from rr_actors_lab.observe._seal import Seal  # noqa: PLC0415 - cryptography

    elsewhere = Seal(rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=members), "elsewhere")
    claims_robot = _in_doubt("claims-robot", 10)  # (`host` "robot": this host's name)
    tampered = _in_doubt("tampered", 11)
    batches = [
        (claims_robot, operator.seal(claims_robot)),  # delivered, as operator's
        (_in_doubt("unsealed", 12), None),
        (_in_doubt("stranger", 13), stranger.seal(_in_doubt("stranger", 13))),
        (_in_doubt("forger", 14), forger.seal(_in_doubt("forger", 14))),
        (tampered.replace(b"tampered", b"tampere!"), operator.seal(tampered)),
        (_in_doubt("elsewhere", 15), elsewhere.seal(_in_doubt("elsewhere", 15))),
        (_in_doubt("last", 16), operator.seal(_in_doubt("last", 16))),
    ]
    net = rr.ZenohNetwork(system=SEALED_SYSTEM, listen=["tls/127.0.0.1:0"], tls=tls)
    seen: list[events.Event] = []
    with net, net.subscribe_events(seen.append, window=0) as subscription:
        raw = _raw_session(net)
        try:
            publisher = raw.declare_publisher(
                f"rr/{net.system}/ev/{raw.zid()}",
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            assert wait_for(lambda: publisher.matching_status.matching, BOUND)
            for data, seal in batches:
                publisher.put(data, attachment=seal)
            ids = lambda: {getattr(e, "query_id", None) for e in seen}  # noqa: E731
            assert wait_for(lambda: "last" in ids(), BOUND)
            assert subscription.wait_delivered(timeout=BOUND)
        finally:
            raw.close()

    theirs = [e for e in seen if isinstance(e, events.InDoubt)]
    assert [("claims-robot", "operator"), ("last", "operator")] == [
        (e.query_id, e.host) for e in theirs
    ]
    dropped = [(e.count, e.cause) for e in seen if isinstance(e, events.EventsDropped)]
    assert 5 == sum(count for count, _ in dropped)
    assert {"refused"} == {cause for _, cause in dropped}
    said = [r.getMessage() for r in caplog.records if "sealed by member" in r.getMessage()]
    assert 1 == len(said)
    assert "sealed by member operator, say they happened on host 'robot'" in said[0]
    assert any("no member's certificate sealed it" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("window", [-1, 61, "1", True, float("nan")])
def test_a_window_out_of_range_is_a_config_error(net: rr.ZenohNetwork, window: Any) -> None:
    with pytest.raises(rr.ConfigError, match="window"):
        net.subscribe_events(print, window=window)


def test_a_manager_process_that_takes_the_feed_imports_no_supervisor_and_no_web_server() -> None:
    """A process that attaches through its router unpickles the router's `Across` (its
    address carries it), which imports this module there: it must not pull the
    supervisor (the observer's protocol lives beside it, `_supervision.watching`) nor
    the observer's web server."""
    code = (
        "import sys, rr_actors_lab.observe._feed; "
        "print(sorted(m for m in ('rr_actors._supervision.supervisor', 'starlette', "
        "'uvicorn') if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )

    assert "[]" == done.stdout.strip()
