"""The Zenoh link (`rr_actors._transport.zenoh.link`): outboxes drained at a close;
`TestABuggyMember`: what a buggy member sends costs the inbox bounded threads and lines.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing.connection
import queue
import struct
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zenoh

import rr_actors as rr
from rr_actors._core import hlc
from rr_actors._core.wire import WIRE_VERSION
from rr_actors._registrar.life import Served
from rr_actors._transport.codec import NO_REPLY, frame
from rr_actors._transport.zenoh.link import Outboxes
from rr_actors._transport.zenoh.net import ZenohNetwork
from rr_actors._transport.zenoh.wire import MESSAGE, PLAIN, PYTHON, Keys, envelope
from tests.support.carriers import record_warnings, setup_servers, warnings_logged

BOUND = 10.0


"""Seconds a put may take to be received here (it takes milliseconds)."""


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    """A Zenoh session on its own: no router, no scouting; it hears its own puts."""
    config = zenoh.Config.from_json5(
        '{"mode": "peer", "scouting": {"multicast": {"enabled": false}}, '
        '"listen": {"endpoints": []}}'
    )
    opened = zenoh.open(config)
    yield opened
    opened.close()  # type: ignore[no-untyped-call]


def _received(session: zenoh.Session, key: str) -> queue.Queue[bytes]:
    got: queue.Queue[bytes] = queue.Queue()
    session.declare_subscriber(key, lambda sample: got.put(sample.payload.to_bytes()))
    return got


WAIT = 10.0


"""Seconds any one step may take on a loaded machine."""


@contextlib.contextmanager
def buggy_member(network: ZenohNetwork) -> Iterator[zenoh.Session]:
    """A raw Zenoh session attached through `network`'s router, with a process token (a
    member, as far as liveliness says); closed on exit."""
    config = zenoh.Config.from_json5(
        '{"mode": "client", "scouting": {"multicast": {"enabled": false}}, '
        f'"connect": {{"endpoints": ["unixsock-stream/{network.address.socket_path}"]}}}}'
    )
    session = zenoh.open(config)
    try:
        token = session.liveliness().declare_token(f"rr/{network.system}/live/proc/{session.zid()}")
        yield session
        token.undeclare()
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _header(kind: int, sender: str, wire: int = WIRE_VERSION) -> bytes:
    zid = sender.encode("ascii")
    return struct.pack("!2sBBBBB", b"rz", wire, *PYTHON, kind, len(zid)) + zid


def _put(session: zenoh.Session, key: str, payload: bytes) -> None:
    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def _warnings(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and text in r.getMessage()
    ]


def _registrar(network: ZenohNetwork) -> rr.ResourceRegistrar:
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"r-{uuid.uuid4().hex[:6]}", call_timeout=WAIT)
    )
    network.serve(Served(registrar))
    return registrar


# -- item 6: nothing of a member's runs on Zenoh's thread ------------------------------------------


class _Gate:
    """Holds the thread that unpickles a `_Held` frame (in the process that unpickles it)."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()


GATE = _Gate()


def _hold(value: Any) -> Any:
    GATE.entered.set()
    GATE.release.wait(20)
    return value


class _Held:
    """Unpickles as `value`, once `GATE.release` is set (in the unpickling process)."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __reduce__(self) -> tuple[Any, ...]:
        return (_hold, (self.value,))


def _gate_entered(_registrar: Any) -> bool:
    return GATE.entered.wait(WAIT)


def _gate_closed(_registrar: Any) -> bool:
    return not GATE.release.is_set()


def _open_gate(_registrar: Any) -> None:
    GATE.release.set()


def _manager(address: Any, name: str, control: multiprocessing.connection.Connection) -> None:
    """A process attached through the router (one link: every frame for it comes that way)
    that serves registrar `name` until its control pipe says so."""
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, call_timeout=WAIT))
    try:
        setup_servers(registrar)
        member.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        GATE.release.set()
        registrar.stop()
        member.close()


# -- item 7: a flood of what is not a message ----------------------------------------------------


class _Counter:
    """Counts the `_Counted` values unpickled in this process."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.count = 0
        self.target = 0
        self.reached = threading.Event()


