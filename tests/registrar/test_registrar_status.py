"""Status notifications (DESIGN rule 9)."""

from __future__ import annotations

import threading
import uuid
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.workers import Workers
from rr_actors.testing import catalog_snapshot

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def own_ids(inbox):
    """For each update an inbox got: (the query's id, the update's query_id)."""
    return [(query.id, update.query_id) for query, update in inbox.updates]


def test_status_reaches_every_consumer_with_its_own_query_id(make_registrar, serve, inbox):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    serve(provider, "leaf")
    boxes = [inbox() for _ in range(3)]
    queries = [
        one.call(provider.name, "leaf", "cam", on_status=boxes[0]),
        one.call(provider.name, "leaf", "cam", on_status=boxes[1]),
        two.call(provider.name, "leaf", "cam", on_status=boxes[2]),
    ]

    provider.send_status(queries[0].id, rr.Status.WARNING, "hot")

    for box, query in zip(boxes, queries, strict=True):
        assert [(query.id, query.id)] == own_ids(box)
    (_, update) = boxes[2].updates[0]
    assert (rr.Status.WARNING, "hot", f"{provider.name}/leaf") == (
        update.status,
        update.message,
        update.source,
    )


def test_send_status_works_with_any_consumer_id_of_the_resource(make_registrar, serve, inbox):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    first, second = inbox(), inbox()
    consumer.call(provider.name, "leaf", "cam", on_status=first)
    q2 = consumer.call(provider.name, "leaf", "cam", on_status=second)

    provider.send_status(q2.id, rr.Status.OK, "")

    assert (1, 1) == (len(first.updates), len(second.updates))


def test_the_provider_server_s_on_status_runs_once_per_status(make_registrar, serve):
    provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
    leaf = serve(provider, "leaf")
    query = one.call(provider.name, "leaf", "cam")
    one.call(provider.name, "leaf", "cam")
    two.call(provider.name, "leaf", "cam")

    provider.send_status(query.id, rr.Status.ERROR, "broken")

    ((seen_query, update),) = leaf.statuses
    assert (query.id, query.id, rr.Status.ERROR) == (seen_query.id, update.query_id, update.status)


def test_status_climbs_the_dependency_chain_to_the_top_consumer(make_registrar, serve, inbox):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    leaf = serve(producer, "leaf")
    composite = serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response)
    top = inbox()
    query = consumer.call(agent.name, "composite", "x", on_status=top)
    (leaf_query,) = producer.server_queries("leaf")

    producer.send_status(leaf_query.id, rr.Status.FATAL, "unplugged")

    assert 1 == len(leaf.statuses)
    assert 1 == len(composite.statuses)
    assert [(query.id, query.id)] == own_ids(top)
    (_, update) = top.updates[0]
    assert (rr.Status.FATAL, "unplugged", f"{producer.name}/leaf") == (
        update.status,
        update.message,
        update.source,
    )


def test_status_climbs_every_path_and_each_callback_runs_once(make_registrar, serve, inbox):
    """A diamond: top needs left and right, both need the same leaf."""
    consumer, provider, producer = (make_registrar(n) for n in ("consumer", "mid", "producer"))
    leaf = serve(producer, "leaf")
    left = serve(provider, "left", lambda r: provider.call(producer.name, "leaf", "shared").id)
    right = serve(provider, "right", lambda r: provider.call(producer.name, "leaf", "shared").id)

    def both(request):
        provider.call(provider.name, "left", request)
        provider.call(provider.name, "right", request)
        return "top"

    top = serve(provider, "top", both)
    box = inbox()
    query = consumer.call(provider.name, "top", "x", on_status=box)
    some_leaf_id = producer.server_queries("leaf")[0].id

    producer.send_status(some_leaf_id, rr.Status.WARNING, "drifting")

    assert [1, 1, 1, 1] == [len(s.statuses) for s in (leaf, left, right, top)]
    assert [(query.id, query.id)] == own_ids(box)


def test_a_consumer_client_on_an_intermediate_dependency_hears_the_status(
    make_registrar, serve, inbox
):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf")
    middle = inbox()
    serve(
        agent,
        "composite",
        lambda r: agent.call(producer.name, "leaf", r, on_status=middle).response,
    )
    consumer.call(agent.name, "composite", "x")
    (leaf_query,) = producer.server_queries("leaf")

    producer.send_status(leaf_query.id, rr.Status.UPDATE, "new frame rate")

    assert [(leaf_query.id, leaf_query.id)] == own_ids(middle)


