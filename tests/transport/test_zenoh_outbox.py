"""A process that leaves a Zenoh system first puts what it was given to send.

The last messages of a registrar that stops (the `Abandon` of a call it withdraws) are
handed to an outbox's writer thread just before its process closes the session. A close
that dropped them left the provider holding a consumer id nobody would release (CI, one
run in twenty of `test_consumer_records_are_cleared_when_a_consumer_stops_while_a_load_runs`
in the zenoh placement).
"""

from __future__ import annotations

import queue
import uuid
from collections.abc import Iterator

import pytest
import zenoh

from rr_actors._transport.zenoh.link import Outboxes
from rr_actors._transport.zenoh.wire import Keys

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