COUNTER = _Counter()


def _counted(n: int) -> int:
    with COUNTER.lock:
        COUNTER.count += 1
        if COUNTER.count == COUNTER.target:
            COUNTER.reached.set()
    return n


class _Counted:
    """Unpickles as `n`, counted (`COUNTER`)."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __reduce__(self) -> tuple[Any, ...]:
        return (_counted, (self.n,))


# -- issue 40, section 3: a clock stamp far ahead -------------------------------------------------

YEAR_2100 = 4_102_444_800.0


"""2100-01-01 00:00:00 UTC, in seconds since the epoch."""


def _clock_now(_registrar: Any) -> tuple[float, float]:
    """This (child) process's clock: its last stamp's physical part and its physical time,
    in seconds since the epoch."""
    return hlc.seconds(hlc.CLOCK.now()), hlc.CLOCK.wall()


def test_what_was_sent_before_close_is_put_within_the_drain(session: zenoh.Session) -> None:
    keys = Keys(f"test-{uuid.uuid4().hex[:8]}")
    key = keys.registrar("provider")
    got = _received(session, key)
    outboxes = Outboxes(session, keys)
    # A first message to a process that never answers a ping: the writer pings until the
    # outboxes close (at most HEAL_TIMEOUT), so everything below is still queued at close.
    outbox = outboxes.get(key, first_to="nobody")
    sent = [f"message {n}".encode() for n in range(50)]
    for data in sent:
        assert outbox.send(data)

    outboxes.close(drain=BOUND)

    assert [got.get(timeout=BOUND) for _ in sent] == sent


def test_a_close_without_a_drain_drops_what_is_queued_and_runs_each_on_lost(
    session: zenoh.Session,
) -> None:
    keys = Keys(f"test-{uuid.uuid4().hex[:8]}")
    key = keys.registrar("provider")
    outcomes: queue.Queue[tuple[str, bytes]] = queue.Queue()  # ("put" | "lost", message)
    session.declare_subscriber(key, lambda sample: outcomes.put(("put", sample.payload.to_bytes())))
    outboxes = Outboxes(session, keys)
    outbox = outboxes.get(key, first_to="nobody")  # (its writer pings, as above)
    sent = [b"0", b"1", b"2"]
    for data in sent:
        assert outbox.send(data, on_lost=lambda data=data: outcomes.put(("lost", data)))

    outboxes.close()

    # The first message is the writer's task under way (its ping ends at the close): it
    # is put, or lost if the publisher went first. The two queued behind it are dropped.
    # Each message has exactly one outcome.
    seen = sorted((data, how) for how, data in (outcomes.get(timeout=BOUND) for _ in sent))
    assert [data for data, _ in seen] == sent
    assert [how for _, how in seen][1:] == ["lost", "lost"]
    assert not outbox.send(b"late")


def test_a_close_without_a_drain_drops_the_queue_before_the_ping_under_way_ends(
    session: zenoh.Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The forced interleaving of a flake under load (CI-like run with 4 workers): the
    # close ended the first put's ping before it dropped the queue, so a writer that ran
    # in between put all three. Here each outbox's close waits until either the writer
    # put the last message (the ping ended first: the flaw) or the ping asked twice more
    # since the close began (it goes on until the queue is dropped): each outcome is an
    # event, not a time.
    keys = Keys(f"test-{uuid.uuid4().hex[:8]}")
    key = keys.registrar("provider")
    outcomes: queue.Queue[tuple[str, bytes]] = queue.Queue()
    last_put = threading.Event()

    def heard(sample: zenoh.Sample) -> None:
        outcomes.put(("put", sample.payload.to_bytes()))
        if sample.payload.to_bytes() == b"2":
            last_put.set()

    session.declare_subscriber(key, heard)
    pings = threading.Semaphore(0)

    class Counted:  # the session, its gets (the pings) counted
        def __getattr__(self, name: str) -> Any:
            return getattr(session, name)

        def get(self, *args: Any, **kwargs: Any) -> Any:
            pings.release()
            return session.get(*args, **kwargs)

    from rr_actors._transport.zenoh import link  # noqa: PLC0415

    close = link.Outbox.close

    def close_when_forced(outbox: link.Outbox, timeout: float = 0.0) -> None:
        while pings.acquire(blocking=False):
            pass  # (the pings before the close)
        deadline = BOUND
        asked = 0
        while not last_put.is_set() and asked < 2 and deadline > 0:
            if pings.acquire(timeout=0.01):
                asked += 1
            deadline -= 0.01
        close(outbox, timeout)

    monkeypatch.setattr(link.Outbox, "close", close_when_forced)
    outboxes = Outboxes(Counted(), keys)  # type: ignore[arg-type]
    outbox = outboxes.get(key, first_to="nobody")
    sent = [b"0", b"1", b"2"]
    for data in sent:
        assert outbox.send(data, on_lost=lambda data=data: outcomes.put(("lost", data)))
    assert pings.acquire(timeout=BOUND)  # (the writer pings)

    outboxes.close()

    seen = sorted((data, how) for how, data in (outcomes.get(timeout=BOUND) for _ in sent))
    assert [data for data, _ in seen] == sent
    assert [how for _, how in seen][1:] == ["lost", "lost"]


class _Watched:
    """`session`, its publishers wrapped: each one's undeclare and free name their thread."""

    def __init__(self, session: zenoh.Session) -> None:
        self._session = session
        self.undeclared: queue.Queue[str] = queue.Queue()
        self.freed: queue.Queue[str] = queue.Queue()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._session, name)

    def declare_publisher(self, *args: Any, **kwargs: Any) -> Any:
        watched = self

        class Publisher:
            def __init__(self) -> None:
                self.real = watched._session.declare_publisher(*args, **kwargs)

            def put(self, data: bytes) -> None:
                self.real.put(data)

            def undeclare(self) -> None:
                watched.undeclared.put(threading.current_thread().name)
                self.real.undeclare()

            def __del__(self) -> None:
                watched.freed.put(threading.current_thread().name)

        return Publisher()


