"""A plain call's answer is recorded before its registrar's next message, without a wake of its own.

The caller hands the answer over (`DueAnswers.outcomes`, see `_registrar/calls.py`); the
registrar actor takes the outcomes waiting before every message it handles, and is woken
for them only when something waits: a failure, a notice held back for that answer, a
dependency's answer, or a full backlog.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors._registrar.calls import BACKLOG, CallAttempt
from rr_actors.testing import call_futures, catalog_snapshot, intercept


class Pair:
    def __init__(self) -> None:
        uid = uuid.uuid4().hex[:8]
        self.provider = rr.ResourceRegistrar.start(f"prov-{uid}")
        self.consumer = rr.ResourceRegistrar.start(f"cons-{uid}")
        self.provider.register_server("leaf", load=lambda r: f"got {r}", unload=_no_unload)

    def call(self, request: object, **kwargs: object) -> rr.Query:
        return self.consumer.call(self.provider.name, "leaf", request, **kwargs)  # type: ignore[arg-type]


def _no_unload(_request: object, _response: object) -> None:
    return None


@pytest.fixture
def pair() -> Iterator[Pair]:
    made = Pair()
    yield made
    made.consumer.stop()
    made.provider.stop()


def test_answers_are_recorded_before_the_next_message_and_wake_nobody_on_their_own(
    pair: Pair,
) -> None:
    pair.call("first")  # (its client is started: the calls below ask the actor nothing)
    steps: list[str] = []
    intercept(pair.consumer, "client_loaded", before=lambda _m: steps.append("client_loaded"))
    intercept(pair.consumer, "take_outcomes", before=lambda _m: steps.append("take_outcomes"))
    intercept(pair.consumer, "client_queries", before=lambda _m: steps.append("client_queries"))

    queries = [pair.call("shared") for _ in range(3)]
    assert [] == steps  # nothing woke the consumer's actor

    held = pair.consumer.client_queries()

    assert ["client_loaded"] * 3 + ["client_queries"] == steps
    assert {q.id for q in queries} <= {q.id for q in held}


def test_an_unload_right_after_a_call_finds_its_record(pair: Pair) -> None:
    for _ in range(20):
        query = pair.call("shared")
        pair.consumer.unload(query.id)

    assert [] == pair.provider.server_queries("leaf")
    assert () == catalog_snapshot(pair.consumer).clients


def test_a_full_backlog_of_answers_wakes_the_registrar(pair: Pair) -> None:
    pair.call("first")
    woken = threading.Event()
    intercept(pair.consumer, "take_outcomes", before=lambda _m: woken.set())

    for _ in range(BACKLOG - 1):
        pair.call("shared")
    assert not woken.is_set()
    pair.call("shared")

    assert woken.wait(5)


def test_a_status_notice_that_overtakes_the_answer_is_delivered_once_the_caller_has_it(
    pair: Pair,
) -> None:
    # The caller is held between its answer and handing it over; meanwhile the provider
    # sends a status about that query, which the consumer holds back (its answer is
    # due). Handing the answer over must wake the consumer: `send_status` waits for the
    # delivery, and nothing else would come.
    answered, release, notice_held = threading.Event(), threading.Event(), threading.Event()

    class HeldAfterItsAnswer(CallAttempt):
        def wait(self, timeout: float | None = None) -> bool:
            done = super().wait(timeout)
            answered.set()
            assert release.wait(5)
            return done

    updates: list[rr.StatusUpdate] = []
    pair.call("first")  # (its client is started)
    intercept(pair.consumer, "status_notice", after=lambda _m: notice_held.set())
    with ThreadPoolExecutor(2) as pool, call_futures(pair.consumer, HeldAfterItsAnswer):
        query_id = str(uuid.uuid4())
        call = pool.submit(
            pair.call, "watched", query_id=query_id, on_status=lambda _q, u: updates.append(u)
        )
        assert answered.wait(5)
        sent = pool.submit(pair.provider.send_status, query_id, rr.Status.UPDATE, "hi", timeout=5)
        assert notice_held.wait(5)
        release.set()

        assert query_id == call.result(5).id
        sent.result(5)  # delivered (it raises CallTimeoutError otherwise)
    assert ["hi"] == [u.message for u in updates]
