"""The event bus: publishers, subscriptions with bounded queues, forwarders.

The bus is generic, so most tests publish plain values (ints, tuples); the notice of a gap
comes from a factory (`("dropped", count)` here; `EventsDropped` for rr_actors' events).
Every wait is bounded; a blocked callback waits on an event the `gates` fixture opens at
teardown, and `no_bus_threads` fails a test that leaves a subscriber or forwarder thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core import queues
from rr_actors._core.bus import Forwarder, Publisher, Subscription

WAIT = 5.0
"""Seconds any bounded wait in these tests gets (they normally take microseconds)."""

LOGGER = "rr_actors.test_bus"


def notice(count: int) -> tuple[str, int]:
    return ("dropped", count)


@pytest.fixture(autouse=True)
def no_bus_threads() -> Iterator[None]:
    """Fail the test if a subscriber or forwarder thread outlives it."""
    before = set(threading.enumerate())
    yield
    left = [
        t
        for t in threading.enumerate()
        if t not in before and t.name.startswith(("rr-events-", "rr-forward-"))
    ]
    for thread in left:
        thread.join(WAIT)
    alive = [t.name for t in left if t.is_alive()]
    assert [] == alive


@pytest.fixture
def publisher() -> Publisher[Any]:
    return Publisher(logger=logging.getLogger(LOGGER), notice=notice)


class Blocking:
    """A callback (or `send`) that records what it gets and blocks on its first call."""

    def __init__(self, gate: threading.Event) -> None:
        self.gate = gate
        self.entered = threading.Event()
        self.got: list[Any] = []

    def __call__(self, item: Any) -> None:
        self.got.append(item)
        if not self.entered.is_set():
            self.entered.set()
            assert self.gate.wait(WAIT)


# -- subscriptions --------------------------------------------------------------------------


def test_a_subscriber_gets_every_event_in_publish_order(publisher: Publisher[Any]) -> None:
    got: list[int] = []
    with publisher.subscribe(got.append) as subscription:
        for i in range(1000):
            publisher.publish(i)
        assert subscription.wait_delivered(timeout=WAIT)
    assert list(range(1000)) == got


def test_each_subscription_gets_its_own_copy_of_the_stream(publisher: Publisher[Any]) -> None:
    first: list[int] = []
    second: list[int] = []
    with publisher.subscribe(first.append) as a, publisher.subscribe(second.append) as b:
        for i in range(100):
            publisher.publish(i)
        assert a.wait_delivered(timeout=WAIT)
        assert b.wait_delivered(timeout=WAIT)
    assert list(range(100)) == first
    assert list(range(100)) == second


def test_the_callback_runs_on_a_thread_of_the_subscription(publisher: Publisher[Any]) -> None:
    threads: list[threading.Thread] = []
    with publisher.subscribe(
        lambda _: threads.append(threading.current_thread()), name="watcher"
    ) as subscription:
        publisher.publish(1)
        assert subscription.wait_delivered(timeout=WAIT)
    assert ["rr-events-watcher"] == [t.name for t in threads]
    assert threads[0] is not threading.current_thread()
    assert threads[0].daemon


def test_a_blocked_subscriber_does_not_block_publish(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    published = threading.Event()

    def publish_many() -> None:
        for i in range(1, 10_001):
            publisher.publish(i)
        published.set()

    with publisher.subscribe(callback, maxsize=100):
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        threading.Thread(target=publish_many, daemon=True).start()
        assert published.wait(WAIT)  # the subscriber is still blocked
        assert not gate.is_set()
        gate.set()


def test_a_full_queue_drops_new_events_and_counts_them_exactly(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback, maxsize=100) as subscription:
        publisher.publish(0)
        assert callback.entered.wait(WAIT)  # 0 is out of the queue, in the callback
        for i in range(1, 10_001):
            publisher.publish(i)
        assert 10_000 - 100 == subscription.dropped
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)
    assert [0, *range(1, 101), ("dropped", 9_900)] == callback.got


def test_the_notice_of_a_gap_comes_where_the_gap_is(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback, maxsize=2) as subscription:
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        for i in range(1, 6):
            publisher.publish(i)  # 1, 2 queued; 3, 4, 5 dropped
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)
        publisher.publish(6)
        assert subscription.wait_delivered(timeout=WAIT)
    assert [0, 1, 2, ("dropped", 3), 6] == callback.got


def test_the_notice_arrives_once_the_queue_ran_empty_without_further_publishing(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    noticed = threading.Event()
    callback = Blocking(gate)

    def watch(item: Any) -> None:
        callback(item)
        if isinstance(item, tuple):
            noticed.set()

    with publisher.subscribe(watch, maxsize=1):
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        publisher.publish(1)  # queued
        publisher.publish(2)  # dropped
        gate.set()  # nothing is published (or waited for) after this
        assert noticed.wait(WAIT)
    assert [0, 1, ("dropped", 1)] == callback.got


def test_a_gap_closed_by_the_next_publish_puts_its_notice_before_that_event(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback, maxsize=1) as subscription:
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        publisher.publish(1)  # queued
        publisher.publish(2)  # dropped
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)
    assert [0, 1, ("dropped", 1)] == callback.got


def test_each_gap_is_warned_about_once(
    publisher: Publisher[Any],
    gates: Callable[[], threading.Event],
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(queues, "LOG_EVERY", 0.0)  # (gaps further apart than the rate limit)
    caplog.set_level(logging.WARNING, logger="rr_actors")
    first, second = gates(), gates()
    entered = [threading.Event(), threading.Event()]

    def callback(item: Any) -> None:
        if item in (0, 10):
            entered[item // 10].set()
            assert (first if item == 0 else second).wait(WAIT)

    with publisher.subscribe(callback, maxsize=1, name="slow") as subscription:
        for gate, start, event in ((first, 0, entered[0]), (second, 10, entered[1])):
            publisher.publish(start)
            assert event.wait(WAIT)
            for i in range(start + 1, start + 6):
                publisher.publish(i)
            gate.set()
            assert subscription.wait_delivered(timeout=WAIT)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert 2 == len(warnings)
    assert "'slow'" in warnings[0].getMessage()


def test_without_a_notice_factory_drops_are_only_counted(
    gates: Callable[[], threading.Event],
) -> None:
    publisher: Publisher[int] = Publisher()
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback, maxsize=1) as subscription:
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        for i in range(1, 4):
            publisher.publish(i)
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)
        publisher.publish(4)
        assert subscription.wait_delivered(timeout=WAIT)
    assert 2 == subscription.dropped
    assert [0, 1, 4] == callback.got


def test_a_raising_callback_is_logged_and_delivery_goes_on(
    publisher: Publisher[Any], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, logger="rr_actors")
    got: list[int] = []

    def callback(item: int) -> None:
        if item == 1:
            raise ValueError("bad subscriber")
        got.append(item)

    with publisher.subscribe(callback, name="faulty") as subscription:
        for i in range(3):
            publisher.publish(i)
        assert subscription.wait_delivered(timeout=WAIT)
    assert [0, 2] == got
    [record] = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert "'faulty'" in record.getMessage()
    assert record.exc_info is not None
    assert "bad subscriber" == str(record.exc_info[1])


def test_close_ends_the_thread_and_is_idempotent(publisher: Publisher[Any]) -> None:
    subscription = publisher.subscribe(lambda _: None, name="closing")
    [thread] = [t for t in threading.enumerate() if t.name == "rr-events-closing"]
    subscription.close()
    assert not thread.is_alive()
    assert subscription.closed
    subscription.close()
    assert not thread.is_alive()


def test_close_unsubscribes(publisher: Publisher[Any]) -> None:
    got: list[int] = []
    subscription = publisher.subscribe(got.append)
    publisher.publish(1)
    subscription.close()
    publisher.publish(2)
    assert [1] == got
    assert not publisher.active


def test_close_delivers_what_was_already_queued(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    subscription = publisher.subscribe(callback)
    publisher.publish(0)
    assert callback.entered.wait(WAIT)
    for i in range(1, 6):
        publisher.publish(i)
    closer = threading.Thread(target=subscription.close, kwargs={"timeout": WAIT})
    closer.start()
    gate.set()
    closer.join(WAIT)
    assert not closer.is_alive()
    assert list(range(6)) == callback.got


def test_close_drops_the_rest_when_its_timeout_passes(
    publisher: Publisher[Any],
    gates: Callable[[], threading.Event],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="rr_actors")
    gate = gates()
    callback = Blocking(gate)
    subscription = publisher.subscribe(callback, name="stuck")
    publisher.publish(0)
    assert callback.entered.wait(WAIT)
    for i in range(1, 6):
        publisher.publish(i)
    subscription.close(timeout=0.01)  # the callback is blocked: this timeout passes
    [thread] = [t for t in threading.enumerate() if t.name == "rr-events-stuck"]
    gate.set()
    thread.join(WAIT)
    assert not thread.is_alive()
    assert [0] == callback.got
    assert not subscription.wait_delivered(timeout=WAIT)
    assert any("'stuck'" in r.getMessage() for r in caplog.records)


def test_a_callback_may_close_its_own_subscription(publisher: Publisher[Any]) -> None:
    got: list[int] = []
    holder: list[Subscription[Any]] = []
    closed = threading.Event()

    def callback(item: int) -> None:
        got.append(item)
        holder[0].close()
        closed.set()

    holder.append(publisher.subscribe(callback, name="self-closing"))
    [thread] = [t for t in threading.enumerate() if t.name == "rr-events-self-closing"]
    publisher.publish(1)
    assert closed.wait(WAIT)
    thread.join(WAIT)
    assert not thread.is_alive()
    assert [1] == got


def test_wait_delivered_from_the_callback_raises(publisher: Publisher[Any]) -> None:
    errors: list[BaseException] = []
    holder: list[Subscription[Any]] = []

    def callback(_: object) -> None:
        try:
            holder[0].wait_delivered(timeout=WAIT)
        except RuntimeError as exc:
            errors.append(exc)

    with publisher.subscribe(callback) as subscription:
        holder.append(subscription)
        publisher.publish(1)
        assert subscription.wait_delivered(timeout=WAIT)
    assert 1 == len(errors)


def test_wait_delivered_is_false_while_the_callback_is_blocked(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback) as subscription:
        publisher.publish(0)
        assert callback.entered.wait(WAIT)
        assert not subscription.wait_delivered(timeout=0.01)
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)


def test_with_maxbytes_a_queue_heavier_than_it_drops_new_events_and_marks_the_gap(
    publisher: Publisher[Any], gates: Callable[[], threading.Event]
) -> None:
    """Events from other processes are bounded by weight too (issue 40): a few big ones
    must not hold what `maxsize` small ones would."""
    gate = gates()
    callback = Blocking(gate)
    with publisher.subscribe(callback, maxsize=100, maxbytes=10, weigh=len) as subscription:
        publisher.publish("0")
        assert callback.entered.wait(WAIT)  # it weighs until the callback returns
        for item in ("aaa", "bbb", "cc", "dd", "e" * 11, "f"):
            publisher.publish(item)  # 1 + 3 + 3 + 2 = 9; dd and the 11 dropped; f fits
        assert 2 == subscription.dropped
        gate.set()
        assert subscription.wait_delivered(timeout=WAIT)
        publisher.publish("g" * 10)  # all handled: room for a whole 10 again
        assert subscription.wait_delivered(timeout=WAIT)
    assert ["0", "aaa", "bbb", "cc", ("dropped", 2), "f", "g" * 10] == callback.got


def test_maxbytes_must_be_a_positive_int_given_with_weigh(publisher: Publisher[Any]) -> None:
    for bad in (0, -1, 1.5, True):
        with pytest.raises(rr.ConfigError, match="maxbytes"):
            publisher.subscribe(lambda _: None, maxbytes=bad, weigh=len)  # type: ignore[arg-type]
    with pytest.raises(rr.ConfigError, match="maxbytes"):
        publisher.subscribe(lambda _: None, maxbytes=10)


def test_maxsize_must_be_a_positive_int(publisher: Publisher[Any]) -> None:
    for bad in (0, -1, 1.5, True):
        with pytest.raises(rr.ConfigError, match="maxsize"):
            publisher.subscribe(lambda _: None, maxsize=bad)  # type: ignore[arg-type]


def test_subscribing_and_closing_from_many_threads_while_publishing_loses_nothing(
    publisher: Publisher[Any],
) -> None:
    publishers, churners, rounds = 3, 4, 10
    stop = threading.Event()
    counts = [0] * publishers
    got: list[tuple[int, int]] = []
    failures: list[BaseException] = []

    def publish(which: int) -> None:
        while not stop.is_set():
            publisher.publish((which, counts[which]))
            counts[which] += 1

    def churn() -> None:
        try:
            for _ in range(rounds):
                subscription = publisher.subscribe(lambda _: None)
                publisher.publish(("churn", 0))
                subscription.close(timeout=WAIT)
        except BaseException as exc:
            failures.append(exc)

    with publisher.subscribe(
        lambda item: got.append(item) if item[0] != "churn" else None, maxsize=10_000_000
    ) as steady:
        threads = [threading.Thread(target=publish, args=(i,)) for i in range(publishers)]
        churning = [threading.Thread(target=churn) for _ in range(churners)]
        for thread in threads + churning:
            thread.start()
        for thread in churning:
            thread.join(60)
        stop.set()
        for thread in threads:
            thread.join(WAIT)
        assert steady.wait_delivered(timeout=60)
        assert 0 == steady.dropped
    assert [] == failures
    for which in range(publishers):
        assert list(range(counts[which])) == [i for w, i in got if w == which]
    assert not publisher.active


# -- the publisher ---------------------------------------------------------------------------


def test_a_publisher_is_inactive_with_no_subscriber_and_info_disabled(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    assert not Publisher(logger=logging.getLogger(LOGGER)).active
    assert not Publisher().active


def test_a_subscriber_makes_the_publisher_active(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    publisher: Publisher[int] = Publisher(logger=logging.getLogger(LOGGER))
    with publisher.subscribe(lambda _: None):
        assert publisher.active
    assert not publisher.active


def test_a_sink_makes_the_publisher_active() -> None:
    publisher: Publisher[int] = Publisher()
    sink: list[int] = []
    publisher.add_sink(sink.append)
    assert publisher.active
    publisher.remove_sink(sink.append)
    assert not publisher.active


def test_info_on_the_logger_makes_the_publisher_active(caplog: pytest.LogCaptureFixture) -> None:
    publisher: Publisher[int] = Publisher(logger=logging.getLogger(LOGGER))
    caplog.set_level(logging.INFO, logger=LOGGER)
    assert publisher.active
    caplog.set_level(logging.WARNING, logger=LOGGER)
    assert not publisher.active


def test_publish_logs_the_described_event_at_info(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    publisher: Publisher[int] = Publisher(
        logger=logging.getLogger(LOGGER), describe=lambda n: f"event number {n}"
    )
    publisher.publish(7)
    [record] = caplog.records
    assert (LOGGER, logging.INFO, "event number 7") == (
        record.name,
        record.levelno,
        record.getMessage(),
    )
    assert 7 == record.event  # type: ignore[attr-defined]
    assert "test_publish_logs_the_described_event_at_info" == record.funcName


def test_publish_logs_nothing_when_info_is_disabled(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    publisher: Publisher[int] = Publisher(logger=logging.getLogger(LOGGER), describe=str)
    sink: list[int] = []
    publisher.add_sink(sink.append)
    publisher.publish(7)
    assert [] == caplog.records
    assert [7] == sink


def test_sinks_run_on_the_publishing_thread_in_the_order_added() -> None:
    publisher: Publisher[int] = Publisher()
    calls: list[tuple[str, int, threading.Thread]] = []
    publisher.add_sink(lambda n: calls.append(("a", n, threading.current_thread())))
    publisher.add_sink(lambda n: calls.append(("b", n, threading.current_thread())))
    publisher.publish(1)
    me = threading.current_thread()
    assert [("a", 1, me), ("b", 1, me)] == calls


def test_a_raising_sink_is_logged_and_the_other_sinks_still_get_the_event(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR, logger="rr_actors")
    publisher: Publisher[int] = Publisher()

    def broken(_: int) -> None:
        raise RuntimeError("broken sink")

    sink: list[int] = []
    publisher.add_sink(broken)
    publisher.add_sink(sink.append)
    publisher.publish(1)
    assert [1] == sink
    [record] = caplog.records
    assert record.exc_info is not None
    assert "broken sink" == str(record.exc_info[1])


def test_remove_sink_of_a_sink_never_added_changes_nothing() -> None:
    publisher: Publisher[int] = Publisher()
    sink: list[int] = []
    publisher.add_sink(sink.append)
    publisher.remove_sink(print)
    publisher.publish(1)
    assert [1] == sink


# -- forwarders -----------------------------------------------------------------------------


def test_a_forwarder_sends_every_event_in_order() -> None:
    batches: list[list[int]] = []
    forwarder: Forwarder[int] = Forwarder(batches.append)
    publisher: Publisher[int] = Publisher()
    publisher.add_sink(forwarder)
    for i in range(1000):
        publisher.publish(i)
    assert forwarder.wait_sent(timeout=WAIT)
    forwarder.close()
    assert list(range(1000)) == [i for batch in batches for i in batch]


def test_a_forwarder_batches_what_piled_up_while_send_ran(
    gates: Callable[[], threading.Event],
) -> None:
    send = Blocking(gates())
    forwarder: Forwarder[int] = Forwarder(send)
    forwarder(0)
    assert send.entered.wait(WAIT)
    for i in range(1, 51):
        forwarder(i)
    send.gate.set()
    assert forwarder.wait_sent(timeout=WAIT)
    forwarder.close()
    assert [[0], list(range(1, 51))] == send.got


def test_a_forwarder_sends_at_most_max_batch_events_at_once(
    gates: Callable[[], threading.Event],
) -> None:
    send = Blocking(gates())
    forwarder: Forwarder[int] = Forwarder(send, max_batch=20)
    forwarder(0)
    assert send.entered.wait(WAIT)
    for i in range(1, 51):
        forwarder(i)
    send.gate.set()
    assert forwarder.wait_sent(timeout=WAIT)
    forwarder.close()
    expected = [[0], list(range(1, 21)), list(range(21, 41)), list(range(41, 51))]
    assert expected == send.got


def test_a_full_forwarder_counts_drops_and_marks_the_gap(
    gates: Callable[[], threading.Event],
) -> None:
    send = Blocking(gates())
    forwarder: Forwarder[Any] = Forwarder(send, maxsize=10, notice=notice)
    forwarder(0)
    assert send.entered.wait(WAIT)
    for i in range(1, 101):
        forwarder(i)
    assert 90 == forwarder.dropped
    send.gate.set()
    assert forwarder.wait_sent(timeout=WAIT)
    forwarder.close()
    assert [0, *range(1, 11), ("dropped", 90)] == [i for batch in send.got for i in batch]


def test_a_failing_send_is_logged_once_and_its_events_count_as_dropped(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.ERROR, logger="rr_actors")

    def send(batch: list[int]) -> None:
        raise BrokenPipeError("the supervisor is gone")

    forwarder: Forwarder[int] = Forwarder(send, name="broken")
    for i in range(3):
        forwarder(i)
        assert forwarder.wait_sent(timeout=WAIT)
    forwarder.close()
    assert 3 == forwarder.dropped
    [record] = caplog.records
    assert "'broken'" in record.getMessage()


def test_forwarder_close_sends_what_is_buffered_and_is_idempotent(
    gates: Callable[[], threading.Event],
) -> None:
    send = Blocking(gates())
    forwarder: Forwarder[int] = Forwarder(send, name="flushing")
    [thread] = [t for t in threading.enumerate() if t.name == "rr-forward-flushing"]
    forwarder(0)
    assert send.entered.wait(WAIT)
    for i in range(1, 4):
        forwarder(i)
    closer = threading.Thread(target=forwarder.close, kwargs={"timeout": WAIT})
    closer.start()
    send.gate.set()
    closer.join(WAIT)
    assert not closer.is_alive()
    assert not thread.is_alive()
    forwarder.close()
    assert [[0], [1, 2, 3]] == send.got


def test_a_forwarder_ships_a_lone_event_at_once_and_a_burst_after_lingering(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(queues, "FORWARD_LINGER", 3600.0)  # lingers until a wait hurries it
    batches: list[list[int]] = []
    shipped = threading.Event()

    def send(batch: list[int]) -> None:
        batches.append(batch)
        shipped.set()

    forwarder: Forwarder[int] = Forwarder(send)
    forwarder(0)
    assert shipped.wait(WAIT)  # nothing waited for it: a lone event goes at once
    for i in range(1, 101):
        forwarder(i)  # while it lingers: no wake-up per event, one batch later
    assert forwarder.wait_sent(timeout=WAIT)  # a wait cuts the linger short
    forwarder(101)
    forwarder.close(timeout=WAIT)  # so does a close
    assert [[0], list(range(1, 101)), [101]] == batches


def test_max_batch_must_be_a_positive_int() -> None:
    with pytest.raises(rr.ConfigError, match="max_batch"):
        Forwarder(print, max_batch=0)


def test_a_forwarder_closed_at_once_with_nothing_left_warns_of_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # (a Zenoh network closes its events' forwarder so, in every manager process: a
    # warning of "0 events dropped" each time was only noise on the demo's terminal)
    caplog.set_level(logging.WARNING, logger="rr_actors")
    batches: list[list[int]] = []
    forwarder: Forwarder[int] = Forwarder(batches.append, name="idle")
    forwarder(1)
    assert forwarder.wait_sent(timeout=WAIT)  # its thread runs, idle

    forwarder.close(timeout=0)

    assert [[1]] == batches
    assert 0 == forwarder.dropped
    assert [] == [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