def test_a_closed_outbox_lets_its_publisher_go_on_its_writer_thread(
    session: zenoh.Session,
) -> None:
    # zenoh-python's free of a publisher releases the GIL: it must happen on a thread the
    # session's close joins, not wherever the outbox's last reference goes (kept here).
    keys = Keys(f"test-{uuid.uuid4().hex[:8]}")
    watched = _Watched(session)
    outboxes = Outboxes(watched, keys)  # type: ignore[arg-type]
    outbox = outboxes.get(keys.registrar("provider"))
    assert outbox.send(b"started")  # (its writer thread runs)

    outboxes.close()

    writer = "rr-zput-provider"
    assert (watched.undeclared.get(timeout=WAIT), watched.freed.get(timeout=WAIT)) == (
        writer,
        writer,
    )
    assert outbox.closed


def test_a_publisher_declared_by_the_task_under_way_at_the_close_is_undeclared_after_it(
    session: zenoh.Session,
) -> None:
    # A lane's outbox declares its publisher on its writer thread once the network said
    # who serves the name (`ZenohCarrier.found`); the server's going closes the outbox
    # meanwhile: the publisher declared after the close must still go.
    keys = Keys(f"test-{uuid.uuid4().hex[:8]}")
    watched = _Watched(session)
    outboxes = Outboxes(watched, keys)  # type: ignore[arg-type]
    lane = outboxes.get(keys.registrar("provider"), declared=False)
    asking, answered = threading.Event(), threading.Event()

    def found() -> None:  # (as `ZenohCarrier.found`: asks the network, then declares)
        asking.set()
        assert answered.wait(WAIT)
        lane.declare()

    assert lane.run(found)
    assert asking.wait(WAIT)
    popped = outboxes.pop(lane.key)  # (`ZenohCarrier.server_gone`)
    assert popped is lane
    lane.close()
    answered.set()

    writer = "rr-zput-provider"
    assert (watched.undeclared.get(timeout=WAIT), watched.freed.get(timeout=WAIT)) == (
        writer,
        writer,
    )


