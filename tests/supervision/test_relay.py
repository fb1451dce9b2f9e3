"""A tree's event relay: a new listener hears what happens from the moment it subscribed.

The "off" switch reaches a manager process asynchronously: what the process made before
it heard it may arrive after the next listener subscribed (seen once in a full run beside
two CPU-bound processes: a load made while nobody listened reached the next subscriber).
"""

from __future__ import annotations

import threading
import time

from rr_actors import events
from rr_actors._supervision.relay import EventRelay


def _loaded(at: float) -> events.ChildStarted:
    return events.ChildStarted("root", "erm", 1, at=at)


def test_an_event_made_before_the_listener_subscribed_is_not_delivered_to_it() -> None:
    relay = EventRelay()
    first = relay.publisher.subscribe(lambda _e: None)
    first.close()  # nobody listens: the processes are told "off" (they may not hear it yet)
    made_while_nobody_listened = _loaded(time.time() - 0.001)  # (before the next subscribe)
    heard: list[events.Event] = []
    got = threading.Event()

    def listener(event: events.Event) -> None:
        heard.append(event)
        got.set()

    with relay.publisher.subscribe(listener):
        relay.deliver([made_while_nobody_listened])  # forwarded before "off" arrived
        made_after = _loaded(time.time())
        relay.deliver([made_after])
        assert got.wait(5)

    assert [made_after] == heard
