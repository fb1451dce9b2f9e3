"""Dependencies and cycles (DESIGN rules 5-7)."""

from __future__ import annotations

import contextvars
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def resource_id(registrar, server):
    (resource,) = [r for r in catalog_snapshot(registrar).resources if r.server == server]
    return resource.id


def parents(registrar):
    """query id -> parent resource id of every client record of `registrar`."""
    return {c.query.id: c.parent for c in catalog_snapshot(registrar).clients}


def test_a_call_inside_load_is_a_dependency_of_the_resource_being_loaded(
    make_registrar, serve, shared
):
    consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
    serve(producer, "leaf")
    sub_ids = shared.list()
    serve(agent, "composite", lambda r: sub_ids.append(agent.call(producer.name, "leaf", r).id))

    consumer.call(agent.name, "composite", "x")

    assert {sub_ids[0]: resource_id(agent, "composite")} == parents(agent)


def test_a_call_to_a_server_of_the_same_registrar_is_a_dependency(make_registrar, serve, shared):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    sub_ids = shared.list()
    serve(
        provider, "composite", lambda r: sub_ids.append(provider.call(provider.name, "leaf", r).id)
    )

    consumer.call(provider.name, "composite", "x")

    assert {sub_ids[0]: resource_id(provider, "composite")} == parents(provider)


def test_a_call_outside_any_load_is_a_top_level_query(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    query = consumer.call(provider.name, "leaf", "x")

    assert {query.id: None} == parents(consumer)


def test_a_call_from_a_thread_that_runs_in_the_loads_context_is_a_dependency(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    def composite(request):
        context = contextvars.copy_context()
        with ThreadPoolExecutor(1) as pool:
            return pool.submit(context.run, provider.call, provider.name, "leaf", request).result()

    serve(provider, "composite", composite)

    consumer.call(provider.name, "composite", "x")

    assert [resource_id(provider, "composite")] == list(parents(provider).values())


def test_a_call_made_by_another_registrar_inside_a_load_is_top_level_there(make_registrar, serve):
    provider, consumer, bystander = (make_registrar(n) for n in ("provider", "consumer", "by"))
    serve(bystander, "leaf")
    serve(provider, "composite", lambda r: bystander.call(bystander.name, "leaf", r).id)

    consumer.call(provider.name, "composite", "x")

    assert [None] == list(parents(bystander).values())
    assert {} == parents(provider)


def test_concurrent_loads_record_their_dependencies_on_their_own_resources(
    make_registrar, serve, shared
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")
    both_started = shared.barrier(2, timeout=5)

    def composite(request):
        both_started.wait()
        return provider.call(provider.name, "leaf", f"part-of-{request}").response

    serve(provider, "composite", composite)
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda r: consumer.call(provider.name, "composite", r), ["a", "b"]))

    snapshot = catalog_snapshot(provider)
    owner_of = {r.id: r.request for r in snapshot.resources}
    assert {"part-of-a": "a", "part-of-b": "b"} == {
        c.query.request: owner_of[c.parent] for c in snapshot.clients
    }


def test_dependencies_belong_to_the_resource_not_to_the_first_consumer(make_registrar, serve):
    provider, first, second = (make_registrar(n) for n in ("provider", "first", "second"))
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    q1 = first.call(provider.name, "composite", "x")
    q2 = second.call(provider.name, "composite", "x")

    first.unload(q1.id)

    assert [] == leaf.unloads, "the first consumer took the shared resource's dependency away"
    second.unload(q2.id)
    assert ["x"] == [request for request, _ in leaf.unloads]


def test_a_resource_keeps_its_dependencies_when_the_last_consumer_was_the_first(
    make_registrar, serve
):
    provider, first, second = (make_registrar(n) for n in ("provider", "first", "second"))
    leaf = serve(provider, "leaf")
    serve(provider, "composite", lambda r: provider.call(provider.name, "leaf", r).response)
    q1 = first.call(provider.name, "composite", "x")
    q2 = second.call(provider.name, "composite", "x")

    second.unload(q2.id)

    assert [] == leaf.unloads
    first.unload(q1.id)
    assert ["x"] == [request for request, _ in leaf.unloads]


def test_a_load_that_calls_its_own_server_with_an_equal_request_raises_a_cycle_error(
    make_registrar, serve
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "loop", lambda r: provider.call(provider.name, "loop", r, timeout=20))

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(provider.name, "loop", "x", timeout=20)


def test_a_cycle_across_registrars_raises_a_cycle_error_at_the_top_caller(make_registrar, serve):
    consumer, a, b = (make_registrar(n) for n in ("consumer", "a", "b"))
    serve(a, "x", lambda r: a.call(b.name, "y", r, timeout=20))
    serve(b, "y", lambda r: b.call(a.name, "x", r, timeout=20))

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(a.name, "x", "ping", timeout=20)

    for registrar in (a, b):
        snapshot = catalog_snapshot(registrar)
        assert ((), ()) == (snapshot.resources, snapshot.clients)


def test_a_call_made_through_another_registrar_inside_a_load_carries_the_chain(
    make_registrar, serve
):
    consumer, a, b = (make_registrar(n) for n in ("consumer", "a", "b"))
    serve(a, "x", lambda r: b.call(a.name, "x", r, timeout=20))

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(a.name, "x", "ping", timeout=20)

    assert ((), ()) == (catalog_snapshot(a).resources, catalog_snapshot(b).clients)


def test_runaway_recursion_raises_a_cycle_error_and_unloads_what_it_loaded(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def deeper(n):
        return provider.call(provider.name, "deeper", n + 1, timeout=30).response

    log = serve(provider, "deeper", deeper)

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(provider.name, "deeper", 0, timeout=30)

    assert len(log.loads) <= rr.MAX_DEPENDENCY_DEPTH
    assert () == catalog_snapshot(provider).resources


def test_a_cycle_error_caught_inside_a_load_is_reported_as_a_cycle_error(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")

    def wraps(request):
        try:
            provider.call(provider.name, "loop", request, timeout=20)
        except rr.DependencyCycleError as exc:
            raise RuntimeError("could not build the loop") from exc

    serve(provider, "loop", wraps)

    with pytest.raises(rr.DependencyCycleError):
        consumer.call(provider.name, "loop", "x", timeout=20)
