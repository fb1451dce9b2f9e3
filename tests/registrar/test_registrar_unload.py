"""Unloading (DESIGN rules 7-8)."""

from __future__ import annotations

import uuid
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def test_the_unload_callback_runs_only_when_the_last_consumer_id_is_released(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    first = consumer.call(provider.name, "leaf", "camera")
    second = consumer.call(provider.name, "leaf", "camera")

    consumer.unload(first.id)
    assert [] == leaf.unloads
    consumer.unload(second.id)

    assert [("camera", {"resource": "camera"})] == leaf.unloads


def test_unload_returns_after_the_unload_callback_ran(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    query = consumer.call(provider.name, "leaf", "camera")

    consumer.unload(query.id)

    assert leaf.unloaded.is_set()
    assert [] == provider.server_queries("leaf")
    assert [] == consumer.client_queries()


def test_a_resource_s_dependencies_are_released_before_its_own_unload_runs(
    make_registrar, serve, journal
):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf")
    serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response)
    query = consumer.call(agent.name, "composite", "x")

    consumer.unload(query.id)

    unloads = [server for server, what, _ in journal if what == "unload"]
    assert [f"{producer.name}/leaf", f"{agent.name}/composite"] == unloads


def test_unloading_an_unknown_id_raises_and_changes_nothing(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    consumer.call(provider.name, "leaf", "camera")
    before = (catalog_snapshot(provider), catalog_snapshot(consumer))

    with pytest.raises(rr.UnknownQueryError):
        consumer.unload(str(uuid.uuid4()))

    assert before == (catalog_snapshot(provider), catalog_snapshot(consumer))


def test_unloading_an_already_released_id_raises_and_changes_nothing(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    kept = consumer.call(provider.name, "leaf", "camera")
    released = consumer.call(provider.name, "leaf", "camera")
    consumer.unload(released.id)

    with pytest.raises(rr.UnknownQueryError):
        consumer.unload(released.id)

    assert [] == leaf.unloads
    assert [kept.id] == [q.id for q in provider.server_queries("leaf")]


def test_a_registrar_cannot_unload_another_registrar_s_query_id(make_registrar, serve):
    provider, owner, other = (make_registrar(n) for n in ("provider", "owner", "other"))
    serve(provider, "leaf")
    query = owner.call(provider.name, "leaf", "camera")

    with pytest.raises(rr.UnknownQueryError):
        other.unload(query.id)

    assert [query.id] == [q.id for q in provider.server_queries("leaf")]


def test_a_dependency_id_cannot_be_unloaded_directly(make_registrar, serve, shared):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    sub_ids = shared.list()
    serve(
        provider, "composite", lambda r: sub_ids.append(provider.call(provider.name, "leaf", r).id)
    )
    consumer.call(provider.name, "composite", "x")
    before = catalog_snapshot(provider)

    with pytest.raises(rr.UnknownQueryError):
        consumer.unload(sub_ids[0])

    assert before == catalog_snapshot(provider)


def test_an_unload_callback_that_raises_still_releases_the_resource(make_registrar, shared):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    loads = shared.list()

    def broken_unload(request, response):
        raise RuntimeError("could not stop it")

    provider.register_server("leaf", load=loads.append, unload=broken_unload)
    query = consumer.call(provider.name, "leaf", "camera")

    consumer.unload(query.id)

    assert [] == provider.server_queries("leaf")
    consumer.call(provider.name, "leaf", "camera")
    assert ["camera", "camera"] == loads


def test_a_resource_loads_again_after_it_was_unloaded(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    consumer.unload(consumer.call(provider.name, "leaf", "camera").id)

    consumer.call(provider.name, "leaf", "camera")

    assert ["camera", "camera"] == leaf.loads


def test_an_equal_call_during_its_unload_waits_and_loads_the_resource_afresh(
    make_registrar, gates, arrived, shared
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    gate, unloading = gates(), shared.event()
    journal = shared.list()

    def load(request):
        journal.append("load")
        return len(journal)

    def unload(request, response):
        unloading.set()
        assert gate.wait(10)
        journal.append("unload")

    provider.register_server("leaf", load=load, unload=unload)
    query = consumer.call(provider.name, "leaf", "camera")
    with ThreadPoolExecutor(2) as pool:
        unload_done = pool.submit(consumer.unload, query.id)
        assert unloading.wait(5)
        again_id = str(uuid.uuid4())
        again = pool.submit(consumer.call, provider.name, "leaf", "camera", query_id=again_id)
        assert arrived(provider, [again_id])
        gate.set()
        unload_done.result(timeout=10)
        response = again.result(timeout=10).response

    assert (["load", "unload", "load"], 3) == (journal, response)
    assert [again_id] == [q.id for q in provider.server_queries("leaf")]


# -- clauses a mutation audit found caught only by chance --------------------------


def test_a_resource_s_unload_runs_only_after_its_dependencies_finished_unloading(
    make_registrar, shared
):
    """Rule 7: "after the resource's own dependencies are released".

    Mutation caught: `_release_dependencies` sends the dependencies' `Unload`s and runs
    `then()` at once instead of waiting for their answers. The journal-order test in
    test_registrar_unload.py misses that about one run in five (the two unloads race); here
    the dependency's unload stays busy until the composite's unload has started (bounded by
    one second, which is what the correct order costs), so a composite unload that does not
    wait always sees an unfinished dependency.
    """
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    leaf_done, composite_started = shared.event(), shared.event()
    leaf_done_when_composite_started = shared.list()

    def leaf_unload(request, response):
        composite_started.wait(1.0)  # in the right order nothing sets it: time out, finish
        leaf_done.set()

    def composite_unload(request, response):
        leaf_done_when_composite_started.append(leaf_done.is_set())
        composite_started.set()

    producer.register_server("leaf", load=lambda r: r, unload=leaf_unload)
    agent.register_server(
        "composite",
        load=lambda r: agent.call(producer.name, "leaf", r).response,
        unload=composite_unload,
    )
    query = consumer.call(agent.name, "composite", "x")

    consumer.unload(query.id)

    assert [True] == leaf_done_when_composite_started


def test_the_first_consumer_leaving_does_not_take_the_resource_s_dependency(
    make_registrar, serve, inbox
):
    """Rule 7: "Dependencies belong to the resource, not to whichever consumer came first".

    Mutation caught: releasing the first consumer id of a resource that keeps other
    consumers also releases the resource's dependencies (without waiting for that). The
    test in test_registrar_dependencies.py then passes whenever the stray release lands
    after its check; here the provider is asked after it handled the release (its mailbox
    is in order), and the status path through the dependency is checked too.
    """
    provider, first, second = (make_registrar(n) for n in ("provider", "first", "second"))
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    box = inbox()
    q1 = first.call(provider.name, "composite", "x")
    q2 = second.call(provider.name, "composite", "x", on_status=box)
    (dependency,) = provider.server_queries("leaf")

    first.unload(q1.id)

    assert [dependency.id] == [q.id for q in provider.server_queries("leaf")]
    assert [dependency.id] == [q.id for q in provider.client_queries()]
    provider.send_status(dependency.id, rr.Status.WARNING, "still held", timeout=5)
    assert [(q2.id, rr.Status.WARNING)] == [(u.query_id, u.status) for _, u in box.updates]
    assert [] == leaf.unloads
    second.unload(q2.id)
    assert ["x"] == [request for request, _ in leaf.unloads]
