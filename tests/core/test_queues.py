"""Bounded queues between a publisher and a subscriber (`rr_actors._core.queues`): a
subscriber in trouble costs a few log lines, not one per event (issue 21).

- A callback that raises on every event logs its first exception with its traceback,
  then a count (at most every `LOG_EVERY` seconds, and when it closes).
- A subscriber that falls behind again and again is warned about once per interval.
- Events that a `close()` which ran out of time left unhandled count as `dropped`.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.bus import Publisher

WAIT = 10.0


def test_a_callback_raising_on_every_event_logs_one_traceback_then_a_count(
    started: list[rr.ResourceRegistrar], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, logger="rr_actors")
    registrar = rr.ResourceRegistrar.start(f"floods-{uuid.uuid4().hex[:8]}")
    started.append(registrar)
    registrar.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
    seen: list[Any] = []

    def callback(event: Any) -> None:
        seen.append(event)
        raise ValueError("this subscriber is broken")

    with registrar.subscribe(callback) as subscription:
        for n in range(200):
            registrar.unload(registrar.call(registrar.name, "leaf", n, timeout=10).id)
        assert subscription.wait_delivered(timeout=WAIT)

    errors = [r for r in caplog.records if "event subscriber" in r.getMessage()]
    assert len(seen) >= 800  # (each call and unload publishes several events)
    assert [True, False] == [r.exc_info is not None for r in errors]
    assert f"raised {len(seen) - 1} more times" in errors[1].getMessage()


def test_a_subscriber_falling_behind_again_and_again_is_warned_about_once(
    gates: Callable[[], threading.Event], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    publisher: Publisher[Any] = Publisher(notice=lambda count: ("dropped", count))
    rounds = [(gates(), threading.Event()) for _ in range(20)]

    def callback(item: Any) -> None:
        if isinstance(item, int) and item % 10 == 0:  # the first event of a round blocks
            gate, entered = rounds[item // 10]
            entered.set()
            assert gate.wait(WAIT)

    with publisher.subscribe(callback, maxsize=1, name="slow") as subscription:
        for n, (gate, entered) in enumerate(rounds):
            publisher.publish(n * 10)
            assert entered.wait(WAIT)
            for i in range(n * 10 + 1, n * 10 + 6):  # one queued, four dropped
                publisher.publish(i)
            gate.set()
            assert subscription.wait_delivered(timeout=WAIT)

    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert (80, 1) == (subscription.dropped, len(warnings))
    assert "'slow' falls behind" in warnings[0]


def test_events_a_close_that_ran_out_of_time_left_unhandled_count_as_dropped(
    gates: Callable[[], threading.Event], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    publisher: Publisher[Any] = Publisher()
    gate, entered = gates(), threading.Event()

    def callback(_item: Any) -> None:
        entered.set()
        assert gate.wait(WAIT)

    subscription = publisher.subscribe(callback, name="stuck")
    for n in range(10):
        publisher.publish(n)
    assert entered.wait(WAIT)
    subscription.close(timeout=0.2)  # the first event is in the callback, 9 wait
    gate.set()

    assert 9 == subscription.dropped
    assert any("the 9 events it had not handled" in r.getMessage() for r in caplog.records)