def test_send_status_returns_after_every_callback_on_the_path_ran(make_registrar, serve, shared):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf")
    serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response)
    ran = shared.event()

    def slow_callback(query, update):
        threading.Event().wait(0.2)  # work that takes a while
        ran.set()

    consumer.call(agent.name, "composite", "x", on_status=slow_callback)
    (leaf_query,) = producer.server_queries("leaf")

    producer.send_status(leaf_query.id, rr.Status.OK, "")

    assert ran.is_set()


def test_send_status_times_out_when_a_callback_hangs(make_registrar, serve, gates):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    gate = gates()
    query = consumer.call(provider.name, "leaf", "x", on_status=lambda q, u: gate.wait(10))

    with pytest.raises(rr.CallTimeoutError):
        provider.send_status(query.id, rr.Status.OK, "", timeout=0.3)


def test_a_status_callback_that_raises_does_not_stop_delivery(make_registrar, serve, inbox):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    def broken(query, update):
        raise RuntimeError("callback bug")

    box = inbox()
    query = consumer.call(provider.name, "leaf", "x", on_status=broken)
    consumer.call(provider.name, "leaf", "x", on_status=box)

    provider.send_status(query.id, rr.Status.OK, "")

    assert 1 == len(box.updates)


def test_a_released_consumer_no_longer_hears_status(make_registrar, serve, inbox):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    gone, kept = inbox(), inbox()
    released = consumer.call(provider.name, "leaf", "x", on_status=gone)
    still = consumer.call(provider.name, "leaf", "x", on_status=kept)
    consumer.unload(released.id)

    provider.send_status(still.id, rr.Status.OK, "")

    assert ([], 1) == (gone.updates, len(kept.updates))