class TestABuggyMember:
    """A buggy member of a Zenoh system: what it sends costs bounded threads and log lines,
    and nothing it sends runs on Zenoh's threads or breaks `serve` (issue 29, items 5-7).

    Members are trusted with code (they unpickle each other's messages); these are mistakes,
    not attacks. The buggy member is a raw Zenoh session that attaches through the test
    process's router (its Unix socket) and puts what it likes on `rr/<system>/...` keys.
    """

    @pytest.fixture
    def net(self) -> Iterator[ZenohNetwork]:
        """A fresh system whose router is the test process."""
        network = rr.ZenohNetwork(system=f"test-{uuid.uuid4().hex[:8]}", tls=None)
        yield network
        network.close()

    # -- item 5: a thread per claimed sender id ------------------------------------------------

    def test_a_thousand_claimed_sender_ids_start_no_thread_each_and_one_warning(
        self, net: ZenohNetwork, caplog: pytest.LogCaptureFixture, eventually: Callable[..., bool]
    ) -> None:
        target = _registrar(net)
        answered = threading.Event()
        try:
            with buggy_member(net) as raw, caplog.at_level(logging.WARNING, logger="rr_actors"):
                sender = str(raw.zid())
                raw.declare_subscriber(f"rr/{net.system}/ans/{sender}", lambda _s: answered.set())
                key = f"rr/{net.system}/reg/{target.name}"
                before = threading.active_count()
                for i in range(1000):  # (another version: answered unread, from its own id)
                    _put(raw, key, _header(MESSAGE, f"{i:032x}", WIRE_VERSION + 98) + frame(7, i))
                _put(raw, key, _header(MESSAGE, sender, WIRE_VERSION + 98) + frame(8, None))
                assert answered.wait(WAIT)  # every put before it went through Zenoh's callback
                grown = threading.active_count() - before
                assert grown < 20
                assert eventually(lambda: _warnings(caplog, "dropped a message"), timeout=WAIT)
        finally:
            target.stop()

        assert len(caplog.records) <= 2  # the first drop; the one refusal of the real sender
        assert all(len(r.getMessage()) < 500 for r in caplog.records)

    @pytest.fixture
    def manager(
        self, net: ZenohNetwork, context: multiprocessing.context.ForkServerContext
    ) -> Iterator[str]:
        """The name of a registrar served by a manager process attached through `net`."""
        name = f"m-{uuid.uuid4().hex[:6]}"
        parent_end, child_end = context.Pipe()
        process = context.Process(target=_manager, args=(net.address, name, child_end), daemon=True)
        process.start()
        child_end.close()
        try:
            assert parent_end.poll(30), "the manager did not get ready"
            assert "ready" == parent_end.recv()
            yield name
        finally:
            with contextlib.suppress(OSError):
                parent_end.send("stop")
            process.join(10)
            if process.is_alive():
                process.kill()
                process.join(5)
            parent_end.close()

    def test_a_frame_flagged_plain_whose_unpickling_blocks_does_not_stall_other_calls(
        self, net: ZenohNetwork, manager: str
    ) -> None:
        consumer = _registrar(net)
        try:
            with buggy_member(net) as raw:
                _put(
                    raw,
                    f"rr/{net.system}/reg/{manager}",
                    _header(MESSAGE | PLAIN, str(raw.zid())) + frame(NO_REPLY, _Held("bad")),
                )
                assert net.run(manager, _gate_entered, timeout=WAIT)  # its unpickling is held

                query = consumer.call(manager, "echo", "meanwhile", timeout=WAIT)
                still_held = net.run(manager, _gate_closed, timeout=WAIT)
                net.run(manager, _open_gate, timeout=WAIT)
        finally:
            consumer.stop()

        assert ({"resource": "meanwhile"}, True) == (query.response, still_held)

    def test_a_claim_whose_zenoh_id_is_not_hex_is_one_warning_and_serve_works(
        self, net: ZenohNetwork, caplog: pytest.LogCaptureFixture, eventually: Callable[..., bool]
    ) -> None:
        name = f"n-{uuid.uuid4().hex[:6]}"
        with (
            rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name)) as registrar,
            buggy_member(net) as raw,
            caplog.at_level(logging.WARNING, logger="rr_actors"),
        ):
            bad = f"rr/{net.system}/live/claim/{name}/not-hex"
            claim = raw.liveliness().declare_token(bad)
            net.serve(Served(registrar))  # asks for the claims of `name`: sees it
            claim.undeclare()

        # (the presence thread logs it as the token's event comes: perhaps after `serve`)
        assert eventually(lambda: _warnings(caplog, "malformed liveliness token"), timeout=WAIT)
        warned = _warnings(caplog, "malformed liveliness token")
        assert 1 == len(warned)
        assert bad in warned[0]

    def test_a_registrar_token_with_a_limit_that_is_not_an_integer_is_one_warning(
        self, net: ZenohNetwork, caplog: pytest.LogCaptureFixture, eventually: Callable[..., bool]
    ) -> None:
        with buggy_member(net) as raw, caplog.at_level(logging.WARNING, logger="rr_actors"):
            zid = str(raw.zid())
            bad = f"rr/{net.system}/live/reg/bad-{uuid.uuid4().hex[:6]}/{zid}/none/lots/1"
            for _ in range(3):  # an event each: declared, then undeclared
                raw.liveliness().declare_token(bad).undeclare()
            sentinel = f"s-{uuid.uuid4().hex[:6]}"  # heard after them (one link, in order)
            token = raw.liveliness().declare_token(
                f"rr/{net.system}/live/reg/{sentinel}/{zid}/none/1000000/1"
            )
            assert eventually(lambda: sentinel in net.names(), timeout=WAIT)
            token.undeclare()

        assert [] == [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        warned = _warnings(caplog, "malformed liveliness token")
        assert 1 == len(warned)
        assert bad in warned[0]

    def test_a_flood_of_non_messages_is_a_few_bounded_warning_lines(
        self, net: ZenohNetwork, caplog: pytest.LogCaptureFixture
    ) -> None:
        count = 10_000
        COUNTER.target = count + 1  # (the last is told after all the others)
        target = _registrar(net)
        target.register_server("s", load=lambda request: request, unload=lambda *_: None)
        try:
            with buggy_member(net) as raw, caplog.at_level(logging.WARNING, logger="rr_actors"):
                head = _header(MESSAGE, str(raw.zid()))
                key = f"rr/{net.system}/reg/{target.name}"
                for n in range(count + 1):
                    _put(raw, key, head + frame(NO_REPLY, (_Counted(n), "x" * 1000)))
                assert COUNTER.reached.wait(30)
                assert [] == target.server_queries("s", timeout=30)  # after the others, in order
        finally:
            target.stop()

        warned = _warnings(caplog, "unknown message")
        assert 1 <= len(warned) <= 3
        assert all(len(line) < 500 for line in warned)

    @pytest.mark.parametrize(
        "stamp",
        [
            pytest.param(2**64 - 1, id="the-last-stamp"),
            pytest.param(hlc.from_seconds(YEAR_2100), id="2100"),
        ],
    )
    def test_a_stamp_far_ahead_is_not_taken_in_and_the_receiver_goes_on_answering(
        self, net: ZenohNetwork, manager: str, eventually: Callable[..., bool], stamp: int
    ) -> None:
        consumer = _registrar(net)
        try:
            net.run(manager, record_warnings, timeout=WAIT)
            with buggy_member(net) as raw:
                sender = str(raw.zid())
                poisoned = envelope(MESSAGE, sender, frame(NO_REPLY, None), stamp)
                _put(raw, f"rr/{net.system}/reg/{manager}", poisoned)

                def refused() -> bool:
                    logged = net.run(manager, warnings_logged, timeout=WAIT)
                    return any(sender in line and "max_offset" in line for line in logged)

                assert eventually(refused, timeout=WAIT)
            query = consumer.call(manager, "echo", "after", timeout=WAIT)
            stamped, wall = net.run(manager, _clock_now, timeout=WAIT)
            warned = [
                line for line in net.run(manager, warnings_logged, timeout=WAIT) if sender in line
            ]
        finally:
            consumer.stop()

        assert {"resource": "after"} == query.response
        assert stamped - wall < 1.0  # not taken in: the clock is this host's
        assert 1 == len(warned)
        assert "ahead of this host's clock" in warned[0]