def test_a_status_callback_may_call_unload_and_send_status_on_the_sender(
    make_registrar, serve, shared
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    serve(provider, "spare")
    done = shared.list()

    def reentrant(query, update):
        if update.status is rr.Status.WARNING:
            spare = consumer.call(provider.name, "spare", "backup", timeout=5)
            provider.send_status(spare.id, rr.Status.OK, "from a callback", timeout=5)
            consumer.unload(spare.id, timeout=5)
            another = provider.call(provider.name, "spare", "own", timeout=5)
            provider.unload(another.id, timeout=5)
            done.append(update.status)

    query = consumer.call(provider.name, "leaf", "x", on_status=reentrant)

    provider.send_status(query.id, rr.Status.WARNING, "", timeout=10)

    assert [rr.Status.WARNING] == done
    assert [] == provider.server_queries("spare")


def test_a_server_on_status_may_call_its_own_registrar(make_registrar, shared):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    provider.register_server("spare", load=lambda r: r, unload=lambda r, s: None)
    done = shared.list()

    def on_status(query, update):
        spare = provider.call(provider.name, "spare", "replacement", timeout=5)
        provider.unload(spare.id, timeout=5)
        done.append(query.id)

    provider.register_server(
        "leaf", load=lambda r: r, unload=lambda r, s: None, on_status=on_status
    )
    query = consumer.call(provider.name, "leaf", "x")

    provider.send_status(query.id, rr.Status.ERROR, "", timeout=10)

    assert [query.id] == done


def test_a_status_callback_may_unload_the_resource_it_hears_about(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    def give_up(query, update):
        consumer.unload(query.id, timeout=5)

    query = consumer.call(provider.name, "leaf", "x", on_status=give_up)

    provider.send_status(query.id, rr.Status.FATAL, "dead", timeout=10)

    assert [("x", {"resource": "x"})] == leaf.unloads
    assert ((), ()) == (catalog_snapshot(provider).resources, catalog_snapshot(consumer).clients)


def test_send_status_for_an_unknown_id_raises(make_registrar, serve):
    provider = make_registrar("provider")
    serve(provider, "leaf")

    with pytest.raises(rr.UnknownQueryError):
        provider.send_status(str(uuid.uuid4()), rr.Status.OK, "")


def test_only_the_provider_can_send_status_about_a_resource(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.UnknownQueryError):
        consumer.send_status(query.id, rr.Status.OK, "")


# -- clauses a mutation audit found unguarded ---------------------------------------


def test_send_status_s_timeout_bounds_the_wait(make_registrar, serve, gates):
    """Rule 9: "`send_status` returns when the notification has been delivered ... (a
    `timeout` bounds it)".

    Mutation caught: `send_status` ignores its `timeout` and waits the registrar's default
    `call_timeout`. The existing timeout test still gets its `CallTimeoutError` (after the
    default 10 s); here the default is long and the error must come within a few seconds.
    """
    provider = make_registrar("provider", call_timeout=30.0)
    consumer = make_registrar("consumer")
    serve(provider, "leaf")
    gate = gates()
    query = consumer.call(provider.name, "leaf", "x", on_status=lambda q, u: gate.wait(30))

    with ThreadPoolExecutor(1) as pool:
        sending = pool.submit(provider.send_status, query.id, rr.Status.OK, "", timeout=0.3)
        try:
            error = sending.exception(timeout=10)
        finally:
            gate.set()  # let the hung callback (and a send_status that ignored its timeout) end

    assert isinstance(error, rr.CallTimeoutError)


def test_a_status_callback_may_send_a_status_that_reaches_its_own_client(
    make_registrar, serve, inbox, shared
):
    """Rule 9: a status callback may call `send_status` on the sender without deadlock.

    Here the nested status is for another resource the same consumer holds at the same
    server. Mutation caught: status callbacks run on the registrar's actor thread, or on
    any one thread per client, instead of on workers: the nested delivery then waits
    behind the running callback (a deadlock, cut by the nested call's timeout).
    """
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    box = inbox()
    outcome = shared.list()
    other = consumer.call(provider.name, "leaf", "b", on_status=box)

    def reentrant(query, update):
        try:
            provider.send_status(other.id, rr.Status.OK, "nested", timeout=5)
        except rr.CallTimeoutError:
            outcome.append("deadlocked")
        else:
            outcome.append("delivered")

    first = consumer.call(provider.name, "leaf", "a", on_status=reentrant)

    provider.send_status(first.id, rr.Status.WARNING, "outer", timeout=15)

    assert ["delivered"] == outcome
    assert [(other.id, "nested")] == [(u.query_id, u.message) for _, u in box.updates]


def test_a_server_on_status_may_call_and_send_status_on_its_own_server(make_registrar, shared):
    """Rule 9: the provider server's `on_status` may `call` its own server and `send_status`
    about another of its resources without deadlock.

    Mutation caught: `on_status` runs on an actor thread (the registrar's or the server's)
    instead of on a worker: the nested load and the nested `on_status` then wait behind
    the running callback.
    """
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    seen, outcome, other_ids = shared.list(), shared.list(), shared.list()

    def on_status(query, update):
        seen.append(query.request)
        if query.request != "a":
            return
        try:
            spare = provider.call(provider.name, "leaf", "spare", timeout=5)
            provider.unload(spare.id, timeout=5)
            provider.send_status(other_ids[0], rr.Status.OK, "nested", timeout=5)
        except rr.CallTimeoutError as exc:
            outcome.append(f"deadlocked: {exc}")
        else:
            outcome.append("done")

    provider.register_server(
        "leaf", load=lambda r: r, unload=lambda r, s: None, on_status=on_status
    )
    other_ids.append(consumer.call(provider.name, "leaf", "b").id)
    query = consumer.call(provider.name, "leaf", "a")

    provider.send_status(query.id, rr.Status.ERROR, "outer", timeout=20)

    assert ["done"] == outcome
    assert ["a", "b"] == seen


def test_a_status_callback_that_gets_no_thread_is_skipped_and_its_registrar_keeps_serving(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    provider = rr.ResourceRegistrar.start(f"P-{uuid.uuid4().hex[:8]}")
    consumer = rr.ResourceRegistrar.start(f"C-{uuid.uuid4().hex[:8]}")
    heard: list[rr.StatusUpdate] = []
    try:
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
        query = consumer.call(provider.name, "leaf", "a", on_status=lambda _q, u: heard.append(u))

        def no_thread(_self: Workers, _task: Any) -> None:
            raise RuntimeError("can't start new thread")

        monkeypatch.setattr(Workers, "submit", no_thread)  # say, too many hung callbacks
        provider.send_status(query.id, rr.Status.WARNING, "hot", timeout=5)

        assert [] == heard
        assert consumer.is_alive()
        assert [query.id] == [q.id for q in consumer.client_queries()]
    finally:
        monkeypatch.undo()
        consumer.stop()
        provider.stop()
